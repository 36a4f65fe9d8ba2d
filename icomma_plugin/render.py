"""The one place the plugin calls the rasterizer (`gaussian_renderer_pose`).

Mirrors upstream ``gaussian_renderer/__init__.py::render`` (activated opacity, scales and
normalised rotations, SH evaluated by the rasterizer, ``prefiltered=False``) but takes the camera
as :class:`~icomma_plugin.camera.Intrinsics` plus a differentiable world-to-camera ``w2c``
(OpenCV axes, column vectors; docs/CONTRACTS.md). The pose gradient flows
``loss -> viewmatrix/projmatrix/campos -> camera_matrices -> w2c``.

A scene rendered many times from different poses (a localization) is prepared once with
:func:`prepare_scene`: the activations, the SH concatenation and, at SH degree 0, the colours
(view independent there) are computed once, the tensors are checked for NaN/Inf once, and each
render then skips the rasterizer's per-call scans. The image, depth, alpha and pose gradient are
bit-identical to ``render(model, ...)`` (tests/icomma_plugin/test_render.py); timings in
docs/SPEED.md.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import torch

import gaussian_renderer_pose as grp

from .camera import Intrinsics
from .gaussians import SH_C0, GaussianModel, GaussianTensors, num_sh_coeffs

__all__ = ["PreparedScene", "model_for_backend", "prepare_scene", "render"]


@dataclass(frozen=True)
class PreparedScene(GaussianTensors):
    """The rasterizer inputs of a fixed :class:`GaussianModel`, computed once.

    Made by :func:`prepare_scene`; all contiguous, detached, finite, on the model's dtype and
    device.

    Attributes:
        means: ``[P, 3]``.
        opacities: ``[P, 1]`` (sigmoid).
        scales: ``[P, 3]`` (exp).
        rotations: ``[P, 4]`` (normalised).
        shs: ``[P, (D+1)^2, 3]`` at ``sh_degree`` D >= 1, else None.
        colors: ``[P, 3]`` at D = 0 (``max(SH_C0 f_dc + 0.5, 0)``, the rasterizer's own clamp),
            else None.
        sh_degree: D.
    """

    means: torch.Tensor
    opacities: torch.Tensor
    scales: torch.Tensor
    rotations: torch.Tensor
    shs: Optional[torch.Tensor]
    colors: Optional[torch.Tensor]
    sh_degree: int


def _check_sh_degree(sh_degree, model_degree: int) -> int:
    if sh_degree is None:
        return model_degree
    if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) \
            or not 0 <= sh_degree <= model_degree:
        raise ValueError(f"sh_degree must be an int in [0, {model_degree}] (the model's), "
                         f"got {sh_degree!r}")
    return sh_degree


def _finite(name: str, t: torch.Tensor) -> torch.Tensor:
    bad = int((~torch.isfinite(t)).sum())
    if bad:
        entries = "entry" if bad == 1 else "entries"
        raise ValueError(f"{name} must be finite, got {bad} NaN/Inf {entries}")
    return t.contiguous()


def prepare_scene(model: GaussianModel, sh_degree: Optional[int] = None) -> PreparedScene:
    """The rasterizer inputs of ``model``, computed and checked once, for many renders.

    The scene is frozen: no gradient reaches the model's parameters through a prepared scene
    (pose gradients flow as with ``render(model, ...)``). Prepare again after changing the model.

    Args:
        model: the Gaussians (raw parameters).
        sh_degree: SH degree to evaluate (<= ``model.sh_degree``); None = the model's. At 0 the
            colours are computed here, as the rasterizer would (``max(SH_C0 f_dc + 0.5, 0)``).

    Raises:
        ValueError: on a non-GaussianModel, a bad SH degree, or parameters whose activations
            are not finite (the message names the model field).
    """
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    degree = _check_sh_degree(sh_degree, model.sh_degree)
    with torch.no_grad():
        means = _finite("model.means", model.means)
        opacities = _finite("model.opacity_logit (after sigmoid)", model.opacities())
        scales = _finite("model.scale_log (after exp)", model.scales())
        rotations = _finite("model.quat (normalised)", model.rotations())
        if degree == 0:
            # The rasterizer's SH colour at degree 0 (gaussian_renderer_pose DESIGN step 4), the
            # same float operations in the same order: SH_C0 * f_dc + 0.5, clamped at 0.
            dc = _finite("model.sh_dc", model.sh_dc[:, 0])
            shs, colors = None, torch.clamp_min(SH_C0 * dc + 0.5, 0.0).contiguous()
        else:
            rest = model.sh_rest[:, : num_sh_coeffs(degree) - 1]
            shs = _finite("model.sh_dc / model.sh_rest", torch.cat([model.sh_dc, rest], dim=1))
            colors = None
    return PreparedScene(*(None if t is None else t.detach()
                           for t in (means, opacities, scales, rotations, shs, colors)), degree)


def model_for_backend(model: GaussianModel, backend: str) -> GaussianModel:
    """``model`` where ``backend`` renders it: moved to the GPU for ``"cuda"``, else as it is.

    The rasterizer renders the tensors where they are and refuses a backend of another device;
    callers that take a backend name (the Localizer, the fitter's evaluation, the demo scene)
    move a CPU model here, once.
    """
    if backend == "cuda" and model.means.device.type != "cuda":
        return model.to("cuda")
    return model


def render(
    model: Union[GaussianModel, PreparedScene],
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
        model: Gaussians (raw parameters), or a :class:`PreparedScene` of them (faster for many
            renders; no gradient to the Gaussians); their dtype/device decide the computation's.
        intrinsics: pinhole camera; the image is ``intrinsics.height x intrinsics.width``.
        w2c: ``[4, 4]`` rigid world-to-camera; may require grad. Cast to the model's
            dtype/device (differentiably).
        bg: ``[3]`` background colour in [0, 1].
        backend: rasterizer backend (``"auto"``, ``"reference"``, ``"cpu"``, ``"cuda"``).
        sh_degree: SH degree to evaluate (<= ``model.sh_degree``); None = the model's. A prepared
            scene renders at the degree it was prepared for (None or that degree).
        antialiasing: upstream 2024 antialiasing (opacity compensation).
        scale_modifier: multiplies every scale (upstream ``scaling_modifier``).

    Returns:
        ``RasterOutput(color [3,H,W], radii [P] int32, invdepth [1,H,W], depth [1,H,W],
        alpha [1,H,W])``.

    Raises:
        ValueError: on bad argument types/shapes or an SH degree above the model's.
    """
    prepared = isinstance(model, PreparedScene)
    if not prepared and not isinstance(model, GaussianModel):
        raise ValueError("model must be a GaussianModel or a PreparedScene, got "
                         f"{type(model).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise ValueError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not isinstance(w2c, torch.Tensor) or tuple(w2c.shape) != (4, 4):
        got = list(w2c.shape) if isinstance(w2c, torch.Tensor) else type(w2c).__name__
        raise ValueError(f"w2c must be a torch.Tensor of shape [4, 4], got {got}")
    if not isinstance(bg, torch.Tensor) or tuple(bg.shape) != (3,):
        got = list(bg.shape) if isinstance(bg, torch.Tensor) else type(bg).__name__
        raise ValueError(f"bg must be a torch.Tensor of shape [3], got {got}")
    if prepared and sh_degree not in (None, model.sh_degree):
        raise ValueError(f"sh_degree must be None or {model.sh_degree} (the degree the scene was "
                         f"prepared for), got {sh_degree!r}")
    sh_degree = _check_sh_degree(sh_degree, model.sh_degree)

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
    if prepared:
        return grp.rasterize_gaussians(
            model.means, model.opacities, settings, shs=model.shs, colors_precomp=model.colors,
            scales=model.scales, rotations=model.rotations, validate=False,
        )
    return grp.rasterize_gaussians(
        model.means,
        model.opacities(),
        settings,
        shs=model.sh_dc,
        shs_rest=model.sh_rest,
        scales=model.scales(),
        rotations=model.rotations(),
    )
