"""Initial Gaussians from a point cloud, as upstream `GaussianModel.create_from_pcd`.

Scales: log(sqrt(mean squared distance to the 3 nearest neighbours)), clamped at 1e-7 (simple-knn
`distCUDA2`), isotropic; rotations identity; opacity `inverse_sigmoid(0.1)`; colour into the SH DC
band (`RGB2SH`), higher bands zero.
"""
from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..gaussians import GaussianModel, num_sh_coeffs, rgb_to_sh


def mean_knn_sq_dist(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean squared distance of each point to its k nearest other points (simple-knn distCUDA2)."""
    points = np.asarray(points, dtype=np.float64)
    n = points.shape[0]
    if n < 2:
        return np.full((n,), 1e-2, dtype=np.float64)
    kk = min(k, n - 1)
    d, _ = cKDTree(points).query(points, k=kk + 1)
    d = np.asarray(d).reshape(n, kk + 1)[:, 1:]  # drop self
    return np.clip((d ** 2).mean(axis=1), 1e-7, None)


def random_cube_points(
    n: int, half_extent: float = 1.3, seed: int = 0
) -> Tuple[np.ndarray, np.ndarray]:
    """Upstream Blender init: n uniform points in [-h, h]^3 with random colours (float in [0, 1])."""
    if n < 1:
        raise ValueError(f"n (number of random points) must be >= 1, got {n!r}")
    rng = np.random.default_rng(seed)
    xyz = (rng.random((n, 3)) * 2.0 - 1.0) * half_extent
    # upstream draws SH DC ~ U[0,1)/255 -> colour ~ 0.5 + C0 * small; we draw the colour itself
    rgb = rng.random((n, 3))
    return xyz.astype(np.float32), rgb.astype(np.float32)


def model_from_points(
    xyz: np.ndarray,
    rgb: np.ndarray,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    dtype: torch.dtype = torch.float32,
    device: Optional[torch.device] = None,
) -> GaussianModel:
    """A GaussianModel with one isotropic Gaussian per point (upstream `create_from_pcd`)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    rgb = np.asarray(rgb, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.shape[0] < 1:
        raise ValueError(f"xyz must be a non-empty [N, 3] array, got shape {list(xyz.shape)}")
    if rgb.shape != xyz.shape:
        raise ValueError(f"rgb must have the shape of xyz {list(xyz.shape)}, got {list(rgb.shape)}")
    if rgb.max(initial=0.0) > 1.0 + 1e-6:  # uint8-style colours
        rgb = rgb / 255.0
    P = xyz.shape[0]
    dist2 = mean_knn_sq_dist(xyz)
    t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    scale_log = t(np.log(np.sqrt(dist2)))[:, None].repeat(1, 3)
    quat = torch.zeros(P, 4, dtype=dtype, device=device)
    quat[:, 0] = 1.0
    logit = math.log(init_opacity / (1.0 - init_opacity))
    return GaussianModel(
        means=t(xyz).contiguous(),
        sh_dc=rgb_to_sh(t(rgb)).view(P, 1, 3).contiguous(),
        sh_rest=torch.zeros(P, num_sh_coeffs(sh_degree) - 1, 3, dtype=dtype, device=device),
        opacity_logit=torch.full((P, 1), logit, dtype=dtype, device=device),
        scale_log=scale_log.contiguous(),
        quat=quat,
        sh_degree=sh_degree,
    )


def subsample_points(
    xyz: np.ndarray, rgb: np.ndarray, max_points: int, seed: int = 0
) -> Tuple[np.ndarray, np.ndarray]:
    """At most max_points of the cloud, drawn without replacement (order kept)."""
    n = xyz.shape[0]
    if n <= max_points:
        return xyz, rgb
    idx = np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))
    return xyz[idx], rgb[idx]
