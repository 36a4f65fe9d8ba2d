"""One camera's focal length, estimated from many of its photos or frames together.

A single photo's verdict refits its matches with the focal length free (``signals.focal``); one
photo says too little to decide on, many of one camera say it together. A video
(``tracking.TrackingConfig.focal_from_frames``) and a batch of photo files given one camera
(``BatchFocalConfig``) pool those refits (``pooled_focal_scale``) and localize their photos again
with the focal length they agree on. Each row records the focal length it was localized with as
a share of the given one (``CAMERA_FOCAL_KEY``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence

import numpy as np

from ..checks import check_bool, check_int, check_real

__all__ = ["CAMERA_FOCAL_KEY", "BatchFocalConfig", "check_pooling", "photo_focal_scale",
           "pooled_focal_scale"]

#: a row's field: the focal length its photo was localized with, a share of the given one
CAMERA_FOCAL_KEY = "camera_focal_scale"


def pooled_focal_scale(scales: Sequence[Optional[float]], current: float = 1.0,
                       min_change: float = 0.01, agree: float = 0.8) -> Optional[float]:
    """The focal scale the photos agree on, or None when they do not say ``current`` is off.

    ``scales``: per photo, the focal length its matches prefer as a share of the given one
    (``photo_focal_scale``; None and non-finite entries are skipped); ``current``: the share
    used now. Their median when it is more than ``min_change`` (relative) from ``current`` and at
    least ``agree`` of them lie on its side of ``current``. Given the right focal length, the lego
    path video's frames scatter about it with a standard deviation of 0.6 % (medians of 10 frames
    within 0.3 %); given one 4 % off, every frame lies on one side.
    """
    s = np.asarray([x for x in scales if x is not None and np.isfinite(x) and x > 0], np.float64)
    if s.size == 0:
        return None
    m = float(np.median(s))
    if abs(m / current - 1.0) <= min_change:
        return None
    same_side = float(np.mean((s > current) == (m > current)))
    return m if same_side >= agree else None


def photo_focal_scale(row: Dict[str, Any]) -> Optional[float]:
    """The focal length a photo's matches prefer, as a share of the given one.

    The verdict's refit (``signals.focal.scale``, of the focal length the photo was localized
    with) times the photo's own estimate when its method made one (``details["focal_scale"]``)
    times the one it was localized with (``CAMERA_FOCAL_KEY``); None for a failed photo or one
    without the signal.
    """
    if row.get("status") == "failed" or row.get("c2w") is None:
        return None
    scale = ((row.get("signals") or {}).get("focal") or {}).get("scale")
    if scale is None:
        return None
    own = (row.get("details") or {}).get("focal_scale") or 1.0
    return float(row.get(CAMERA_FOCAL_KEY) or 1.0) * float(own) * float(scale)


def check_pooling(cfg: Any, group: str) -> None:
    """The pooling settings shared by a batch's and a sequence's config (``focal_*``)."""
    check_real(cfg.focal_min_change, f"{group}.focal_min_change", 0.0, 0.5)
    check_real(cfg.focal_agree, f"{group}.focal_agree", 0.5, 1.0)
    check_int(cfg.focal_rounds, f"{group}.focal_rounds", 1)
    check_real(cfg.focal_settle, f"{group}.focal_settle", 0.0, cfg.focal_min_change)


@dataclass
class BatchFocalConfig:
    """A batch's focal length from its photos (the tool's ``batch`` group).

    focal_from_photos: when the photos are files given one camera (``data.intrinsics``, not a
        dataset folder's own cameras) and at least ``focal_min_photos`` of them were localized,
        their refits' median (``pooled_focal_scale``) more than ``focal_min_change`` off the
        focal length used, with at least ``focal_agree`` of them on its side, is adopted and
        every photo is localized again with it, from its first pose; at most ``focal_rounds``
        times, the later ones on a change above ``focal_settle``. A sharded run decides per shard.
    """

    focal_from_photos: bool = True
    focal_min_photos: int = 5
    focal_min_change: float = 0.01
    focal_agree: float = 0.8
    focal_rounds: int = 3
    focal_settle: float = 0.005

    def __post_init__(self):
        check_bool(self.focal_from_photos, "batch.focal_from_photos")
        check_int(self.focal_min_photos, "batch.focal_min_photos", 2)
        check_pooling(self, "batch")

    def adopt(self, rows: Sequence[Dict[str, Any]], current: float, adopted_before: bool
              ) -> Optional[float]:
        """The focal scale the photos of ``rows`` agree on instead of ``current``, or None."""
        scales = [s for s in map(photo_focal_scale, rows) if s is not None]
        if not self.focal_from_photos or len(scales) < self.focal_min_photos:
            return None
        return pooled_focal_scale(
            scales, current, self.focal_settle if adopted_before else self.focal_min_change,
            self.focal_agree)
