"""Pose maths: SE(3) exp/log (`se3`) and frame conversions / error metrics (`convert`).

Conventions are stated once in `icomma_plugin/pose/se3.py` (and docs/CONTRACTS.md).
"""
from .se3 import hat, se3_exp, se3_log, so3_exp, so3_left_jacobian, so3_log, vee

__all__ = [
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "se3_exp",
    "se3_log",
]
