"""Matching-only baseline: matcher + essential matrix (RANSAC).

Between the image rendered at the initial pose and the query, as the paper's LightGlue / LoFTR
rows of the relative-pose table.

Relative pose convention: for cameras A (the render at the initial pose) and B (the query) with
world-to-camera ``w2c_a``, ``w2c_b``, the relative pose maps A-camera coordinates to B-camera
coordinates: ``x_b = R_ab x_a + t_ab``, ``R_ab = R_b R_a^T``, ``t_ab = t_b - R_ab t_a``. OpenCV's
``findEssentialMat(pts_a, pts_b)`` / ``recoverPose`` estimate exactly this (t up to scale).
Keypoints are pixels with integer pixel centres (3DGS); they are normalised with each camera's
K before estimation (LoFTR's ``estimate_pose``), the RANSAC threshold is given in pixels and
divided by the mean focal length.

For iComMa, the relative rotation from the fixed initial camera is ``R_est R_a^T``, so its
relative rotation error equals its absolute rotation error.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

import numpy as np

from ..pose.convert import invert_rigid, rotation_error_deg
import torch

logger = logging.getLogger(__name__)

__all__ = ["RelativePose", "relative_pose_gt", "rotation_angle_deg", "translation_angle_deg",
           "estimate_relative_pose", "essential_matrix_baseline"]


@dataclass(frozen=True)
class RelativePose:
    """An estimated relative pose A -> B (module docstring) and its match counts."""

    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3] unit vector
    num_matches: int
    num_inliers: int


def _K(K) -> np.ndarray:
    if isinstance(K, torch.Tensor):
        K = K.detach().cpu().double().numpy()
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be a 3x3 calibration matrix, got shape {K.shape}")
    return K


def _pts(p, name) -> np.ndarray:
    if isinstance(p, torch.Tensor):
        p = p.detach().cpu().double().numpy()
    p = np.asarray(p, np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape [N, 2], got {p.shape}")
    return p


def relative_pose_gt(w2c_a: np.ndarray, w2c_b: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(R_ab, t_ab) with ``x_b = R_ab x_a + t_ab``."""
    A, B = np.asarray(w2c_a, np.float64), np.asarray(w2c_b, np.float64)
    R = B[:3, :3] @ A[:3, :3].T
    t = B[:3, 3] - R @ A[:3, 3]
    return R, t


def rotation_angle_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of ``R_est R_gt^T`` in degrees (``pose.convert.rotation_error_deg``)."""
    return float(rotation_error_deg(np.asarray(R_est, np.float64), np.asarray(R_gt, np.float64)))


def translation_angle_deg(t_est: np.ndarray, t_gt: np.ndarray) -> Optional[float]:
    """Angle between translation directions in degrees (None if either is ~0)."""
    a, b = np.asarray(t_est, np.float64), np.asarray(t_gt, np.float64)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return None
    c = float(np.clip(a @ b / (na * nb), -1.0, 1.0))
    return math.degrees(math.acos(c))


def estimate_relative_pose(kpts_a, kpts_b, K_a, K_b, thresh_px: float = 1.0, conf: float = 0.99999,
                           seed: Optional[int] = 0) -> Optional[RelativePose]:
    """Essential matrix with RANSAC + cheirality check (cv2). None with < 5 matches or no model.

    Args:
        kpts_a: [N, 2] matched pixels in image A.
        kpts_b: [N, 2] the matching pixels in image B.
        K_a: 3x3 calibration of camera A.
        K_b: 3x3 calibration of camera B.
        thresh_px: RANSAC threshold in pixels (divided by the mean focal length of both cameras).
        conf: RANSAC confidence.
        seed: seeds OpenCV's RNG (``cv2.setRNGSeed``) for a reproducible RANSAC; None leaves it.
    """
    import cv2

    pa, pb = _pts(kpts_a, "kpts_a"), _pts(kpts_b, "kpts_b")
    if pa.shape[0] != pb.shape[0]:
        raise ValueError(
            f"kpts_a and kpts_b must have the same length, got {pa.shape[0]} and {pb.shape[0]}"
        )
    if not (isinstance(thresh_px, (int, float)) and thresh_px > 0):
        raise ValueError(f"thresh_px must be a positive number, got {thresh_px!r}")
    n = int(pa.shape[0])
    if n < 5:
        return None
    Ka, Kb = _K(K_a), _K(K_b)
    na = (pa - Ka[[0, 1], [2, 2]]) / Ka[[0, 1], [0, 1]]
    nb = (pb - Kb[[0, 1], [2, 2]]) / Kb[[0, 1], [0, 1]]
    f_mean = float(np.mean([Ka[0, 0], Ka[1, 1], Kb[0, 0], Kb[1, 1]]))
    if seed is not None:
        cv2.setRNGSeed(int(seed))
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), threshold=thresh_px / f_mean, prob=conf,
                                   method=cv2.RANSAC)
    if E is None:
        return None
    best = None
    for Ei in np.split(E, len(E) // 3):
        ninl, R, t, m = cv2.recoverPose(Ei, na, nb, np.eye(3), 1e9, mask=mask.copy())
        if best is None or ninl > best[0]:
            best = (int(ninl), R, t.reshape(-1)[:3])
    ninl, R, t = best
    tn = t / max(np.linalg.norm(t), 1e-12)
    return RelativePose(R=np.asarray(R, np.float64), t=tn, num_matches=n, num_inliers=ninl)


def essential_matrix_baseline(
    model, query_rgb: torch.Tensor, intrinsics, init_c2w: np.ndarray, gt_c2w: np.ndarray, matcher,
    bg: Optional[torch.Tensor] = None, backend: str = "auto", thresh_px: float = 1.0,
    conf: float = 0.99999, seed: Optional[int] = 0,
) -> Dict[str, Any]:
    """Render at ``init_c2w``, match render <-> query, estimate the relative pose.

    Returns:
        A JSON-ready dict with the errors against the ground truth (``rel_rot_err_deg`` is None
        when the estimate failed).
    """
    from ..render import render

    t0 = time.perf_counter()
    w2c_a = invert_rigid(np.asarray(init_c2w, np.float64))
    w2c_b = invert_rigid(np.asarray(gt_c2w, np.float64))
    if bg is None:
        bg = torch.zeros(3)
    with torch.no_grad():
        img = render(model, intrinsics, torch.as_tensor(w2c_a, dtype=model.dtype),
                     torch.as_tensor(bg, dtype=model.dtype).reshape(3), backend=backend).color
        img = img.clamp(0.0, 1.0)
        m = matcher.match(img, query_rgb.to(img.dtype), differentiable=False)
    K = intrinsics.K().numpy()
    est = estimate_relative_pose(m.kpts0, m.kpts1, K, K, thresh_px=thresh_px, conf=conf, seed=seed)
    R_gt, t_gt = relative_pose_gt(w2c_a, w2c_b)
    out: Dict[str, Any] = {
        "num_matches": int(len(m)),
        "num_inliers": None,
        "rel_rot_err_deg": None,
        "rel_trans_angle_deg": None,
        "gt_rel_rot_deg": rotation_angle_deg(R_gt, np.eye(3)),
        "seconds": None,
    }
    if est is not None:
        out["num_inliers"] = est.num_inliers
        out["rel_rot_err_deg"] = rotation_angle_deg(est.R, R_gt)
        out["rel_trans_angle_deg"] = translation_angle_deg(est.t, t_gt)
    out["seconds"] = time.perf_counter() - t0
    return out
