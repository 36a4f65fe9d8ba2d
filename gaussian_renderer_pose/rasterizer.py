"""Drop-in replacement for graphdeco-inria ``diff_gaussian_rasterization``, with pose gradients.

It follows upstream's late-2024 main (with antialiasing and inverse depth) and also gives
camera-pose gradients.

Conventions (docs/CONTRACTS.md, gaussian_renderer_pose/DESIGN.md):
- Matrices are TRANSPOSED (row-vector convention, as in the 3DGS codebase):
  ``viewmatrix = w2c.T`` (``world_view_transform``), ``projmatrix = (P @ w2c).T``
  (``full_proj_transform``), ``campos`` = camera centre in world. Build them with
  `gaussian_renderer_pose.camera_matrices` to get pose gradients w.r.t. ``w2c``.
- Pixel centres sit at integer coordinates, ``px = ((ndc_x + 1) W - 1) / 2``; with the 3DGS
  projection the principal point is the image centre ``(W - 1)/2``, and an off-centre one is
  carried by ``projmatrix`` (``P[0,2] = (2 cx + 1 - W)/W``, ``P[1,2] = (2 cy + 1 - H)/H``).

Numerics (identical in every backend):
1. ``t = hom(m) @ viewmatrix``; ``p_hom = hom(m) @ projmatrix``;
   ``ndc = p_hom.xyz / (p_hom.w + 1e-7)``; cull when ``t.z <= 0.2``.
2. ``Sigma = R S^2 R^T`` with ``S = scales * scale_modifier`` and R from the UNNORMALISED quaternion
   (w, x, y, z), or ``cov3D_precomp`` (xx, xy, xz, yy, yz, zz) as given.
   ``focal = W / (2 tanfovx)``, ``H / (2 tanfovy)``; ``tx = clamp(t.x/t.z, +-1.3 tanfovx) t.z``
   (same for y); ``J = [[fx/tz, 0, -fx tx/tz^2], [0, fy/tz, -fy ty/tz^2]]``;
   ``cov2D = J Rw Sigma Rw^T J^T`` with ``Rw = viewmatrix[:3,:3].T``.
3. ``det0 = det(cov2D)``; ``cov2D += 0.3 I``; with antialiasing the opacity is multiplied by
   ``sqrt(max(2.5e-5, det0 / det))``; cull when ``det == 0``; ``conic = inv(cov2D)``;
   ``radius = ceil(3 sqrt(mid + sqrt(max(0.1, mid^2 - det))))``; 16x16 tiles, tile rect
   ``[int((px - r)/16), int((px + r + 15)/16))`` clamped to the grid, cull when empty.
4. Colour: SH of degree 0..3 at ``dir = normalize(m - campos)`` plus 0.5, clamped at 0;
   or ``colors_precomp``.
5. Front-to-back blending by increasing ``t.z`` (ties by index) over the Gaussians whose tile
   rect contains the pixel's tile: ``power = -0.5 (c00 dx^2 + c11 dy^2) - c01 dx dy`` (skip if > 0),
   ``alpha = min(0.99, o exp(power))`` (skip if < 1/255), stop before the Gaussian that would
   bring ``T`` below 1e-4. ``color = sum c a T + T_final bg``, ``invdepth = sum a T / z``,
   ``depth_acc = sum a T z``, ``alpha = 1 - T_final``.

Gradients flow to every tensor input (means3D, means2D in NDC units as upstream, opacities, shs,
colors_precomp, scales, rotations, cov3D_precomp, bg, viewmatrix, projmatrix, campos).
"""
from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch
from torch import nn

from . import _dispatch
from ._validate import RasterizerInputError, is_absent
from ._validate import validate as validate_inputs


class GaussianRasterizationSettings(NamedTuple):
    """Upstream field order; `antialiasing` (upstream's last field) and `backend` have defaults."""

    image_height: int
    image_width: int
    tanfovx: float
    tanfovy: float
    bg: torch.Tensor
    scale_modifier: float
    viewmatrix: torch.Tensor
    projmatrix: torch.Tensor
    sh_degree: int
    campos: torch.Tensor
    prefiltered: bool
    debug: bool
    antialiasing: bool = False
    backend: str = "auto"


class RasterOutput(NamedTuple):
    """What `rasterize_gaussians` returns (upstream's three outputs plus depth and alpha)."""

    color: torch.Tensor  # [3, H, W]
    radii: torch.Tensor  # [P] int32
    invdepth: torch.Tensor  # [1, H, W] sum w / z
    depth: torch.Tensor  # [1, H, W] expected depth sum w z / alpha (0 where alpha <= 1e-6)
    alpha: torch.Tensor  # [1, H, W] 1 - T_final


def rasterize_gaussians(
    means3D: torch.Tensor,
    opacities: torch.Tensor,
    settings: GaussianRasterizationSettings,
    *,
    means2D: Optional[torch.Tensor] = None,
    shs: Optional[torch.Tensor] = None,
    colors_precomp: Optional[torch.Tensor] = None,
    scales: Optional[torch.Tensor] = None,
    rotations: Optional[torch.Tensor] = None,
    cov3D_precomp: Optional[torch.Tensor] = None,
    validate: bool = True,
    shs_rest: Optional[torch.Tensor] = None,
) -> RasterOutput:
    """Render; see the module docstring for conventions and numerics.

    Exactly one of ``shs`` / ``colors_precomp`` and exactly one of (``scales``, ``rotations``) /
    ``cov3D_precomp``; absent inputs may be None or empty tensors. Raises `RasterizerInputError`
    (a ValueError) on bad input, RuntimeError when an explicitly requested backend is unusable.

    ``validate=False`` skips the NaN/Inf scans of the per-Gaussian tensors (means3D, means2D,
    opacities, shs, colors_precomp, scales, rotations, cov3D_precomp), whose cost grows with the
    scene; use it only for tensors already checked (e.g. a scene rendered many times, checked
    once). Types, shapes, dtypes, devices, the settings and the camera tensors are still checked.

    ``shs_rest`` [P, M - 1, 3]: the SH coefficients after the first, with ``shs`` [P, 1, 3]
    holding the first; the image and gradients are those of their concatenation along dim 1.
    A fitter keeps the two as separate parameters (upstream's ``features_dc`` /
    ``features_rest``, with their own learning rates): the CPU kernel reads and writes them
    where they are instead of a copy of both every step (other backends concatenate them).
    """
    if not isinstance(settings, GaussianRasterizationSettings):
        raise RasterizerInputError(
            f"settings must be a GaussianRasterizationSettings, got {type(settings).__name__}"
        )
    args = validate_inputs(
        means3D,
        opacities,
        settings,
        means2D=means2D,
        shs=shs,
        colors_precomp=colors_precomp,
        scales=scales,
        rotations=rotations,
        cov3D_precomp=cov3D_precomp,
        check_finite=validate,
        shs_rest=shs_rest,
    )
    fn = _dispatch.select_backend(settings.backend, means3D.device, means3D.dtype)
    color, radii, invdepth, depth_acc, alpha = fn(
        args["means3D"],
        args["means2D"],
        args["opacities"],
        args["shs"],
        args["colors_precomp"],
        args["scales"],
        args["rotations"],
        args["cov3D_precomp"],
        args["bg"],
        args["viewmatrix"],
        args["projmatrix"],
        args["campos"],
        image_height=args["image_height"],
        image_width=args["image_width"],
        tanfovx=args["tanfovx"],
        tanfovy=args["tanfovy"],
        scale_modifier=args["scale_modifier"],
        sh_degree=args["sh_degree"],
        prefiltered=args["prefiltered"],
        antialiasing=args["antialiasing"],
        shs_rest=args["shs_rest"],
    )
    covered = alpha > 1e-6
    depth = torch.where(
        covered,
        depth_acc / torch.where(covered, alpha, torch.ones_like(alpha)),
        torch.zeros_like(alpha),
    )
    return RasterOutput(color, radii, invdepth, depth, alpha)


class GaussianRasterizer(nn.Module):
    """Upstream-compatible module.

    ``forward(...) -> (color [3,H,W], radii [P] int32, invdepth [1,H,W])``.
    """

    def __init__(self, raster_settings: GaussianRasterizationSettings):
        super().__init__()
        self.raster_settings = raster_settings

    def markVisible(self, positions: torch.Tensor) -> torch.Tensor:
        """bool [P]: view-space depth > 0.2 (upstream ``in_frustum``; no x/y test). No gradient."""
        with torch.no_grad():
            if (
                not isinstance(positions, torch.Tensor)
                or positions.dim() != 2
                or positions.shape[1] != 3
            ):
                got = (
                    list(positions.shape)
                    if isinstance(positions, torch.Tensor)
                    else type(positions).__name__
                )
                raise RasterizerInputError(f"positions must have shape [P, 3], got {got}")
            view = self.raster_settings.viewmatrix.to(positions)
            z = positions @ view[:3, 2] + view[3, 2]
            return z > 0.2

    def forward(
        self,
        means3D: torch.Tensor,
        means2D: torch.Tensor,
        opacities: torch.Tensor,
        shs: Optional[torch.Tensor] = None,
        colors_precomp: Optional[torch.Tensor] = None,
        scales: Optional[torch.Tensor] = None,
        rotations: Optional[torch.Tensor] = None,
        cov3D_precomp: Optional[torch.Tensor] = None,
    ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Render with upstream's argument order and checks (see `rasterize_gaussians`).

        Returns:
            (color [3, H, W], radii [P] int32, invdepth [1, H, W]).

        Raises:
            RasterizerInputError: not exactly one of shs / colors_precomp, or of
                (scales, rotations) / cov3D_precomp, or any check of `rasterize_gaussians`.
        """
        if is_absent(shs) == is_absent(colors_precomp):
            raise RasterizerInputError(
                "Please provide exactly one of either SHs (shs) or precomputed colors "
                "(colors_precomp)!"
            )
        if (is_absent(scales) or is_absent(rotations)) == is_absent(cov3D_precomp):
            raise RasterizerInputError(
                "Please provide exactly one of either scale/rotation pair (scales, rotations) "
                "or precomputed 3D covariance (cov3D_precomp)!"
            )
        out = rasterize_gaussians(
            means3D,
            opacities,
            self.raster_settings,
            means2D=means2D,
            shs=shs,
            colors_precomp=colors_precomp,
            scales=scales,
            rotations=rotations,
            cov3D_precomp=cov3D_precomp,
        )
        return out.color, out.radii, out.invdepth
