"""One camera's lens distortion, estimated from many of its photos together.

The model renders pinhole images. A phone photo whose lens distortion was not removed
(``data.intrinsics.distortion`` not given) is localized with the pose taking up what it can of
the distortion: fox's phone photos given their pinhole intrinsics alone end 0.14 deg off (median),
0.02 deg undistorted (docs/BATCHES.md). Each photo's verdict refits its matches with the lens
distortion free (``signals.distortion``, ``geometry.fit_pose_and_distortion``); one photo's
coefficients scatter with its matches (bird's soft photos, which have no distortion, fit up to
9 px of it), many photos of one camera agree. A batch of photo files given one camera
(``BatchLensConfig``) pools them (``pooled_distortion``), undistorts its photos with the
coefficients they agree on and localizes them again. Each row records the coefficients its photo
was undistorted with (``CAMERA_DISTORTION_KEY``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from ..checks import check_bool, check_int, check_real
from ..localization.geometry import distortion_field

__all__ = ["CAMERA_DISTORTION_KEY", "BatchLensConfig", "PhotoDistortion", "photo_distortion",
           "pooled_distortion"]

#: a row's field: OpenCV's ``[k1, k2, p1, p2]`` its photo was undistorted with (adopted from the
#: photos); absent when none
CAMERA_DISTORTION_KEY = "camera_distortion"


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


def pooled_distortion(estimates: Sequence[PhotoDistortion],
                      current: Sequence[float] = (0.0, 0.0, 0.0, 0.0), min_shift_px: float = 0.5,
                      agree: float = 0.8) -> Optional[Tuple[float, float, float, float]]:
    """The coefficients the photos agree on, or None when they do not say ``current`` is off.

    The median of each coefficient, when the change from ``current`` moves a pixel by more than
    ``min_shift_px`` within the photos' reach (their median reach and focal length) and at least
    ``agree`` of the photos' own changes point the same way (a positive inner product of the two
    displacement fields over that disc). Fox's 50 phone photos given no distortion: k1 0.056, k2
    -0.078 (its calibration: 0.058, -0.081), 2.2 px, all 50 the same way; bird, goldcape and fox
    undistorted: 0.1-0.3 px, 48-72 % (docs/BATCHES.md).
    """
    est = [e for e in estimates if e is not None]
    if not est:
        return None
    cs = np.array([e.coefficients for e in est], np.float64)
    cur = np.asarray(current, np.float64)
    reach = float(np.median([e.reach for e in est]))
    focal = float(np.median([e.focal_px for e in est]))
    pooled = np.median(cs, axis=0)
    field = distortion_field(pooled, reach, focal) - distortion_field(cur, reach, focal)
    if float(np.linalg.norm(field, axis=1).max()) <= min_shift_px:
        return None
    base = distortion_field(cur, reach, focal)
    same_way = np.mean([float(((distortion_field(c, reach, focal) - base) * field).sum()) > 0.0
                        for c in cs])
    return tuple(float(v) for v in pooled) if same_way >= agree else None


@dataclass
class BatchLensConfig:
    """A batch's lens distortion from its photos (the tool's ``batch.lens`` group).

    from_photos: when the photos are files given one camera and no distortion (``data.intrinsics``
        without ``distortion``; not a dataset folder's views, which are undistorted already) and
        at least ``min_photos`` of them were localized, the coefficients they agree on
        (``pooled_distortion``: ``min_shift_px``, ``agree``) are adopted and every photo is
        undistorted with them and localized again, from its pose; at most ``rounds`` times. This
        is decided before the focal length (``batch.focal_from_photos``), whose refits a
        distortion left in the photos pulls. A sharded run decides per shard.
    """

    from_photos: bool = True
    min_photos: int = 5
    min_shift_px: float = 0.5
    agree: float = 0.8
    rounds: int = 2

    def __post_init__(self):
        check_bool(self.from_photos, "batch.lens.from_photos")
        check_int(self.min_photos, "batch.lens.min_photos", 2)
        check_real(self.min_shift_px, "batch.lens.min_shift_px", 0.0, lo_open=True)
        check_real(self.agree, "batch.lens.agree", 0.5, 1.0)
        check_int(self.rounds, "batch.lens.rounds", 1)

    def adopt(self, rows: Sequence[Dict[str, Any]], current: Optional[Sequence[float]]
              ) -> Optional[Tuple[float, float, float, float]]:
        """The coefficients the photos of ``rows`` agree on instead of ``current``, or None."""
        est = [e for e in map(photo_distortion, rows) if e is not None]
        if not self.from_photos or len(est) < self.min_photos:
            return None
        return pooled_distortion(est, (0.0,) * 4 if current is None else current,
                                 self.min_shift_px, self.agree)
