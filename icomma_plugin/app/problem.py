"""Assemble a localization problem from a plain configuration mapping (the tools' ``data`` group).

The model, the query photo with its intrinsics and masks, the start pose (or none), the ground
truth when it is known, and the model's cameras (candidate views).

Every bad input raises :class:`ProblemError` (a ValueError) whose message names the key of the
``data`` group that caused it, so the tools print it as one line.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from ..camera import Intrinsics
from ..pose.convert import as_rigid, cameras_extent, perturb_pose
from ..localization.types import Query

logger = logging.getLogger(__name__)

__all__ = [
    "INIT_PIVOTS",
    "Problem",
    "ProblemError",
    "load_c2w_file",
    "load_problem",
    "query_from_view",
    "read_query_image",
]

INIT_PIVOTS = ("scene_center", "camera", "origin")


class ProblemError(ValueError):
    """Bad input in the problem's configuration (the message names the key)."""


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

    @property
    def name(self) -> str:
        """The query's name."""
        return self.query.name

    def candidate_c2ws(self) -> List[np.ndarray]:
        """Camera-to-world of the model's cameras, leaving out any at the query's own pose."""
        out = []
        for e in self.cameras:
            if self.gt_c2w is not None and np.allclose(e.c2w, self.gt_c2w, atol=1e-6):
                continue
            out.append(np.asarray(e.c2w, np.float64))
        return out


def load_c2w_file(path, what: str) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world from a text or .npy file; ProblemError naming ``what``."""
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise ProblemError(f"{what}: file not found: {p}")
    try:
        arr = np.load(p) if p.suffix == ".npy" else np.loadtxt(p, ndmin=2)
    except Exception as e:  # noqa: BLE001 - any parse error is a user error here
        raise ProblemError(
            f"{what}: cannot read a 4x4 matrix from {p} ({type(e).__name__}: {e})"
        ) from None
    if np.size(arr) not in (12, 16):
        raise ProblemError(
            f"{what}: {p} must hold a 4x4 (or 3x4) camera-to-world matrix, got {np.size(arr)} "
            "numbers"
        )
    arr = as_rigid(np.reshape(arr, (-1, 4)), f"{what}: {p}", ProblemError)
    return arr


def _bg(white: bool) -> torch.Tensor:
    return torch.ones(3) if white else torch.zeros(3)


def read_query_image(path, bg: torch.Tensor):
    """(rgb [3, H, W], alpha [1, H, W] or None) of a photo file; RGBA composited over ``bg``."""
    from ..io.datasets import read_image_file

    img = read_image_file(Path(str(path)).expanduser())
    t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float()
    rgb, alpha = t[:3], (t[3:4] if t.shape[0] == 4 else None)
    if alpha is not None:
        rgb = rgb * alpha + bg.view(3, 1, 1) * (1 - alpha)
    return rgb.contiguous(), alpha


def query_from_view(view, bg: torch.Tensor, scale: float = 1.0) -> Query:
    """The :class:`Query` of a dataset view at ``scale`` (its undistortion mask included)."""
    im = view.load_image(scale=scale, background=bg)
    intr = view.intrinsics if scale == 1.0 else view.intrinsics.scaled(scale)
    return Query(im.rgb, intr, im.alpha, im.valid, str(view.name))


def _get(d: Dict[str, Any], key: str, default=None):
    v = d.get(key, default) if isinstance(d, dict) else default
    return default if v is None else v


def _demo(d: Dict[str, Any], backend: str) -> Problem:
    from .demo_scene import build_demo_scene
    from ..io.cameras_json import read_cameras_json

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
    ini = _init_group(d.get("init"))
    if ini is None:
        init = None
    elif ini.get("rot_deg") is not None:
        init = _perturbed(scene.gt_c2w, ini, scene.scene_centre, None)
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
    white = (
        mf.white_background
        if data.get("white_background") is None
        else bool(data["white_background"])
    )
    return mf, white


def _model_folder(d: Dict[str, Any]) -> Problem:
    from ..io.cameras_json import entry_to_intrinsics, find_entry
    from ..io.datasets import read_dataset

    mf, white = open_model_folder(d)
    mp = mf.path
    bg = _bg(white)
    q = d.get("query") or {}

    def entry(name, what):
        if not mf.cameras:
            raise ProblemError(f"{what}={name!r}: the model folder {mp} has no cameras.json")
        try:
            return find_entry(mf.cameras, name)
        except ValueError as e:
            raise ProblemError(f"{what}: {e}") from None

    def dataset(what):
        root = q.get("dataset") or mf.cfg.get("source_path")
        if not root or not Path(str(root)).expanduser().is_dir():
            raise ProblemError(
                f"{what} needs the source images: set data.query.dataset (cfg_args source_path "
                f"{mf.cfg.get('source_path')!r} is not a folder here) or data.query.image"
            )
        return read_dataset(Path(str(root)).expanduser(), white_background=white)

    chosen = [k for k in ("image", "camera", "index") if q.get(k) is not None]
    if not chosen:
        raise ProblemError(
            "choose the query: set data.query.image (a file), data.query.camera (a cameras.json "
            "name/id) or data.query.index (a dataset view)"
        )
    view = cam = None
    valid = None
    if q.get("camera") is not None:
        cam = entry(q["camera"], "data.query.camera")
    if q.get("image") is not None:
        rgb, alpha = read_query_image(q["image"], bg)
        name = Path(str(q["image"])).stem
    elif cam is not None:
        scene = dataset(f"data.query.camera={q['camera']!r}")
        views = [v for v in scene.train + scene.test
                 if os.path.splitext(v.name)[0] == os.path.splitext(cam.img_name)[0]]
        if not views:
            raise ProblemError(
                f"data.query.camera={q['camera']!r}: no view named {cam.img_name!r} in the dataset"
            )
        view = views[0]
    else:
        scene = dataset(f"data.query.index={q['index']}")
        split = q.get("split", "test")
        if split not in ("train", "test"):
            raise ProblemError(f"data.query.split must be train or test, got {split!r}")
        views = getattr(scene, split)
        if not (0 <= int(q["index"]) < len(views)):
            raise ProblemError(
                f"data.query.index={q['index']} out of range: split {split!r} has "
                f"{len(views)} views"
            )
        view = views[int(q["index"])]
    if view is not None:
        im = view.load_image(background=bg)
        rgb, alpha, valid, name = im.rgb, im.alpha, im.valid, view.name
    H, W = int(rgb.shape[1]), int(rgb.shape[2])

    it = d.get("intrinsics") or {}
    if it.get("fx") is not None:
        fy = it.get("fy") if it.get("fy") is not None else it["fx"]
        intr = Intrinsics(
            W,
            H,
            float(it["fx"]),
            float(fy),
            None if it.get("cx") is None else float(it["cx"]),
            None if it.get("cy") is None else float(it["cy"]),
        )
    else:
        src = None
        if it.get("camera") is not None:
            src = entry_to_intrinsics(entry(it["camera"], "data.intrinsics.camera"))
        elif view is not None:
            src = view.intrinsics
        elif cam is not None:
            src = entry_to_intrinsics(cam)
        if src is None:
            raise ProblemError(
                "query intrinsics unknown: set data.intrinsics.fx/fy or data.intrinsics.camera"
            )
        if (src.width, src.height) != (W, H):
            src = Intrinsics(W, H, src.fx * W / src.width, src.fy * H / src.height)
        intr = src

    g = d.get("gt") or {}
    gt = None
    if g.get("camera") is not None:
        gt = entry(g["camera"], "data.gt.camera").c2w
    elif g.get("c2w_file") is not None:
        gt = load_c2w_file(g["c2w_file"], "data.gt.c2w_file")
    elif view is not None:
        gt = view.c2w
    elif cam is not None:
        gt = cam.c2w
    gt = None if gt is None else np.asarray(gt, np.float64)

    init = _initial_pose(d.get("init"), gt, mf)
    query = Query(rgb.contiguous(), intr, alpha, valid, str(name))
    scale = cameras_extent([e.c2w for e in mf.cameras]) if mf.cameras else None
    return Problem(
        model=mf.model,
        query=query,
        init_c2w=init,
        gt_c2w=gt,
        bg=bg,
        scene_scale=scale,
        cameras=list(mf.cameras or []),
        model_side=mf.training_side(),
        info={
            "model_path": str(mp),
            "iteration": mf.iteration,
            "num_gaussians": mf.model.num_gaussians,
        },
    )


def _init_group(ini) -> Optional[Dict[str, Any]]:
    """The ``data.init`` group as a mapping, or None for ``data.init=none``."""
    if ini is None:
        return {}
    if isinstance(ini, str):
        if ini.strip().lower() == "none":
            return None
        raise ProblemError(
            f"data.init must be a group (camera / c2w_file / rot_deg ...) or none, got {ini!r}"
        )
    if not isinstance(ini, dict):
        raise ProblemError(f"data.init must be a group or none, got {type(ini).__name__}")
    return ini


def _perturbed(gt: np.ndarray, ini: Dict[str, Any], scene_centre, mf) -> np.ndarray:
    """``gt`` rotated by ``init.rot_deg`` about ``init.pivot`` and moved by ``init.trans``."""
    rng = np.random.default_rng(int(ini.get("seed") or 0))
    pivot = ini.get("pivot") or "scene_center"
    if pivot not in INIT_PIVOTS:
        raise ProblemError(f"data.init.pivot must be one of {INIT_PIVOTS}, got {pivot!r}")
    if pivot == "scene_center":
        pivot = (
            scene_centre
            if scene_centre is not None
            else mf.model.means.double().median(0).values.numpy()
        )
    try:
        return perturb_pose(
            gt, float(ini["rot_deg"]), float(ini.get("trans") or 0.0), rng, pivot=pivot
        )
    except ValueError as e:
        raise ProblemError(f"data.init: {e}") from None


def _initial_pose(ini, gt: Optional[np.ndarray], mf) -> Optional[np.ndarray]:
    """The start pose from the ``data.init`` group: none | camera | c2w_file | rot_deg."""
    from ..io.cameras_json import find_entry

    ini = _init_group(ini)
    if ini is None:
        return None
    chosen = [k for k in ("camera", "c2w_file", "rot_deg") if ini.get(k) is not None]
    if len(chosen) != 1:
        raise ProblemError(
            "choose exactly one initial pose: data.init.camera, data.init.c2w_file or "
            f"data.init.rot_deg, or none with data.init=none (got {chosen or 'none of them'})"
        )
    if ini.get("camera") is not None:
        if not mf.cameras:
            raise ProblemError(
                f"data.init.camera={ini['camera']!r}: the model folder has no cameras.json"
            )
        try:
            return np.asarray(find_entry(mf.cameras, ini["camera"]).c2w, np.float64)
        except ValueError as e:
            raise ProblemError(f"data.init.camera: {e}") from None
    if ini.get("c2w_file") is not None:
        return load_c2w_file(ini["c2w_file"], "data.init.c2w_file")
    if gt is None:
        raise ProblemError(
            "data.init.rot_deg perturbs the ground truth, but no ground-truth pose is known "
            "for this query (use data.query.camera / index, or data.gt.*)"
        )
    return _perturbed(gt, ini, None, mf)


def load_problem(data: Dict[str, Any], backend: str = "auto") -> Problem:
    """The problem described by a ``data`` group mapping (``kind: demo | model_folder``)."""
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind == "demo":
        return _demo(data, backend)
    if kind == "model_folder":
        return _model_folder(data)
    raise ProblemError(f"data.kind must be demo or model_folder, got {kind!r}")
