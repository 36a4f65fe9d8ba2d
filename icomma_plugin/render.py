"""The one place the plugin calls the rasterizer (`gaussian_renderer_pose`).

Mirrors upstream ``gaussian_renderer/__init__.py::render`` (activated opacity, scales and
normalised rotations, SH evaluated by the rasterizer, ``prefiltered=False``) but takes the camera
as :class:`~icomma_plugin.camera.Intrinsics` plus a differentiable world-to-camera ``w2c``
(OpenCV axes, column vectors; docs/CONTRACTS.md). The pose gradient flows
``loss -> viewmatrix/projmatrix/campos -> camera_matrices -> w2c``.
"""
from __future__ import annotations

from typing import Optional

import torch

import gaussian_renderer_pose as grp

from .camera import Intrinsics
from .gaussians import GaussianModel

__all__ = ["render"]


def render(
    model: GaussianModel,
    intrinsics: Intrinsics,
    w2c: torch.Tensor,
    bg: torch.Tensor,
    backend: str = "auto",
    sh_degree: Optional[int] = None,
    antialiasing: bool = False,
    scale_modifier: float = 1.0,
) -> "grp.RasterOutput":
    """Render ``model`` from pose ``w2c``.

    Args:
        model: Gaussians (raw parameters); their dtype/device decide the computation's.
        intrinsics: pinhole camera; the image is ``intrinsics.height x intrinsics.width``.
        w2c: ``[4, 4]`` rigid world-to-camera; may require grad. Cast to the model's
            dtype/device (differentiably).
        bg: ``[3]`` background colour in [0, 1].
        backend: rasterizer backend (``"auto"``, ``"reference"``, ``"cpu"``, ``"cuda"``).
        sh_degree: SH degree to evaluate (<= ``model.sh_degree``); None = the model's.
        antialiasing: upstream 2024 antialiasing (opacity compensation).
        scale_modifier: multiplies every scale (upstream ``scaling_modifier``).

    Returns:
        ``RasterOutput(color [3,H,W], radii [P] int32, invdepth [1,H,W], depth [1,H,W],
        alpha [1,H,W])``.

    Raises:
        ValueError: on bad argument types/shapes or an SH degree above the model's.
    """
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise ValueError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not isinstance(w2c, torch.Tensor) or tuple(w2c.shape) != (4, 4):
        got = list(w2c.shape) if isinstance(w2c, torch.Tensor) else type(w2c).__name__
        raise ValueError(f"w2c must be a torch.Tensor of shape [4, 4], got {got}")
    if not isinstance(bg, torch.Tensor) or tuple(bg.shape) != (3,):
        got = list(bg.shape) if isinstance(bg, torch.Tensor) else type(bg).__name__
        raise ValueError(f"bg must be a torch.Tensor of shape [3], got {got}")
    if sh_degree is None:
        sh_degree = model.sh_degree
    if not isinstance(sh_degree, int) or not 0 <= sh_degree <= model.sh_degree:
        raise ValueError(f"sh_degree must be an int in [0, {model.sh_degree}] (the model's), "
                         f"got {sh_degree!r}")

    dtype, device = model.dtype, model.device
    w2c = w2c.to(dtype=dtype, device=device)
    mats = grp.camera_matrices(
        w2c, intrinsics.fx, intrinsics.fy, intrinsics.width, intrinsics.height,
        intrinsics.cx, intrinsics.cy,
    )
    settings = grp.GaussianRasterizationSettings(
        image_height=intrinsics.height,
        image_width=intrinsics.width,
        tanfovx=mats.tanfovx,
        tanfovy=mats.tanfovy,
        bg=bg.to(dtype=dtype, device=device),
        scale_modifier=float(scale_modifier),
        viewmatrix=mats.viewmatrix,
        projmatrix=mats.projmatrix,
        sh_degree=sh_degree,
        campos=mats.campos,
        prefiltered=False,
        debug=False,
        antialiasing=bool(antialiasing),
        backend=backend,
    )
    return grp.rasterize_gaussians(
        model.means,
        model.opacities(),
        settings,
        shs=model.shs(),
        scales=model.scales(),
        rotations=model.rotations(),
    )
