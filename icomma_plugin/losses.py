"""iComMa losses: photometric comparison and keypoint matching (normalised image coordinates).

Keypoints are pixel positions ``(x, y)`` in the 3DGS convention (pixel centres at integers,
docs/CONTRACTS.md). They are normalised per image as ``((x + 0.5) / W, (y + 0.5) / H)``, i.e. the
image spans [0, 1] whatever its size: iComMa stretches both images to 640x480 and divides by
640/480, which is the same up to the half-pixel centre offset; for two images of the same size
the offset cancels and the loss equals iComMa's ``mean((dx/W)^2 + (dy/H)^2)`` exactly.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from .camera import Intrinsics

__all__ = ["compare_loss", "match_loss", "reprojection_match_loss"]


def _check(t, name: str, shape_desc: str, ndim: int, last: Optional[int] = None) -> None:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor {shape_desc}, got {type(t).__name__}")
    if t.ndim != ndim or (last is not None and t.shape[-1] != last):
        raise ValueError(f"{name} must have shape {shape_desc}, got {list(t.shape)}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {t.dtype}")


def _check_size(size, name: str):
    if not (isinstance(size, Sequence) and len(size) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0
                    for v in size)):
        raise ValueError(f"{name} must be (width, height) with positive sizes, got {size!r}")
    return float(size[0]), float(size[1])


def compare_loss(
    render: torch.Tensor, query: torch.Tensor, mask: Optional[torch.Tensor] = None
) -> torch.Tensor:
    """Photometric loss (iComMa ``MSELoss()(rendering, query)``).

    Args:
        render: ``[C, H, W]`` rendered image (usually C = 3), differentiable.
        query: ``[C, H, W]`` query image, same shape.
        mask: optional ``[1, H, W]`` weights in [0, 1].

    Returns:
        0-dim tensor: ``mean((render - query)^2)``; with a mask the weighted mean
        ``sum(mask * d^2) / (C * sum(mask))`` over masked pixels (0 if the mask is all zero).

    Raises:
        ValueError: on shape/dtype mismatches.
    """
    _check(render, "render", "[C, H, W]", 3)
    _check(query, "query", "[C, H, W]", 3)
    if render.shape != query.shape:
        raise ValueError(f"query must have the shape of render {list(render.shape)}, "
                         f"got {list(query.shape)}")
    d2 = (render - query.to(render.dtype)) ** 2
    if mask is None:
        return d2.mean()
    _check(mask, "mask", f"[1, {render.shape[1]}, {render.shape[2]}]", 3)
    if mask.shape != (1, *render.shape[1:]):
        raise ValueError(f"mask must have shape [1, {render.shape[1]}, {render.shape[2]}], "
                         f"got {list(mask.shape)}")
    w = mask.to(render.dtype)
    denom = (w.sum() * render.shape[0]).clamp_min(torch.finfo(render.dtype).tiny)
    return (w * d2).sum() / denom


def match_loss(
    kpts_render: torch.Tensor,
    kpts_query: torch.Tensor,
    size_render: Sequence[float],
    size_query: Sequence[float],
) -> torch.Tensor:
    """iComMa matching loss: mean over matches of the squared distance in normalised coordinates.

    ``L = mean_i [ (xr_i'/Wr - xq_i'/Wq)^2 + (yr_i'/Hr - yq_i'/Hq)^2 ]`` with ``x' = x + 0.5``
    (see the module docstring); each keypoint is normalised by its own image's size.

    Args:
        kpts_render: ``[N, 2]`` pixel (x, y) in the rendered image (may carry gradients).
        kpts_query: ``[N, 2]`` matching pixel (x, y) in the query image.
        size_render: ``(W, H)`` of the rendered image.
        size_query: ``(W, H)`` of the query image.

    Returns:
        0-dim tensor.

    Raises:
        ValueError: on bad shapes, N mismatch, N == 0 (callers enforce a minimum match count
            first, as iComMa's ``min_matching_points``) or bad sizes.
    """
    _check(kpts_render, "kpts_render", "[N, 2]", 2, 2)
    _check(kpts_query, "kpts_query", "[N, 2]", 2, 2)
    if kpts_render.shape[0] != kpts_query.shape[0]:
        raise ValueError(f"kpts_render and kpts_query must have the same N, got "
                         f"{kpts_render.shape[0]} and {kpts_query.shape[0]}")
    if kpts_render.shape[0] == 0:
        raise ValueError("match_loss needs at least one match, got N = 0")
    Wr, Hr = _check_size(size_render, "size_render")
    Wq, Hq = _check_size(size_query, "size_query")
    scale_r = kpts_render.new_tensor([1.0 / Wr, 1.0 / Hr])
    scale_q = kpts_render.new_tensor([1.0 / Wq, 1.0 / Hq])
    nr = (kpts_render + 0.5) * scale_r
    nq = (kpts_query.to(kpts_render) + 0.5) * scale_q
    return ((nr - nq) ** 2).sum(-1).mean()


def reprojection_match_loss(
    points_world: torch.Tensor,
    kpts_query: torch.Tensor,
    w2c: torch.Tensor,
    intrinsics_query: Intrinsics,
) -> Optional[torch.Tensor]:
    """Matching loss with render-side keypoints lifted to 3D and reprojected into the query pose.

    Projects ``points_world`` with ``w2c`` (OpenCV axes) and the query intrinsics
    (``u = fx x/z + cx``, pixel centres at integers) and compares with ``kpts_query`` like
    :func:`match_loss` (both in the query image, so ``((u - x)/W)^2 + ((v - y)/H)^2``). Points with
    camera depth ``z <= 1e-6`` are excluded.

    Args:
        points_world: ``[N, 3]`` world points.
        kpts_query: ``[N, 2]`` pixel (x, y) in the query image.
        w2c: ``[4, 4]`` world-to-camera of the query; gradients flow to it (and to the points).
        intrinsics_query: query camera.

    Returns:
        0-dim tensor in ``w2c``'s dtype, or None if no point lies in front of the camera.

    Raises:
        ValueError: on bad shapes or a non-Intrinsics ``intrinsics_query``.
    """
    _check(points_world, "points_world", "[N, 3]", 2, 3)
    _check(kpts_query, "kpts_query", "[N, 2]", 2, 2)
    _check(w2c, "w2c", "[4, 4]", 2)
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"w2c must have shape [4, 4], got {list(w2c.shape)}")
    if points_world.shape[0] != kpts_query.shape[0]:
        raise ValueError(f"points_world and kpts_query must have the same N, got "
                         f"{points_world.shape[0]} and {kpts_query.shape[0]}")
    if not isinstance(intrinsics_query, Intrinsics):
        raise ValueError(f"intrinsics_query must be an Intrinsics, got "
                         f"{type(intrinsics_query).__name__}")
    k = intrinsics_query
    pts = points_world.to(dtype=w2c.dtype, device=w2c.device)
    kq = kpts_query.to(dtype=w2c.dtype, device=w2c.device)
    x_cam = pts @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
    z = x_cam[:, 2]
    valid = z > 1e-6
    if not bool(valid.any()):
        return None
    x_cam, kq = x_cam[valid], kq[valid]
    z = x_cam[:, 2]
    u = k.fx * x_cam[:, 0] / z + k.cx_px
    v = k.fy * x_cam[:, 1] / z + k.cy_px
    du = (u - kq[:, 0]) / k.width
    dv = (v - kq[:, 1]) / k.height
    return (du * du + dv * dv).mean()
