"""Camera poses written out independently of icomma_plugin.pose.

Tests check conventions against known geometry with these, not against the code under test.
"""
from __future__ import annotations

import numpy as np


def look_at_c2w(centre, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) at ``centre`` looking at ``target``."""
    c = np.asarray(centre, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, c
    return m


def gl_look_at_c2w(centre, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world (x right, y up, z back) at ``centre`` looking at ``target``."""
    m = look_at_c2w(centre, target, up)
    m[:3, 1:3] *= -1.0
    return m


def project(view_or_w2c, intr, X) -> np.ndarray:
    """Pixel of world point ``X`` (the project's convention: pixel centres at integers).

    ``view_or_w2c`` is a view (its ``w2c``) or a world-to-camera matrix; ``intr`` the
    intrinsics (``fx``, ``fy``, ``cx_px``, ``cy_px``).
    """
    w2c = view_or_w2c.w2c if hasattr(view_or_w2c, "w2c") else view_or_w2c
    xc = w2c[:3, :3] @ np.asarray(X, float) + w2c[:3, 3]
    assert xc[2] > 0
    return np.array([intr.fx * xc[0] / xc[2] + intr.cx_px, intr.fy * xc[1] / xc[2] + intr.cy_px])
