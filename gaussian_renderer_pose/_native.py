"""Native (compiled) backend: an autograd.Function around the ops `torch.ops.grp.*` (`_ops.py`).

`rasterize_gaussians_native` follows the internal backend contract of docs/CONTRACTS.md and has the
same signature as `gaussian_renderer_pose.reference.rasterize_gaussians_reference`. The forward and
the complete backward (every tensor input, including viewmatrix / projmatrix / campos) run in C++
(csrc/cpu/rasterize_cpu.cpp) for CPU tensors, or in CUDA (csrc/cuda/, present when `_C.WITH_CUDA`)
for CUDA tensors, chosen by the dispatcher; the camera gradient is only computed when one of the
camera tensors requires grad, and the Gaussians' gradients only when one of the Gaussian tensors
(means3D .. cov3D_precomp) does (a localizer's fixed scene: the backward then does only the camera
work, and the camera gradient is the same bits). Arguments are assumed validated
(`_validate.py`); C++ TORCH_CHECKs are a second line of defence and raise RuntimeError.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from . import _backend

__all__ = ["rasterize_gaussians_native", "mark_visible"]


_ops_module = None


def _native_ops():
    """The `_ops` module (loads `_C` on first use; NativeUnavailable when it is not built)."""
    global _ops_module
    if _ops_module is None:
        from . import _ops

        _ops_module = _ops
    return _ops_module


def _f32c(t: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
    return None if t is None else t.contiguous()


class _RasterizeGaussians(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means3D,  # [P, 3]
        means2D,  # [P, 3] or None (gradient holder only)
        opacities,  # [P, 1]
        shs,  # [P, M, 3] or None ([P, 1, 3] with shs_rest)
        colors_precomp,  # [P, 3] or None
        scales,  # [P, 3] or None
        rotations,  # [P, 4] or None
        cov3D_precomp,  # [P, 6] or None
        bg,  # [3]
        viewmatrix,  # [4, 4]
        projmatrix,  # [4, 4]
        campos,  # [3]
        shs_rest,  # [P, M - 1, 3] or None
        settings,  # tuple (H, W, tanfovx, tanfovy, scale_modifier, sh_degree, prefiltered, aa)
    ):
        tensors = [
            _f32c(t) for t in (means3D, opacities, shs, colors_precomp, scales, rotations,
                               cov3D_precomp, bg, viewmatrix, projmatrix, campos, shs_rest)
        ]
        # The op's arguments are the tensors, the settings, then shs_rest (csrc/ops.h
        # GRP_RASTER_INPUTS).
        outs = _native_ops().rasterize_forward(*tensors[:-1], *settings, tensors[-1])
        color, invdepth, depth_acc, alpha, *state = outs
        radii = state[0]
        ctx.settings = settings
        ctx.has = [t is not None for t in tensors]
        ctx.save_for_backward(*[t for t in tensors if t is not None], *state)
        ctx.mark_non_differentiable(radii)
        return color, radii, invdepth, depth_acc, alpha

    @staticmethod
    def backward(ctx, grad_color, _grad_radii, grad_invdepth, grad_depth_acc, grad_alpha):
        H, W = ctx.settings[:2]
        saved = list(ctx.saved_tensors)
        tensors = [saved.pop(0) if present else None for present in ctx.has]
        state = saved  # radii, geom, binning, tile_ranges, offsets, final_T, last_contrib
        device = tensors[0].device  # means3D: every saved tensor lives there
        need = ctx.needs_input_grad
        want_camera = bool(need[9] or need[10] or need[11])
        # means3D .. cov3D_precomp, shs_rest (bg's gradient is always made)
        want_gaussians = any(need[:8]) or bool(need[12])

        def g(t, shape):
            if t is None:
                return torch.zeros(shape, dtype=torch.float32, device=device)
            return t.contiguous()

        grads = _native_ops().rasterize_backward(
            *tensors[:-1], *ctx.settings, tensors[-1], *state,
            g(grad_color, (3, H, W)), g(grad_invdepth, (1, H, W)), g(grad_depth_acc, (1, H, W)),
            g(grad_alpha, (1, H, W)), want_camera, want_gaussians,
        )
        # grads: means3D, means2D, opacities, shs, colors_precomp, scales, rotations,
        # cov3D_precomp, bg, viewmatrix, projmatrix, campos, shs_rest (the order of forward's
        # inputs); None where not computed.
        out = [o if need[i] else None for i, o in enumerate(grads)]
        return (*out, None)


def rasterize_gaussians_native(
    means3D: torch.Tensor,  # [P, 3] world
    means2D: Optional[torch.Tensor],  # [P, 3] gradient holder (d/d NDC xy)
    opacities: torch.Tensor,  # [P, 1]
    shs: Optional[torch.Tensor],  # [P, M, 3]
    colors_precomp: Optional[torch.Tensor],  # [P, 3]
    scales: Optional[torch.Tensor],  # [P, 3]
    rotations: Optional[torch.Tensor],  # [P, 4] (w, x, y, z), unnormalised
    cov3D_precomp: Optional[torch.Tensor],  # [P, 6]
    bg: torch.Tensor,  # [3]
    viewmatrix: torch.Tensor,  # [4, 4] w2c^T
    projmatrix: torch.Tensor,  # [4, 4] (P w2c)^T
    campos: torch.Tensor,  # [3] world
    *,
    image_height: int,
    image_width: int,
    tanfovx: float,
    tanfovy: float,
    scale_modifier: float,
    sh_degree: int,
    prefiltered: bool = False,
    antialiasing: bool = False,
    shs_rest: Optional[torch.Tensor] = None,  # [P, M - 1, 3]; shs is then [P, 1, 3]
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Native twin of `reference.rasterize_gaussians_reference`.

    -> (color [3,H,W], radii [P] int32, invdepth [1,H,W], depth_acc [1,H,W], alpha [1,H,W]).
    """
    kind = means3D.device.type
    if kind not in ("cpu", "cuda"):
        raise _backend.NativeUnavailable(f"there is no native backend for device {kind!r}")
    if kind == "cuda":
        ok, why = _backend.native_status("cuda")
        if not ok:
            raise _backend.NativeUnavailable(why)
        if shs_rest is not None:
            # The CPU kernel reads the two SH tensors in place; the CUDA one, not yet run on a
            # GPU with them, gets their concatenation.
            shs, shs_rest = torch.cat([shs, shs_rest], dim=1), None
    settings = (
        int(image_height), int(image_width), float(tanfovx), float(tanfovy), float(scale_modifier),
        int(sh_degree), bool(prefiltered), bool(antialiasing),
    )
    return _RasterizeGaussians.apply(
        means3D, means2D, opacities, shs, colors_precomp, scales, rotations, cov3D_precomp, bg,
        viewmatrix, projmatrix, campos, shs_rest, settings,
    )


def mark_visible(
    means3D: torch.Tensor, viewmatrix: torch.Tensor, projmatrix: torch.Tensor
) -> torch.Tensor:
    """bool [P]: view-space z > 0.2 (upstream markVisible)."""
    ops = _native_ops()
    if means3D.device.type == "cuda":
        ok, why = _backend.native_status("cuda")
        if not ok:
            raise _backend.NativeUnavailable(why)
    with torch.no_grad():
        return ops.mark_visible(
            means3D.detach().contiguous(), viewmatrix.detach().contiguous(),
            projmatrix.detach().contiguous(),
        )
