"""Initial poses for the benchmark: the ground truth perturbed as iComMa / iNeRF do.

iComMa (``run.py``) builds ``start_c2w = T(t) @ R_z @ R_y @ R_x @ gt_c2w``: every factor is
LEFT-multiplied onto camera-to-world, i.e. applied in the world frame about the WORLD ORIGIN, so
a rotation delta also moves the camera centre (docs: /work/shared/docs/anchors_icomma_3dgs.md
§1.2). ``icomma_plugin.pose.convert.perturb_pose`` instead pivots about the camera centre, so this
module implements the origin pivot itself:

    init_c2w = T(offset) @ T_pivot(R) @ gt_c2w,     T_pivot(R) = [[R, p - R p], [0, 1]]

with ``R`` a rotation by an angle drawn uniformly in ``[rot_lo, rot_hi]`` degrees about a
uniformly random axis (a random axis covers both signs, so ``+-[a, b]`` is ``[a, b]`` here), ``p``
the pivot (the world origin by default) and ``offset`` a world-frame translation of the camera
centre. The rotation error of the result against the ground truth is exactly the drawn angle.

Translations are given in the benchmark's translation unit: world offset = offset x
``translation_scale`` (1 for world units, the default; the scene radius with
``translation_unit=scene_radius``; see docs/BENCHMARK.md). ``per_axis`` draws each component's
magnitude uniformly in ``[t_lo, t_hi]`` with a random sign (iNeRF / iComMa "+-[a, b] per
axis"); ``norm`` draws a uniform direction and a norm uniformly in ``[t_lo, t_hi]``.

Reproducibility: :func:`pose_seed` derives one independent stream per
(protocol seed, interval, query, pose), so a run draws the same poses whatever subset of them it
computes, in whatever order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Tuple, Union

import numpy as np

from ..pose.convert import random_unit_vector, rotation_about_axis

__all__ = ["InitialPose", "pose_seed", "pose_rng", "sample_axis", "sample_initial_pose",
           "rotation_matrix", "TRANSLATION_MODES", "PIVOTS"]

TRANSLATION_MODES = ("per_axis", "norm")
#: "scene_center": the scene's centre (the point nearest to the train cameras' optical axes);
#: the runner passes it as a world point.
PIVOTS = ("origin", "camera", "scene_center")

PivotLike = Union[str, Sequence[float], np.ndarray]


@dataclass(frozen=True)
class InitialPose:
    """A sampled initial pose and how it was drawn (all float64 numpy; c2w in OpenCV axes)."""

    c2w: np.ndarray
    rot_deg: float  # drawn angle = rotation error of c2w against the ground truth
    axis: np.ndarray  # [3] unit rotation axis (world frame)
    pivot: np.ndarray  # [3] world point the rotation turns about
    offset: np.ndarray  # [3] normalised translation of the centre (after the rotation)
    offset_world: np.ndarray  # [3] the same in world units
    seed: Tuple[int, ...]

    def to_json(self) -> dict:
        """The sample as JSON (arrays as lists)."""
        return {
            "rot_deg": float(self.rot_deg),
            "axis": self.axis.tolist(),
            "pivot": self.pivot.tolist(),
            "offset": self.offset.tolist(),
            "offset_world": self.offset_world.tolist(),
            "seed": list(self.seed),
            "init_c2w": self.c2w.tolist(),
        }


def pose_seed(seed: int, interval_index: int, query_index: int, pose_index: int) -> Tuple[int, ...]:
    """The seed sequence of one initial pose (recorded in results.json)."""
    for name, v in (
        ("seed", seed),
        ("interval_index", interval_index),
        ("query_index", query_index),
        ("pose_index", pose_index),
    ):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 0:
            raise ValueError(f"{name} must be a non-negative int, got {v!r}")
    return (int(seed), int(interval_index), int(query_index), int(pose_index))


def pose_rng(seed_seq: Sequence[int]) -> np.random.Generator:
    """A numpy generator seeded by the whole sequence (e.g. ``pose_seed``'s)."""
    return np.random.default_rng(np.random.SeedSequence(list(seed_seq)))


def sample_axis(rng: np.random.Generator) -> np.ndarray:
    """Uniform direction on the unit sphere (``pose.convert.random_unit_vector``)."""
    return random_unit_vector(rng)


def rotation_matrix(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rodrigues rotation (float64 [3, 3]) by ``angle_deg`` about ``axis``.

    ``pose.convert.rotation_about_axis``.
    """
    return rotation_about_axis(axis, angle_deg)


def _range(value, name: str, allow_neg: bool = False) -> Tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair [lo, hi] of numbers, got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi or (not allow_neg and lo < 0):
        raise ValueError(f"{name} must be a finite pair with 0 <= lo <= hi, got {value!r}")
    return lo, hi


def sample_initial_pose(
    gt_c2w: np.ndarray,
    rot_range_deg: Sequence[float],
    trans_range: Sequence[float],
    rng: Union[np.random.Generator, Sequence[int]],
    translation_scale: float = 1.0,
    translation_mode: str = "per_axis",
    pivot: PivotLike = "origin",
) -> InitialPose:
    """Perturb ``gt_c2w`` by a rotation about ``pivot`` and a translation of the centre.

    Args:
        gt_c2w: [4, 4] ground-truth camera-to-world (OpenCV axes).
        rot_range_deg: ``[lo, hi]``: the angle is uniform in it (degrees, 0 <= lo <= hi <= 180).
        trans_range: ``[lo, hi]`` in normalised units (see ``translation_mode``).
        rng: a numpy Generator, or a seed sequence from :func:`pose_seed`.
        translation_scale: world units per normalised unit (the scene radius, or 1 for world units).
        translation_mode: ``"per_axis"`` or ``"norm"``.
        pivot: ``"origin"`` (iComMa), ``"camera"`` (the camera centre: no centre motion from the
            rotation) or a world point [3].

    Returns:
        :class:`InitialPose`.
    """
    T = np.asarray(gt_c2w, np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"gt_c2w must be a finite 4x4 matrix, got shape {T.shape}")
    rlo, rhi = _range(rot_range_deg, "rot_range_deg")
    if rhi > 180:
        raise ValueError(f"rot_range_deg must lie in [0, 180], got {list(rot_range_deg)!r}")
    tlo, thi = _range(trans_range, "trans_range")
    if not (isinstance(translation_scale, (int, float)) and math.isfinite(translation_scale)
            and translation_scale > 0):
        raise ValueError(
            f"translation_scale must be a positive finite number, got {translation_scale!r}"
        )
    if translation_mode not in TRANSLATION_MODES:
        raise ValueError(
            f"translation_mode must be one of {TRANSLATION_MODES}, got {translation_mode!r}"
        )
    seed: Tuple[int, ...] = ()
    if not isinstance(rng, np.random.Generator):
        seed = tuple(int(s) for s in rng)
        rng = pose_rng(seed)
    if isinstance(pivot, str):
        if pivot == "origin":
            p = np.zeros(3)
        elif pivot == "scene_center":
            raise ValueError("pivot 'scene_center' must be passed as the world point itself "
                             "(BenchScene.scene_centre)")
        elif pivot == "camera":
            p = T[:3, 3].copy()
        else:
            raise ValueError(f"pivot must be one of {PIVOTS} or a world point [3], got {pivot!r}")
    else:
        p = np.asarray(pivot, np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(
                f"pivot must be one of {PIVOTS} or a finite world point [3], got {pivot!r}"
            )

    angle = float(rng.uniform(rlo, rhi)) if rhi > rlo else rlo
    axis = sample_axis(rng)
    R = rotation_matrix(axis, angle)
    Tp = np.eye(4)
    Tp[:3, :3] = R
    Tp[:3, 3] = p - R @ p
    if translation_mode == "per_axis":
        mags = rng.uniform(tlo, thi, 3) if thi > tlo else np.full(3, tlo)
        signs = np.where(rng.uniform(size=3) < 0.5, -1.0, 1.0)
        offset = mags * signs
    else:
        norm = float(rng.uniform(tlo, thi)) if thi > tlo else tlo
        offset = sample_axis(rng) * norm
    offset_world = offset * float(translation_scale)
    out = Tp @ T
    out[:3, 3] += offset_world
    return InitialPose(c2w=out, rot_deg=angle, axis=axis, pivot=p, offset=offset,
                       offset_world=offset_world, seed=seed)
