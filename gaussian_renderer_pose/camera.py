"""Camera matrices in the 3DGS layout, built differentiably from a world-to-camera pose.

Conventions (see docs/CONTRACTS.md): column-vector matrices, OpenCV camera axes (x right, y down,
z forward), pixel centres at integer coordinates with the image centre at ``(W - 1) / 2``.
The rasterizer takes the matrices TRANSPOSED (row-vector convention, as the 3DGS codebase):
``viewmatrix = w2c.T`` and ``projmatrix = (P @ w2c).T``; ``campos = -R^T t`` (camera centre).

``P`` is the 3DGS ``getProjectionMatrix`` (D3D-style depth: NDC z in [0, 1], ``w = z_cam``) with
an optional principal-point offset in ``P[0, 2]``, ``P[1, 2]``: with
``P[0, 2] = (2 cx + 1 - W) / W`` the rasterizer's ``ndc2Pix`` gives ``pixel_x = fx x / z + cx``.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional, Union

import torch

from ._validate import _positive_float

Number = Union[int, float]


class CameraMatrices(NamedTuple):
    """Matrices for `GaussianRasterizationSettings` (transposed 3DGS layout)."""

    viewmatrix: torch.Tensor  # [4, 4] = w2c.T
    projmatrix: torch.Tensor  # [4, 4] = (P @ w2c).T
    campos: torch.Tensor  # [3] camera centre in world
    tanfovx: float
    tanfovy: float


def projection_matrix(
    tanfovx: float,
    tanfovy: float,
    znear: float = 0.01,
    zfar: float = 100.0,
    cx_offset: float = 0.0,
    cy_offset: float = 0.0,
    *,
    dtype: torch.dtype = torch.float32,
    device: Optional[Union[str, torch.device]] = None,
) -> torch.Tensor:
    """3DGS ``getProjectionMatrix`` (NOT transposed), column-vector convention.

    ``P[0,0] = 1/tanfovx``, ``P[1,1] = 1/tanfovy``, ``P[0,2] = cx_offset``, ``P[1,2] = cy_offset``
    (NDC offsets of the principal point), ``P[2,2] = f/(f-n)``, ``P[2,3] = -f n/(f-n)``,
    ``P[3,2] = 1`` (so ``w = z_cam``).
    """
    tanfovx = _positive_float("tanfovx", tanfovx)
    tanfovy = _positive_float("tanfovy", tanfovy)
    znear = _positive_float("znear", znear)
    zfar = _positive_float("zfar", zfar)
    if zfar <= znear:
        raise ValueError(f"zfar must be greater than znear={znear}, got {zfar}")
    P = torch.zeros(4, 4, dtype=dtype, device=device)
    P[0, 0] = 1.0 / tanfovx
    P[1, 1] = 1.0 / tanfovy
    P[0, 2] = float(cx_offset)
    P[1, 2] = float(cy_offset)
    P[2, 2] = zfar / (zfar - znear)
    P[2, 3] = -(zfar * znear) / (zfar - znear)
    P[3, 2] = 1.0
    return P


def camera_matrices(
    w2c: torch.Tensor,
    fx: Number,
    fy: Number,
    width: int,
    height: int,
    cx: Optional[Number] = None,
    cy: Optional[Number] = None,
    znear: float = 0.01,
    zfar: float = 100.0,
) -> CameraMatrices:
    """Rasterizer matrices from a rigid ``w2c`` [4, 4]; differentiable w.r.t. ``w2c``.

    ``tanfovx = W / (2 fx)``, ``tanfovy = H / (2 fy)``. ``cx, cy`` (pixels, centre convention
    ``(W-1)/2``) default to the image centre; an off-centre principal point goes into
    ``P[0,2] = (2 cx + 1 - W)/W`` and ``P[1,2] = (2 cy + 1 - H)/H``. ``campos = -R^T t`` is computed
    from the rigid parts (no general inverse), so its gradient flows to ``w2c`` too.
    """
    if not isinstance(w2c, torch.Tensor):
        raise ValueError(f"w2c must be a torch.Tensor of shape [4, 4], got {type(w2c).__name__}")
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"w2c must have shape [4, 4], got {list(w2c.shape)}")
    if not w2c.is_floating_point():
        raise ValueError(f"w2c must be a floating-point tensor, got dtype {w2c.dtype}")
    fx = _positive_float("fx", fx)
    fy = _positive_float("fy", fy)
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValueError(f"{name} must be a positive int, got {v!r}")
    cx = (width - 1) / 2.0 if cx is None else float(cx)
    cy = (height - 1) / 2.0 if cy is None else float(cy)
    if not (math.isfinite(cx) and math.isfinite(cy)):
        raise ValueError(f"cx, cy must be finite, got cx={cx!r}, cy={cy!r}")
    tanfovx = width / (2.0 * fx)
    tanfovy = height / (2.0 * fy)
    P = projection_matrix(
        tanfovx,
        tanfovy,
        znear,
        zfar,
        (2.0 * cx + 1.0 - width) / width,
        (2.0 * cy + 1.0 - height) / height,
        dtype=w2c.dtype,
        device=w2c.device,
    )
    viewmatrix = w2c.transpose(0, 1)
    projmatrix = (P @ w2c).transpose(0, 1)
    R = w2c[:3, :3]
    t = w2c[:3, 3]
    campos = -(R.transpose(0, 1) @ t)
    return CameraMatrices(viewmatrix, projmatrix, campos, tanfovx, tanfovy)
