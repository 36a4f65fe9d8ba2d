"""One camera's lens distortion, estimated from many of its photos together.

The model renders pinhole images. A phone photo whose lens distortion was not removed
(``data.intrinsics.distortion`` not given) is localized with the pose taking up what it can of
the distortion: fox's phone photos given their pinhole intrinsics alone end 0.14 deg off (median),
0.02 deg undistorted (docs/BATCHES.md). Each photo's verdict refits its matches with the lens
distortion free (``signals.distortion``, ``geometry.fit_pose_and_distortion``); one photo's
coefficients scatter with its matches (bird's soft photos, which have no distortion, fit up to
9 px of it), many photos of one camera agree. A batch of photo files given one camera
(``LensConfig``) pools them (``pooled_distortion``), undistorts its photos with the
coefficients they agree on and localizes them again. Each row records the coefficients its photo
was undistorted with (``CAMERA_DISTORTION_KEY``). Photos given no principal point are refitted
with it free beside k1 and k2 (the tangential terms would stand for it), and the batch adopts the
one they agree on (``centre_evidence``, ``LensConfig.adopt_centre``; rows:
``CAMERA_CENTRE_KEY``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from ..camera import Intrinsics
from ..checks import check_bool, check_int, check_real
from ..localization.geometry import distortion_field

__all__ = ["CAMERA_CENTRE_KEY", "CAMERA_DISTORTION_KEY", "LensConfig",
           "PhotoDistortion", "TrackingLensConfig", "centre_evidence", "centre_reading",
           "lens_evidence",
           "moved_centre", "photo_centre", "photo_distortion", "principal_point_given",
           "pooled_distortion"]

#: a row's field: OpenCV's ``[k1, k2, p1, p2]`` its photo was undistorted with (adopted from the
#: photos); absent when none
CAMERA_DISTORTION_KEY = "camera_distortion"

#: a row's field: the principal point ``[cx, cy]`` (pixels of the photo file) its photo was
#: localized with, adopted from the photos when none was given; absent when none was adopted
CAMERA_CENTRE_KEY = "camera_principal_point"


@dataclass(frozen=True)
class PhotoDistortion:
    """The lens distortion a photo's matches prefer, and where they measured it.

    coefficients: OpenCV's ``(k1, k2, p1, p2)`` of the photo as it was read (those it was
    undistorted with plus the verdict's refit of what is left). reach: the largest normalised
    radius of its matches. focal_px: its focal length at the working size (the refit's pixels).
    """

    coefficients: Tuple[float, float, float, float]
    reach: float
    focal_px: float


def photo_distortion(row: Dict[str, Any]) -> Optional[PhotoDistortion]:
    """What a photo's row says of its lens (``signals.distortion``).

    None for a failed photo or one without the signal.
    """
    if row.get("status") == "failed" or row.get("c2w") is None:
        return None
    sig = (row.get("signals") or {}).get("distortion") or {}
    try:
        refit = [float(v) for v in sig["coefficients"]]
        reach, focal = float(sig["reach"]), float(sig["focal_px"])
        used = [float(v) for v in (row.get(CAMERA_DISTORTION_KEY) or (0.0,) * 4)]
    except (KeyError, TypeError, ValueError):
        return None
    if len(refit) != 4 or len(used) != 4:
        return None
    c = tuple(a + b for a, b in zip(refit, used))  # to first order the two add up
    if not (all(np.isfinite(c)) and reach > 0 and focal > 0):
        return None
    return PhotoDistortion(c, reach, focal)


def lens_evidence(estimates: Sequence[PhotoDistortion],
                  current: Sequence[float] = (0.0, 0.0, 0.0, 0.0)) -> Optional[Dict[str, Any]]:
    """What the photos' refits say of their lens together; None without any.

    ``{"coefficients"`` (the median of each of k1, k2, p1, p2), ``"shift_px"`` (what the change
    from ``current`` moves a pixel by, at most, within the photos' median reach, at their median
    focal length), ``"agree"`` (the share of the photos whose own change points the same way: a
    positive inner product of the two displacement fields over that disc), ``"views"}``.
    """
    est = [e for e in estimates if e is not None]
    if not est:
        return None
    cs = np.array([e.coefficients for e in est], np.float64)
    cur = np.asarray(current, np.float64)
    reach = float(np.median([e.reach for e in est]))
    focal = float(np.median([e.focal_px for e in est]))
    pooled = np.median(cs, axis=0)
    base = distortion_field(cur, reach, focal)
    field = distortion_field(pooled, reach, focal) - base
    same_way = np.mean([float(((distortion_field(c, reach, focal) - base) * field).sum()) > 0.0
                        for c in cs])
    return {"coefficients": [float(v) for v in pooled],
            "shift_px": float(np.linalg.norm(field, axis=1).max()), "agree": float(same_way),
            "views": len(est)}


def pooled_distortion(estimates: Sequence[PhotoDistortion],
                      current: Sequence[float] = (0.0, 0.0, 0.0, 0.0), min_shift_px: float = 0.5,
                      agree: float = 0.8) -> Optional[Tuple[float, float, float, float]]:
    """The coefficients the photos agree on, or None when they do not say ``current`` is off.

    :func:`lens_evidence`'s median coefficients, when their change from ``current`` moves a pixel
    by more than ``min_shift_px`` and at least ``agree`` of the photos point the same way. Fox's
    50 phone photos given no distortion: k1 0.055, k2 -0.078, p1 -0.0010, p2 0.0001 (its
    calibration: 0.058, -0.081, -0.0010, 0.0002), 2.5 px, all 50 the same way; goldcape's photos
    as files 0.26 px, 52 %; bird's views 1.7 px, 54 % (docs/BATCHES.md).
    """
    ev = lens_evidence(estimates, current)
    if ev is None or ev["shift_px"] <= min_shift_px or ev["agree"] < agree:
        return None
    return tuple(ev["coefficients"])


def photo_centre(row: Dict[str, Any]) -> Optional[Tuple[float, float, float]]:
    """Where a photo's refit puts its principal point, when none was given.

    ``(dx, dy, focal_px)``: its move from the image centre in focal lengths
    (``signals.distortion.centre``) and the focal length of the refit's pixels; None for a failed
    photo or one without it (a principal point given, or too few matches).
    """
    if row.get("status") == "failed" or row.get("c2w") is None:
        return None
    sig = (row.get("signals") or {}).get("distortion") or {}
    try:
        dx, dy = (float(v) for v in sig["centre"])
        focal = float(sig["focal_px"])
    except (KeyError, TypeError, ValueError):
        return None
    return (dx, dy, focal) if np.isfinite([dx, dy, focal]).all() and focal > 0 else None


def moved_centre(intrinsics: Intrinsics, offset: Sequence[float],
                 focal_px: Optional[float] = None) -> Intrinsics:
    """``intrinsics`` with the principal point ``offset`` focal lengths from the image centre.

    Both axes in units of ``focal_px`` (default: its ``fx``), as the refits measure it
    (``signals.distortion.centre``); from the image centre whatever ``cx``, ``cy`` it had.
    """
    f = float(intrinsics.fx if focal_px is None else focal_px)
    centred = intrinsics.centred()
    return dataclasses.replace(intrinsics, cx=centred.cx_px + float(offset[0]) * f,
                               cy=centred.cy_px + float(offset[1]) * f)


def centre_evidence(rows: Sequence[Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """What the photos' refits say of their principal point together; None without any.

    ``{"offset"`` (the median move of each axis from the image centre, in focal lengths),
    ``"shift_px"`` (its length in pixels of the refits' median focal length), ``"agree"`` (the
    share of the photos whose own move points the same way: a positive inner product with it),
    ``"views"}``.
    """
    est = [c for c in map(photo_centre, rows) if c is not None]
    if not est:
        return None
    moves = np.array([c[:2] for c in est], np.float64)
    offset = np.median(moves, axis=0)
    focal = float(np.median([c[2] for c in est]))
    return {"offset": [float(v) for v in offset],
            "shift_px": float(np.linalg.norm(offset) * focal),
            "agree": float(np.mean(moves @ offset > 0.0)), "views": len(est)}


def principal_point_given(intrinsics) -> bool:
    """Whether ``intrinsics`` (an ``Intrinsics`` or None) hold a principal point of their own."""
    return intrinsics is not None and intrinsics.cx is not None and intrinsics.cy is not None


@dataclass
class LensConfig:
    """One camera's lens distortion from its photos (the tool's ``batch.lens`` group).

    estimate: when the photos are files given one camera and no distortion (``data.intrinsics``
        without ``distortion``; not a dataset folder's views, which are undistorted already) and
        at least ``min_views`` of them were localized, the coefficients they agree on
        (``pooled_distortion``: ``min_shift_px``, ``agree``) are adopted and every photo is
        undistorted with them and localized again, from its pose; at most ``rounds`` times (a
        second round, on the photos undistorted, moved fox's frames' estimate away from its
        calibration: k1 0.058 -> 0.066, docs/BATCHES.md). This
        is decided before the focal length (``batch.focal_from_photos``), whose refits a
        distortion left in the photos pulls. A sharded run decides per shard. Photos given no
        principal point are refitted with it free and k1, k2 alone (a principal point off the
        image centre turns the camera, and p1, p2 would stand for what is left: fox's photos
        given the image centre, 14.5 and 4.8 px from theirs at 1080x1920, adopted p1, p2 of
        -0.0023 and ended 0.61 deg off instead of 0.48); its median move is adopted with the same
        rules (``adopt_centre``) when it is longer than ``min_centre_move`` focal lengths: a
        shorter one is within what a lens's tangential terms, or the matches alone, put there
        (principal point centred: the demo scene's photos through p1 0.002, p2 -0.001 0.0046,
        the lego path video's pinhole renders 0.0040, 80 % of either the same way; fox's
        0.0116, its truth 0.011).
    """

    #: the config group its settings are named by in errors
    GROUP = "batch.lens"

    estimate: bool = True
    min_views: int = 5
    min_shift_px: float = 0.5
    agree: float = 0.8
    rounds: int = 1
    min_centre_move: float = 0.008

    def __post_init__(self):
        g = self.GROUP
        check_bool(self.estimate, f"{g}.estimate")
        check_int(self.min_views, f"{g}.min_views", 2)
        check_real(self.min_shift_px, f"{g}.min_shift_px", 0.0, lo_open=True)
        check_real(self.agree, f"{g}.agree", 0.5, 1.0)
        check_int(self.rounds, f"{g}.rounds", 1)
        check_real(self.min_centre_move, f"{g}.min_centre_move", 0.0)

    def adopt(self, rows: Sequence[Dict[str, Any]], current: Optional[Sequence[float]]
              ) -> Optional[Tuple[float, float, float, float]]:
        """The coefficients the views of ``rows`` agree on instead of ``current``, or None."""
        est = [e for e in map(photo_distortion, rows) if e is not None]
        if not self.estimate or len(est) < self.min_views:
            return None
        return pooled_distortion(est, (0.0,) * 4 if current is None else current,
                                 self.min_shift_px, self.agree)

    def adopt_centre(self, rows: Sequence[Dict[str, Any]]) -> Optional[Tuple[float, float]]:
        """The principal point the views of ``rows`` agree on, or None.

        Its move from the image centre in focal lengths (:func:`centre_evidence`), when at
        least ``min_views`` photos measured it, it moves pixels by more than ``min_shift_px``
        and ``agree`` of them point the same way.
        """
        return self.centre_agreed(centre_evidence(rows))

    def centre_agreed(self, ev: Optional[Dict[str, Any]]) -> Optional[Tuple[float, float]]:
        """:meth:`adopt_centre`'s rule on the photos' :func:`centre_evidence` ``ev``."""
        if (not self.estimate or ev is None or ev["views"] < self.min_views
                or ev["shift_px"] <= self.min_shift_px or ev["agree"] < self.agree
                or float(np.hypot(*ev["offset"])) <= self.min_centre_move):
            return None
        return tuple(ev["offset"])


@dataclass
class TrackingLensConfig(LensConfig):
    """A sequence's lens distortion from its first frames (the tool's ``tracking.lens`` group).

    As :class:`LensConfig`, decided once on the first ``min_views`` frames localized (their lens
    refits: in the tracking mode too until then, on sub-pixel keypoints); when adopted, those
    frames are localized again with it from their poses, and every later frame is undistorted
    with it; a focal length adopted from the distorted frames is undone and estimated again from
    the undistorted ones; frames given no principal point have the one they agree on adopted
    with it (``adopt_centre``). Fox's 50 photos as frames: the first 20
    gave k1 0.058, k2 -0.079 (its calibration: 0.058, -0.081), the first 10 0.055, -0.075.
    """

    GROUP = "tracking.lens"

    min_views: int = 20


def centre_reading(rows: Sequence[Dict[str, Any]],
                   cfg: Optional[LensConfig] = None) -> Optional[Dict[str, Any]]:
    """:func:`centre_evidence` of ``rows`` with ``"off"``: whether ``cfg``'s rule would adopt it.

    For photos taken at the image centre that no batch pools (a dataset's views, the audit's):
    whether their refits agree on a principal point elsewhere (``LensConfig.adopt_centre``; the
    defaults when ``cfg`` is None).
    """
    ev = centre_evidence(rows)
    if ev is not None:
        ev["off"] = (cfg or LensConfig()).centre_agreed(ev) is not None
    return ev
