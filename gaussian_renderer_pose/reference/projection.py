"""Per-Gaussian preprocessing (upstream ``preprocessCUDA``).

Projection, culling, 3D and 2D covariances, conic, radius, tile rect. Pure PyTorch; autograd
gives every gradient.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

BLOCK = 16  # tile side (upstream BLOCK_X = BLOCK_Y = 16)
NEAR_CULL = 0.2  # in_frustum: cull when view z <= 0.2
LOWPASS = 0.3  # h_var added to the cov2D diagonal
AA_MIN = 2.5e-5  # floor of det0/det for the antialiasing opacity factor
FOV_CLAMP = 1.3  # tx/tz clamped to +-1.3 tanfov in the EWA Jacobian
EIG_FLOOR = 0.1  # lambda = mid +- sqrt(max(0.1, mid^2 - det))
W_EPS = 1e-7  # p_w = 1 / (p_hom.w + 1e-7)


def quat_to_rotmat_unnormalised(q: torch.Tensor) -> torch.Tensor:
    """Upstream ``computeCov3D`` rotation from (w, x, y, z), NOT normalised: [K, 4] -> [K, 3, 3]."""
    r, x, y, z = q.unbind(-1)
    rows = [
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)], -1),
        torch.stack([2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)], -1),
        torch.stack([2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return torch.stack(rows, -2)


def cov3d_matrix(scales, rotations, cov3D_precomp, scale_modifier: float) -> torch.Tensor:
    """Sigma [K, 3, 3] = R S^2 R^T (upstream: M = S R_glm, Sigma = M^T M), or from precomp."""
    if cov3D_precomp is not None:
        c = cov3D_precomp
        r0 = torch.stack([c[:, 0], c[:, 1], c[:, 2]], -1)
        r1 = torch.stack([c[:, 1], c[:, 3], c[:, 4]], -1)
        r2 = torch.stack([c[:, 2], c[:, 4], c[:, 5]], -1)
        return torch.stack([r0, r1, r2], -2)
    R = quat_to_rotmat_unnormalised(rotations)
    M = R * (scales * scale_modifier)[:, None, :]
    return M @ M.transpose(-1, -2)


def inject_means2D(ndc_xy: torch.Tensor, m2: torch.Tensor) -> torch.Tensor:
    """Route d/d(NDC xy) into means2D without changing the value (upstream's means2D gradient).

    Kept as a separate function so tests can swap in ``ndc_xy + m2`` (a real offset with the same
    derivative) and check the means2D gradient against finite differences.
    """
    return ndc_xy + (m2 - m2.detach())


@dataclass
class Projected:
    """Quantities of the KEPT Gaussians (index `ids` into the inputs), in index order."""

    ids: torch.Tensor  # [K] long
    xy: torch.Tensor  # [K, 2] pixel position (carries the means2D gradient)
    depth: torch.Tensor  # [K] view z
    conic: torch.Tensor  # [K, 3] (c00, c01, c11) of inv(cov2D + 0.3 I)
    opacity: torch.Tensor  # [K] (times the antialiasing factor)
    radius: torch.Tensor  # [K] long
    rect_min: torch.Tensor  # [K, 2] long (x, y) tile indices
    rect_max: torch.Tensor  # [K, 2] long, exclusive


def _take(t: Optional[torch.Tensor], ids: torch.Tensor) -> Optional[torch.Tensor]:
    return None if t is None else t.index_select(0, ids)


def preprocess(
    means3D,
    means2D,
    opacities,
    scales,
    rotations,
    cov3D_precomp,
    viewmatrix,
    projmatrix,
    *,
    image_height: int,
    image_width: int,
    tanfovx: float,
    tanfovy: float,
    scale_modifier: float,
    antialiasing: bool,
) -> Projected:
    """Project, cull and measure every Gaussian (steps 1-3 of the rasterizer's numerics).

    The tensors and settings are those of the backend contract (docs/CONTRACTS.md); ``means2D``,
    ``scales``/``rotations`` or ``cov3D_precomp`` may be None as there.

    Returns:
        The kept Gaussians' quantities (`Projected`).
    """
    H, W = image_height, image_width
    dev = means3D.device
    P = means3D.shape[0]
    ones = torch.ones(P, 1, dtype=means3D.dtype, device=dev)
    hom = torch.cat([means3D, ones], -1)
    t_all = hom @ viewmatrix
    # Cull first (no gradient through the decision), then compute on the kept subset so culled
    # Gaussians can never leak NaN/Inf into the gradients.
    with torch.no_grad():
        keep = t_all[:, 2] > NEAR_CULL
    ids = torch.nonzero(keep).flatten()
    t = t_all.index_select(0, ids)[:, :3]
    p_hom = hom.index_select(0, ids) @ projmatrix
    p_w = 1.0 / (p_hom[:, 3] + W_EPS)
    ndc_xy = p_hom[:, :2] * p_w[:, None]
    if means2D is not None:
        ndc_xy = inject_means2D(ndc_xy, means2D.index_select(0, ids)[:, :2])

    Sigma = cov3d_matrix(
        _take(scales, ids), _take(rotations, ids), _take(cov3D_precomp, ids), scale_modifier
    )
    focal_x = W / (2.0 * tanfovx)
    focal_y = H / (2.0 * tanfovy)
    limx, limy = FOV_CLAMP * tanfovx, FOV_CLAMP * tanfovy
    tz = t[:, 2]
    tx = torch.clamp(t[:, 0] / tz, -limx, limx) * tz
    ty = torch.clamp(t[:, 1] / tz, -limy, limy) * tz
    zero = torch.zeros_like(tz)
    J = torch.stack(
        [
            torch.stack([focal_x / tz, zero, -focal_x * tx / (tz * tz)], -1),
            torch.stack([zero, focal_y / tz, -focal_y * ty / (tz * tz)], -1),
        ],
        -2,
    )  # [K, 2, 3]
    Rw = viewmatrix[:3, :3].transpose(0, 1)
    T = J @ Rw
    cov = T @ Sigma @ T.transpose(-1, -2)
    a0, b0, c0 = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]

    with torch.no_grad():
        a, c = a0 + LOWPASS, c0 + LOWPASS
        det = a * c - b0 * b0
        mid = 0.5 * (a + c)
        lam1 = mid + torch.sqrt(torch.clamp_min(mid * mid - det, EIG_FLOOR))
        radius = torch.ceil(3.0 * torch.sqrt(lam1))
        px = ((ndc_xy[:, 0] + 1.0) * W - 1.0) * 0.5
        py = ((ndc_xy[:, 1] + 1.0) * H - 1.0) * 0.5
        gx, gy = (W + BLOCK - 1) // BLOCK, (H + BLOCK - 1) // BLOCK
        # C (int) cast truncates toward zero; clamping to [0, grid] first is equivalent.
        rmin_x = torch.trunc(torch.clamp((px - radius) / BLOCK, 0, gx))
        rmin_y = torch.trunc(torch.clamp((py - radius) / BLOCK, 0, gy))
        rmax_x = torch.trunc(torch.clamp((px + radius + BLOCK - 1) / BLOCK, 0, gx))
        rmax_y = torch.trunc(torch.clamp((py + radius + BLOCK - 1) / BLOCK, 0, gy))
        keep2 = (det != 0) & ((rmax_x - rmin_x) * (rmax_y - rmin_y) != 0)
        sel = torch.nonzero(keep2).flatten()

    # Everything with a gradient is computed on the final subset only (no 0 * inf in backward).
    a0, b, c0 = a0.index_select(0, sel), b0.index_select(0, sel), c0.index_select(0, sel)
    det0 = a0 * c0 - b * b
    a, c = a0 + LOWPASS, c0 + LOWPASS
    det = a * c - b * b
    opac = opacities.index_select(0, ids).index_select(0, sel)[:, 0]
    if antialiasing:
        opac = opac * torch.sqrt(torch.clamp_min(det0 / det, AA_MIN))
    conic = torch.stack([c / det, -b / det, a / det], -1)
    px_s = ((ndc_xy[:, 0].index_select(0, sel) + 1.0) * W - 1.0) * 0.5
    py_s = ((ndc_xy[:, 1].index_select(0, sel) + 1.0) * H - 1.0) * 0.5
    return Projected(
        ids=ids.index_select(0, sel),
        xy=torch.stack([px_s, py_s], -1),
        depth=tz.index_select(0, sel),
        conic=conic,
        opacity=opac,
        radius=radius.index_select(0, sel).long(),
        rect_min=torch.stack([rmin_x, rmin_y], -1).index_select(0, sel).long(),
        rect_max=torch.stack([rmax_x, rmax_y], -1).index_select(0, sel).long(),
    )
