"""Views around a scene: its frame (centre, radius, up) and cameras sampled on a sphere.

The candidate views of the localizer and the camera paths of ``tools/render_path.py`` are made
from these.
"""
from __future__ import annotations

import math
from typing import List, Sequence

import numpy as np

from .convert import look_at_c2w

__all__ = ["camera_nearness", "sample_views", "scene_frame"]


def camera_nearness(c2ws: np.ndarray, c2w: np.ndarray) -> tuple:
    """How near each camera of ``c2ws`` [N, 4, 4] is to ``c2w`` [4, 4]: (score [N], angle [N]).

    ``angle``: degrees between the optical axes (+z, OpenCV); ``score`` (lower is nearer):
    ``angle / 30 + distance of the centres / their median distance``, so that a camera beside
    ``c2w`` looking elsewhere is as far as one looking the same way from twice as far.
    """
    c2ws = np.asarray(c2ws, np.float64).reshape(-1, 4, 4)
    c2w = np.asarray(c2w, np.float64)
    cos = np.clip(c2ws[:, :3, 2] @ c2w[:3, 2], -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    dist = np.linalg.norm(c2ws[:, :3, 3] - c2w[:3, 3], axis=1)
    unit = max(float(np.median(dist)), 1e-9) if len(dist) else 1.0
    return angle / 30.0 + dist / unit, angle


def scene_frame(points: np.ndarray, cameras_c2w: Sequence[np.ndarray]):
    """(centre [3], radius, up [3]) of the scene.

    From the cameras when there are any (the point their optical axes pass closest to, their
    median distance to it, their mean 'up'), else from the scene's ``points`` ``[N, 3]`` (a
    model's Gaussian means: median position, 3x their spread, +z).
    """
    means = np.asarray(points, np.float64)
    if len(cameras_c2w) >= 2:
        C = np.stack([c[:3, 3] for c in cameras_c2w])
        D = np.stack([c[:3, 2] for c in cameras_c2w])
        # least-squares point nearest to all optical axes
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for c, d in zip(C, D):
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ c
        try:
            centre = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            centre = np.median(means, 0)
        if not np.all(np.isfinite(centre)) or np.linalg.cond(A) > 1e6:
            centre = np.median(means, 0)
        radius = float(np.median(np.linalg.norm(C - centre, axis=1)))
        up = -np.mean([c[:3, 1] for c in cameras_c2w], 0)  # OpenCV y points down
        up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
        return centre, radius, up
    centre = np.median(means, 0)
    spread = float(np.median(np.linalg.norm(means - centre, axis=1))) if len(means) else 1.0
    return centre, 3.0 * max(spread, 1e-3), np.array([0.0, 0.0, 1.0])


def sample_views(centre: np.ndarray, radius: float, up: np.ndarray, n: int) -> List[np.ndarray]:
    """``n`` c2w poses on a sphere of ``radius`` about ``centre`` (Fibonacci lattice).

    They look at the centre with image 'up' towards ``up``; directions too close to ``up`` are
    skipped.
    """
    out = []
    if n <= 0:
        return out
    golden = math.pi * (3.0 - math.sqrt(5.0))
    # an orthonormal frame with z = up
    z = up / np.linalg.norm(up)
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    for i in range(n):
        h = 1.0 - 2.0 * (i + 0.5) / n
        r = math.sqrt(max(0.0, 1.0 - h * h))
        d = r * math.cos(golden * i) * x + r * math.sin(golden * i) * y + h * z
        if abs(h) > 0.97:
            continue  # looking straight along 'up': the image's up is undefined
        out.append(look_at_c2w(centre + radius * d, centre, up))
    return out
