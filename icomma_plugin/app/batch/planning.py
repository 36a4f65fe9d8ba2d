"""Planning a batch: which photos, with which start pose, truth and intrinsics each.

    plan, mf = plan_batch(data)          # the tool's data group (model_folder)

A photo whose start pose is missing, whose size does not fit its intrinsics or that cannot be
read is planned with an ``error``: it becomes a ``failed`` row and the batch goes on. A bad
configuration (no photos, an unreadable poses file, no intrinsics) raises ``ProblemError``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ...camera import Intrinsics
from ..inputs import (
    PhotoMismatch,
    ProblemError,
    intrinsics_for_photos,
    LensDistortion,
    VIEWS_UNDISTORTED,
    list_photos,
    start_poses,
    truths,
)
from ..lens import moved_centre
from ..problem import open_model_folder, photo_camera, scene_centre_of

__all__ = ["BatchPlan", "PhotoTask", "plan_batch", "run_identity", "select"]


@dataclass
class PhotoTask:
    """One photo of a batch (picklable: it travels to the worker processes).

    intrinsics: at the image file's size (None when ``error`` is set), with the batch's focal
    length. init_c2w: the start pose, or None (candidate views). gt_c2w: the truth when known
    (errors only). error: bad input found while planning: the photo is recorded as failed with
    this reason. focal_scale: the focal length of ``intrinsics`` as a share of the one given
    (``focal.BatchFocalConfig``; ``with_focal_scale``). distortion: OpenCV's ``(k1, k2, p1, p2)``
    the photo is undistorted with, adopted from the batch's photos
    (``lens.LensConfig``), or None. centre: the principal point's move from the image centre in
    focal lengths, adopted from the batch's photos when their intrinsics gave none
    (``with_centre``), or None.
    """

    index: int
    name: str
    path: Optional[str]
    view: Any = None
    intrinsics: Optional[Intrinsics] = None
    init_c2w: Optional[np.ndarray] = None
    gt_c2w: Optional[np.ndarray] = None
    error: Optional[str] = None
    focal_scale: float = 1.0
    distortion: Optional[Tuple[float, ...]] = None
    centre: Optional[Tuple[float, float]] = None

    def with_focal_scale(self, scale: float, init_c2w: Optional[np.ndarray]) -> "PhotoTask":
        """This photo with ``scale`` x the given focal length, started from ``init_c2w``."""
        if self.intrinsics is None:
            return replace(self, init_c2w=init_c2w, focal_scale=scale)
        given = self.intrinsics.with_focal_scale(1.0 / self.focal_scale)
        return replace(self, intrinsics=given.with_focal_scale(scale), init_c2w=init_c2w,
                       focal_scale=scale)

    def with_centre(self, centre: Optional[Tuple[float, float]]) -> "PhotoTask":
        """This photo with its principal point ``centre`` focal lengths from the image centre.

        (None: as planned.) Its intrinsics must have given none (``cx``, ``cy`` None).
        """
        if centre is None or self.intrinsics is None:
            return replace(self, centre=None if centre is None else tuple(centre))
        intr = self.intrinsics
        if intr.cx is not None and self.centre is None:
            raise ValueError(f"the photo {self.name} has a principal point of its own")
        # in the given focal length: a focal length adopted later keeps the pixels
        return replace(self, centre=tuple(centre),
                       intrinsics=moved_centre(intr, centre, intr.fx / self.focal_scale))


@dataclass
class BatchPlan:
    """The photos of a batch (`plan_batch`) and the model they are localized in."""

    tasks: List[PhotoTask]
    model_path: str
    iteration: Optional[int]
    white_background: bool
    resize: Optional[int]
    init_mode: str  # none | constant | per_photo | perturbed
    source: Any = None


def _positive(d, key, default=None):
    v = d.get(key, default)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ProblemError(f"data.{key} must be a positive integer or null, got {v!r}")
    return v


def select(items: Sequence[Any], every: Optional[int], limit: Optional[int]) -> List[int]:
    """Indices of every ``every``-th item, at most ``limit`` of them."""
    idx = list(range(0, len(items), every or 1))
    return idx[:limit] if limit else idx


def _photo_intrinsics(path, of) -> Tuple[Optional[Intrinsics], Optional[str]]:
    """(intrinsics, None) of the photo file at ``path``, or (None, why not) for this photo."""
    from ...io.datasets.base import image_size

    try:
        return of(image_size(path)), None
    except PhotoMismatch as e:  # this photo only
        return None, str(e)
    except ProblemError:  # the config's, the same for every photo
        raise
    except Exception as e:  # noqa: BLE001 - an unreadable photo is a per-photo failure
        return None, f"cannot read the image {path} ({type(e).__name__}: {e})"


def plan_batch(data: Dict[str, Any], mf=None) -> Tuple[BatchPlan, Any]:
    """The photos of ``data.queries`` with their start poses, truths and intrinsics.

    Returns:
        (plan, model folder). ``mf`` may be passed when the caller has loaded it already.

    Raises:
        ProblemError: naming the key (no photos found, an unreadable poses file, no
            intrinsics...).
    """
    if mf is None:
        mf, white = open_model_folder(data)
    else:
        white = mf.white_background if data.get("white_background") is None \
            else bool(data["white_background"])
    every, limit = _positive(data, "every", 1), _positive(data, "limit")
    photos = list_photos(
        data.get("queries"), "data.queries", str(data.get("queries_split") or "all"), white,
        mf.principal_point)
    keep = select(photos.names, every, limit)
    names = [photos.names[i] for i in keep]
    paths = [photos.paths[i] for i in keep]
    views = None if photos.views is None else [photos.views[i] for i in keep]
    gts = truths(data.get("gt"), names, views)
    mode, inits, init_errs = start_poses(data.get("init"), names, gts, mf.cameras,
                                         scene_centre_of(mf.model))
    of = None if views is not None else intrinsics_for_photos(
        data.get("intrinsics"), mf.cameras, photo_camera(data, mf, white)[0])
    if views is not None and LensDistortion.from_config(data.get("intrinsics")) is not None:
        raise ProblemError(VIEWS_UNDISTORTED)
    tasks = []
    for i, name in enumerate(names):
        if views is not None:
            intr, err = views[i].intrinsics, None
        else:
            intr, err = _photo_intrinsics(paths[i], of)
        tasks.append(PhotoTask(i, name, str(paths[i]), None if views is None else views[i],
                               intr, inits[i], gts[i], init_errs[i] or err))
    plan = BatchPlan(tasks, str(Path(mf.path).resolve()), mf.iteration, white,
                     _positive(data, "resize"), mode, data.get("queries"))
    return plan, mf


def run_identity(kind: str, data: Dict[str, Any], model_path: str) -> Dict[str, Any]:
    """What a resumed run must share with the poses.json it continues."""

    def norm(v):
        return (
            [str(x) for x in v] if isinstance(v, (list, tuple)) else (None if v is None else str(v))
        )

    return {
        "kind": kind,
        "model_path": str(model_path),
        "queries": norm(data.get("queries")),
        "sequence": norm(data.get("sequence")),
    }
