"""The native ops `torch.ops.grp.*` and their fake (shape-only) kernels.

The ops are defined by the compiled `_C` (schemas generated from the argument lists of
csrc/ops.h; CPU and CUDA kernels): `rasterize_forward`, `rasterize_backward`, `mark_visible`.
Importing this module loads `_C` (raising `_backend.NativeUnavailable` when it is not built) and
registers the fake kernels that FakeTensor / torch.compile / `torch.library.opcheck` use; `_C`
names this module as their home, so torch imports it when it needs them.
"""
from __future__ import annotations

import math
from typing import Any, Dict, Tuple

import torch

from . import _backend

__all__ = ["rasterize_forward", "rasterize_backward", "mark_visible"]

_C = _backend.load_native()

rasterize_forward = torch.ops.grp.rasterize_forward.default
rasterize_backward = torch.ops.grp.rasterize_backward.default
mark_visible = torch.ops.grp.mark_visible.default


def _bind(op: torch._ops.OpOverload, args: Tuple[Any, ...],
          kwargs: Dict[str, Any]) -> Dict[str, Any]:
    """The op's arguments by their schema names."""
    named = {a.name: v for a, v in zip(op._schema.arguments, args)}
    named.update(kwargs)
    return named


def _images(a: Dict[str, Any]) -> Tuple[torch.Tensor, ...]:
    """color, invdepth, depth_acc, alpha (fake)."""
    m, H, W = a["means3D"], a["image_height"], a["image_width"]
    return m.new_empty(3, H, W), m.new_empty(1, H, W), m.new_empty(1, H, W), m.new_empty(1, H, W)


@torch.library.register_fake("grp::rasterize_forward")
def _rasterize_forward_fake(*args, **kwargs):
    a = _bind(rasterize_forward, args, kwargs)
    m, H, W = a["means3D"], a["image_height"], a["image_width"]
    P = m.shape[0]
    tiles = math.ceil(H / _C.TILE_SIZE) * math.ceil(W / _C.TILE_SIZE)
    num_rendered = torch.library.get_ctx().new_dynamic_size()  # (tile, Gaussian) pairs
    i32, i64 = torch.int32, torch.int64
    return (
        *_images(a),
        m.new_empty(P, dtype=i32),  # radii
        m.new_empty(P, _C.GEOM_STRIDE),  # geom
        m.new_empty(num_rendered, 2, dtype=i32),  # binning
        m.new_empty(tiles + 1, dtype=i32),  # tile_ranges
        m.new_empty(P + 1, dtype=i64),  # offsets
        m.new_empty(H, W),  # final_T
        m.new_empty(H, W, dtype=i32),  # last_contrib
    )


@torch.library.register_fake("grp::rasterize_backward")
def _rasterize_backward_fake(*args, **kwargs):
    a = _bind(rasterize_backward, args, kwargs)
    m = a["means3D"]
    P = m.shape[0]

    def like(name):
        return m.new_empty(a[name].shape)

    # As the kernels: one of colors_precomp / shs, one of cov3D_precomp / (scales, rotations); the
    # Gaussians' gradients only with compute_gaussian_grads, the camera's with compute_camera_grad.
    colors = a["colors_precomp"] is not None
    cov = a["cov3D_precomp"] is not None
    cam = a["compute_camera_grad"]
    gauss = a["compute_gaussian_grads"]
    return (
        like("means3D") if gauss else None,
        m.new_empty(P, 3) if gauss else None,  # means2D
        like("opacities") if gauss else None,
        like("shs") if gauss and not colors else None,
        like("colors_precomp") if gauss and colors else None,
        like("scales") if gauss and not cov else None,
        like("rotations") if gauss and not cov else None,
        like("cov3D_precomp") if gauss and cov else None,
        like("bg"),
        like("viewmatrix") if cam else None,
        like("projmatrix") if cam else None,
        like("campos") if cam else None,
        like("shs_rest") if gauss and a["shs_rest"] is not None else None,
    )


@torch.library.register_fake("grp::mark_visible")
def _mark_visible_fake(*args, **kwargs):
    a = _bind(mark_visible, args, kwargs)
    m = a["means3D"]
    return m.new_empty(m.shape[0], dtype=torch.bool)
