"""Assemble a localization problem from a plain configuration mapping (the tools' ``data`` group).

The model, the query photo with its intrinsics and masks, the start pose (or none), the ground
truth when it is known, and the model's cameras (candidate views).

Every bad input raises :class:`~.inputs.ProblemError` (a ValueError) whose message names the key
of the ``data`` group that caused it, so the tools print it as one line.
"""
from __future__ import annotations

import functools
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from ..io.poses_file import read_c2w_file
from ..localization.localizer import Localizer, source_photos
from ..localization.types import Query
from ..pose.convert import cameras_extent
from .inputs import (
    LensDistortion,
    ProblemError,
    fit_intrinsics,
    init_group,
    perturbed_start,
    photo_intrinsics,
    start_poses,
    truths,
    VIEWS_UNDISTORTED,
)

logger = logging.getLogger(__name__)

__all__ = [
    "Problem",
    "load_problem",
    "open_model_folder",
    "photo_camera",
    "source_camera_like",
    "photos_of",
    "read_query_image",
    "scene_centre_of",
]


@dataclass
class Problem:
    """Everything a localization needs, plus what its report needs.

    init_c2w: start pose (camera-to-world, OpenCV axes), or None (search the candidate views).
    gt_c2w: ground truth, used only to report errors. cameras: the model's cameras (``CameraEntry``,
    candidate views). scene_scale: ``cameras_extent`` of those cameras (None without cameras).
    """

    model: Any
    query: Query
    init_c2w: Optional[np.ndarray]
    gt_c2w: Optional[np.ndarray]
    bg: torch.Tensor
    scene_scale: Optional[float]
    cameras: List[Any] = field(default_factory=list)
    info: Dict[str, Any] = field(default_factory=dict)
    model_side: Optional[int] = None  # longer side of the images the model was fitted on
    photos: Optional[List[Any]] = None  # the model's source photos (anchors), when known

    @property
    def name(self) -> str:
        """The query's name."""
        return self.query.name

    def localizer(self, matcher, method, backend: str = "auto", cache_dir=None,
                  verdict="auto", lod="auto") -> Localizer:
        """The Localizer of this problem's model, cameras, background, training side, photos."""
        return Localizer(self.model, matcher, method, cameras=self.cameras, backend=backend,
                         background=self.bg, model_side=self.model_side, cache_dir=cache_dir,
                         photos=self.photos, verdict=verdict, lod=lod)


def _bg(white: bool) -> torch.Tensor:
    return torch.ones(3) if white else torch.zeros(3)


def scene_centre_of(model) -> np.ndarray:
    """The pivot ``scene_center`` of a model without cameras: the median of its Gaussians."""
    return model.means.detach().double().median(0).values.cpu().numpy()


_ROTATION_WARNED: set = set()  # folders whose photos were said to carry an EXIF rotation


def warn_if_rotated(path) -> None:
    """Log once per folder that a photo carries an EXIF rotation, which is not applied.

    A phone stores a portrait photo sideways and tags it for viewers; COLMAP and upstream 3DGS
    read the stored pixels, and so does this reader, so the model's own photos and a query agree
    when both come from the camera as they are. When the model was fitted on upright copies, the
    query must be made upright the same way, or it is localized on its side.
    """
    from ..io.datasets import exif_orientation

    path = Path(str(path)).expanduser()
    folder = str(path.parent.resolve())
    if folder in _ROTATION_WARNED:
        return
    code = exif_orientation(path)
    if code != 1:
        _ROTATION_WARNED.add(folder)
        logger.warning(
            "%s carries EXIF orientation %d (viewers show it %s); its pixels are used as stored, "
            "as COLMAP and upstream 3DGS read them (said once for %s). If the model was fitted "
            "on upright copies of its photos, make the queries upright the same way",
            path.name, code, "rotated" if code in (5, 6, 7, 8) else "flipped or turned over",
            folder)


def read_query_image(path, bg: torch.Tensor):
    """(rgb [3, H, W], alpha [1, H, W] or None) of a photo file; RGBA composited over ``bg``."""
    from ..io.datasets import read_image_file

    warn_if_rotated(path)
    img = read_image_file(Path(str(path)).expanduser())
    t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float()
    rgb, alpha = t[:3], (t[3:4] if t.shape[0] == 4 else None)
    if alpha is not None:
        rgb = rgb * alpha + bg.view(3, 1, 1) * (1 - alpha)
    return rgb.contiguous(), alpha


def _get(d: Dict[str, Any], key: str, default=None):
    v = d.get(key, default) if isinstance(d, dict) else default
    return default if v is None else v


def _demo(d: Dict[str, Any], backend: str) -> Problem:
    from ..io.cameras_json import read_cameras_json
    from .demo_scene import build_demo_scene

    scene = build_demo_scene(
        d.get("path"),
        seed=int(_get(d, "scene_seed", 0)),
        width=int(_get(d, "width", 200)),
        height=int(_get(d, "height", 200)),
        fov_deg=float(_get(d, "fov_deg", 60.0)),
        rot_range_deg=tuple(_get(d, "rot_range_deg", (20.0, 40.0))),
        trans=float(_get(d, "trans", 0.1)),
        rebuild=bool(_get(d, "rebuild", False)),
        backend=backend,
    )
    model = scene.load_model()
    ini = init_group(d.get("init"))
    if ini is None:
        init = None
    elif ini.get("rot_deg") is not None:
        init = perturbed_start(scene.gt_c2w, ini, scene.scene_centre)
    else:
        init = scene.init_c2w  # the stored start pose of the demo
    cams = read_cameras_json(scene.path / "cameras.json")
    return Problem(
        model=model,
        query=Query(scene.load_query(), scene.intrinsics, name="query"),
        init_c2w=init,
        gt_c2w=scene.gt_c2w,
        bg=_bg(scene.white_background),
        scene_scale=scene.scene_scale,
        cameras=cams,
        info={"demo_path": str(scene.path), "num_gaussians": model.num_gaussians},
    )


def open_model_folder(data: Dict[str, Any]):
    """(ModelFolder, white_background) of ``data.model_path`` / ``data.iteration``.

    ``data.white_background`` overrides the folder's ``cfg_args`` when it is set.
    """
    from ..io.model_folder import load_model_folder

    mp_s = data.get("model_path")
    if not mp_s or mp_s == "???":
        raise ProblemError(
            "data.model_path is required with data=model_folder (a trained 3DGS output folder)"
        )
    mp = Path(str(mp_s)).expanduser()
    if not mp.is_dir():
        raise ProblemError(f"data.model_path: model folder not found: {mp}")
    mf = load_model_folder(mp, iteration=data.get("iteration"))
    try:
        mf = mf.with_principal_point(data.get("principal_point"))
    except ValueError as e:
        raise ProblemError(f"data.principal_point: {e}") from None
    if mf.principal_point_assumed:
        logger.info("model folder %s: nothing says which principal point its views were fitted "
                    "with; taken as upstream 3DGS's, the image centre, for its dataset's views "
                    "(data.principal_point=dataset if its trainer took the dataset's cx, cy)", mp)
    white = (
        mf.white_background
        if data.get("white_background") is None
        else bool(data["white_background"])
    )
    return mf, white


def _entry(mf, name, what: str):
    """The model folder's cameras.json entry ``name`` (ProblemError naming ``what``)."""
    from ..io.cameras_json import find_entry

    if not mf.cameras:
        raise ProblemError(f"{what}={name!r}: the model folder {mf.path} has no cameras.json")
    try:
        return find_entry(mf.cameras, name)
    except ValueError as e:
        raise ProblemError(f"{what}: {e}") from None


def _dataset(q: Dict[str, Any], mf, white: bool, what: str):
    """The dataset the model was fitted from (``data.query.dataset`` or cfg_args)."""
    from ..io.datasets import read_dataset

    root = q.get("dataset") or mf.cfg.get("source_path")
    if not root or not Path(str(root)).expanduser().is_dir():
        raise ProblemError(
            f"{what} needs the source images: set data.query.dataset (cfg_args source_path "
            f"{mf.cfg.get('source_path')!r} is not a folder here) or data.query.image"
        )
    return read_dataset(Path(str(root)).expanduser(), white_background=white,
                        principal_point=mf.principal_point)


def photo_camera(data: Dict[str, Any], mf, white: bool
                 ) -> Tuple[Optional[Intrinsics], Optional[LensDistortion]]:
    """The camera photo files were taken with: (intrinsics for ``data.intrinsics.camera``, lens).

    The lens is ``data.intrinsics.distortion`` when given. With ``data.intrinsics.camera`` (and
    no ``fx``), that camera's view in the model's source dataset (``data.query.dataset``, else
    cfg_args ``source_path``, when it is a folder here) gives its full camera: the principal
    point and, unless given, the lens distortion, which cameras.json does not keep (fox's own
    photos tracked with ``camera=0``: 0.448 deg median without them, 0.029 with them;
    docs/BATCHES.md). ``(None, lens)`` when there is no such view: cameras.json alone.
    """
    it = data.get("intrinsics") or {}
    lens = LensDistortion.from_config(it)
    if it.get("fx") is not None and mf.principal_point == "centre" and (
            it.get("cx") is not None or it.get("cy") is not None):
        _centred_model_note(str(mf.path))
    if it.get("fx") is not None or it.get("camera") is None:
        return None, lens
    q = data.get("query") or {}
    root = q.get("dataset") or mf.cfg.get("source_path")
    if not root or not Path(str(root)).expanduser().is_dir():
        _no_dataset(str(root or ""), lens is None)
        return None, lens
    entry = _entry(mf, it["camera"], "data.intrinsics.camera")
    view = _view_named(str(Path(str(root)).expanduser().resolve()),
                       os.path.splitext(entry.img_name)[0], white, mf.principal_point)
    if view is None:
        return None, lens
    if lens is None and view.distortion is not None and any(view.distortion):
        lens = LensDistortion(tuple(float(v) for v in view.distortion), view.distortion_model)
    return view.intrinsics, lens


#: A source camera is the photos' when its focal lengths, at the photos' size, are these close.
SAME_FOCAL = 0.01


def source_camera_like(data: Dict[str, Any], mf, white: bool, given: Intrinsics
                       ) -> Optional[Dict[str, Any]]:
    """A camera of the model's source dataset that looks like the photos', with more calibration.

    For photo files given ``data.intrinsics.fx`` (``given``, at their size) and not both a
    principal point and a lens: the first view of the source dataset (``data.query.dataset``,
    else cfg_args ``source_path``; at the model's principal point) of the same shape whose focal
    lengths, at the photos' size, are within ``SAME_FOCAL`` of the given ones, and whose camera
    has a principal point off the centre or a lens distortion the photos were not given:
    ``{"camera"`` (its name for ``data.intrinsics.camera``), ``"principal_point"`` (at the
    photos' size) and ``"distortion"``, each None when the photos were given it}. Photos from
    that camera localize better with its calibration than with what a batch estimates (fox:
    0.016 deg against 0.15). None otherwise, or when no source dataset is at hand.
    """
    it = data.get("intrinsics") or {}
    has_centre = it.get("cx") is not None and it.get("cy") is not None
    if it.get("fx") is None or it.get("camera") is not None or (
            has_centre and it.get("distortion") is not None):
        return None
    root = (data.get("query") or {}).get("dataset") or mf.cfg.get("source_path")
    if not root or not Path(str(root)).expanduser().is_dir():
        return None
    size = (given.width, given.height)
    for name, intr, dist in _source_cameras(str(Path(str(root)).expanduser().resolve()), white,
                                            mf.principal_point):
        if not math.isclose(intr.width / intr.height, size[0] / size[1], rel_tol=0.01):
            continue
        at = intr.resized_to(*size)
        if abs(at.fx / given.fx - 1) > SAME_FOCAL or abs(at.fy / given.fy - 1) > SAME_FOCAL:
            continue
        more_centre = not has_centre and at.cx is not None
        more_lens = it.get("distortion") is None and dist is not None
        if more_centre or more_lens:
            return {"camera": name,
                    "principal_point": [at.cx_px, at.cy_px] if more_centre else None,
                    "distortion": list(dist) if more_lens else None}
    return None


@functools.lru_cache(maxsize=4)
def _source_cameras(root: str, white: bool, principal_point: str):
    """``(name, intrinsics, lens or None)`` of each distinct camera of the dataset at ``root``."""
    from ..io.datasets import read_dataset

    try:
        scene = read_dataset(Path(root), white_background=white, principal_point=principal_point)
    except Exception as e:  # noqa: BLE001 - a hint only: the batch runs as it is
        logger.info("no source camera to compare the photos' with (%s: %s)", type(e).__name__, e)
        return ()
    seen, out = set(), []
    for v in scene.train + scene.test:
        dist = tuple(float(x) for x in v.distortion) if v.distortion is not None and any(
            v.distortion) else None
        key = (v.intrinsics, dist)
        if key not in seen:
            seen.add(key)
            out.append((os.path.splitext(v.name)[0], v.intrinsics, dist))
    return tuple(out)


@functools.lru_cache(maxsize=8)
def _centred_model_note(path: str) -> None:
    """Say once that photos given a principal point meet a model fitted with the image centre."""
    logger.warning(
        "data.intrinsics.cx/cy: the model %s was fitted with the image centre as its views' "
        "principal point (upstream 3DGS's camera; data.principal_point=dataset if its trainer "
        "took its photos' own), so photos of its capture's camera come back to their records "
        "through the centre, not through their calibration (fox: 0.025 deg against 0.54): "
        "leave cx, cy out (a batch then measures the principal point against the model)", path)


@functools.lru_cache(maxsize=8)
def _no_dataset(root: str, no_lens: bool) -> None:
    """Say once that ``data.intrinsics.camera`` comes from cameras.json alone (no dataset here)."""
    logger.info("data.intrinsics.camera: the model's source dataset %s is not a folder here, so "
                "the camera is cameras.json's: principal point at the centre%s (a distorted "
                "camera needs data.intrinsics.cx/cy/distortion or data.query.dataset)",
                repr(root) if root else "(none in cfg_args)",
                ", no lens distortion removed" if no_lens else "")


@functools.lru_cache(maxsize=8)
def _view_named(root: str, stem: str, white: bool, principal_point: str):
    """The view of the dataset at ``root`` whose name has ``stem``, or None (read once)."""
    from ..io.datasets import read_dataset

    try:
        scene = read_dataset(Path(root), white_background=white, principal_point=principal_point)
    except Exception as e:  # noqa: BLE001 - cameras.json still gives the focal lengths
        logger.warning("could not read the source dataset %s for data.intrinsics.camera (%s: %s):"
                       " the principal point is taken at the centre, no distortion removed",
                       root, type(e).__name__, e)
        return None
    view = next((v for v in scene.train + scene.test if os.path.splitext(v.name)[0] == stem),
                None)
    if view is not None:
        logger.info("data.intrinsics.camera: the camera of the dataset's view %s (principal point "
                    "%.1f, %.1f; %s distortion %s)", view.name, view.intrinsics.cx_px,
                    view.intrinsics.cy_px, view.distortion_model, view.distortion)
    return view


def _query_view(q: Dict[str, Any], mf, white: bool, cam):
    """The dataset view of ``data.query.camera`` / ``data.query.index``."""
    if cam is not None:
        scene = _dataset(q, mf, white, f"data.query.camera={q['camera']!r}")
        stem = os.path.splitext(cam.img_name)[0]
        views = [v for v in scene.train + scene.test if os.path.splitext(v.name)[0] == stem]
        if not views:
            raise ProblemError(
                f"data.query.camera={q['camera']!r}: no view named {cam.img_name!r} in the dataset"
            )
        return views[0]
    scene = _dataset(q, mf, white, f"data.query.index={q['index']}")
    split = q.get("split", "test")
    if split not in ("train", "test"):
        raise ProblemError(f"data.query.split must be train or test, got {split!r}")
    views = getattr(scene, split)
    if not (0 <= int(q["index"]) < len(views)):
        raise ProblemError(
            f"data.query.index={q['index']} out of range: split {split!r} has {len(views)} views"
        )
    return views[int(q["index"])]


def _query(d: Dict[str, Any], mf, white: bool, bg: torch.Tensor) -> Tuple[Query, Any, Any]:
    """(query, its dataset view or None, its cameras.json entry or None)."""
    from ..io.cameras_json import entry_to_intrinsics

    q = d.get("query") or {}
    if not [k for k in ("image", "camera", "index") if q.get(k) is not None]:
        raise ProblemError(
            "choose the query: set data.query.image (a file), data.query.camera (a cameras.json "
            "name/id) or data.query.index (a dataset view)"
        )
    cam = None if q.get("camera") is None else _entry(mf, q["camera"], "data.query.camera")
    view, valid = None, None
    if q.get("image") is not None:
        rgb, alpha = read_query_image(q["image"], bg)
        name = Path(str(q["image"])).stem
    else:
        view = _query_view(q, mf, white, cam)
        im = view.load_image(background=bg)
        rgb, alpha, valid, name = im.rgb, im.alpha, im.valid, view.name
    size = (int(rgb.shape[2]), int(rgb.shape[1]))
    it = d.get("intrinsics") or {}
    camera, lens = (None, LensDistortion.from_config(it)) if view is not None \
        else photo_camera(d, mf, white)
    if it.get("fx") is not None or it.get("camera") is not None:
        intr = photo_intrinsics(size, it, mf.cameras, camera)
    elif view is not None:
        intr = view.intrinsics
    elif cam is not None:
        intr = fit_intrinsics(entry_to_intrinsics(cam), size, f"data.query.camera={cam.img_name!r}")
    else:
        raise ProblemError(
            "query intrinsics unknown: set data.intrinsics.fx/fy or data.intrinsics.camera"
        )
    if lens is not None:
        if view is not None:
            raise ProblemError(VIEWS_UNDISTORTED)
        rgb, alpha, valid = lens.undistort(rgb, alpha, intr)
    return Query(rgb.contiguous(), intr, alpha, valid, str(name)), view, cam


def _truth(d: Dict[str, Any], name: str, view, cam, mf) -> Optional[np.ndarray]:
    """The query's true pose: ``data.gt``, else its dataset view's or camera's (or None)."""
    g = d.get("gt") or {}
    if g.get("camera") is not None:
        return np.asarray(_entry(mf, g["camera"], "data.gt.camera").c2w, np.float64)
    if g.get("c2w_file") is not None:
        return read_c2w_file(g["c2w_file"], "data.gt.c2w_file")
    gt = truths(g, [name], [view])[0]
    if gt is None and cam is not None:
        gt = np.asarray(cam.c2w, np.float64)
    return gt


def photos_of(data: Dict[str, Any], mf, white: bool):
    """The model's source photos as ``data.photos`` asks (``auto`` | ``none``).

    From ``data.query.dataset`` when given (the source dataset on this machine), else cfg_args.
    """
    mode = str(data.get("photos") or "auto").lower()
    if mode not in ("auto", "none"):
        raise ProblemError(f"data.photos must be auto or none, got {data.get('photos')!r}")
    dataset = (data.get("query") or {}).get("dataset")
    return source_photos(mf, white, dataset) if mode == "auto" else None


def _model_folder(d: Dict[str, Any]) -> Problem:
    mf, white = open_model_folder(d)
    bg = _bg(white)
    query, view, cam = _query(d, mf, white, bg)
    gt = _truth(d, query.name, view, cam, mf)
    _, inits, errors = start_poses(d.get("init"), [query.name], [gt], mf.cameras,
                                   scene_centre_of(mf.model))
    if errors[0]:
        raise ProblemError(errors[0])
    return Problem(
        model=mf.model,
        query=query,
        init_c2w=inits[0],
        gt_c2w=gt,
        bg=bg,
        scene_scale=cameras_extent([e.c2w for e in mf.cameras]) if mf.cameras else None,
        cameras=list(mf.cameras or []),
        model_side=mf.training_side(),
        photos=photos_of(d, mf, white),
        info={
            "model_path": str(mf.path),
            "iteration": mf.iteration,
            "num_gaussians": mf.model.num_gaussians,
        },
    )


def load_problem(data: Dict[str, Any], backend: str = "auto") -> Problem:
    """The problem described by a ``data`` group mapping (``kind: demo | model_folder``)."""
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind == "demo":
        return _demo(data, backend)
    if kind == "model_folder":
        return _model_folder(data)
    raise ProblemError(f"data.kind must be demo or model_folder, got {kind!r}")
