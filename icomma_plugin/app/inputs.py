"""What a localization is asked to do, read from the tools' ``data`` group.

The photos of a batch (``data.queries``), the start pose of each (``data.init``), their truths
(``data.gt``) and their intrinsics (``data.intrinsics``). Bad input raises :class:`ProblemError`
(a ValueError) whose message names the ``data`` key.

Photo lists (``data.queries``): a folder (its image files, natural order), a glob
(``photos/*.jpg``, ``**`` recursive), a list file (one path per line, relative to the list's
folder, ``#`` comments), a single image, a list of any of these, or a dataset folder (COLMAP,
Blender, transforms.json, LLFF: its views with their undistortion and ground truth). Poses files
(``data.init.poses_file``, ``data.gt.poses_file``) are read by ``io.poses_file``.
"""

from __future__ import annotations

import glob
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Intrinsics
from ..io.poses_file import PoseTable, read_c2w_file, read_poses_file
from ..pose.convert import perturb_pose

__all__ = [
    "DATASET_KINDS",
    "VIEWS_UNDISTORTED",
    "INIT_KEYS",
    "INIT_PIVOTS",
    "LensDistortion",
    "PhotoList",
    "PhotoMismatch",
    "ProblemError",
    "fit_intrinsics",
    "init_group",
    "intrinsics_for_photos",
    "list_photos",
    "natural_key",
    "perturbed_start",
    "photo_intrinsics",
    "start_poses",
    "truths",
]

#: Dataset folders that ``data.queries`` reads as views (a plain cameras.json folder is not one).
DATASET_KINDS = ("colmap", "blender", "transforms_json", "llff")
#: The pivots of a perturbed start (``data.init.pivot``).
INIT_PIVOTS = ("scene_center", "camera", "origin")
#: The ways of giving start poses (``data.init.<key>``); ``data.init=none`` gives none.
INIT_KEYS = ("camera", "c2w_file", "rot_deg", "poses_file", "cameras_json")

_GLOB = re.compile(r"[*?\[]")


class ProblemError(ValueError):
    """Bad input in the configuration (the message names the key)."""


class PhotoMismatch(ProblemError):
    """A photo that does not fit the intrinsics it was given (another size or aspect ratio).

    A per-photo failure in a batch, not a configuration error.
    """


def natural_key(s: str):
    """Sort key putting ``frame2`` before ``frame10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


def _is_image(p: Path) -> bool:
    from ..io.datasets.base import is_image_file

    return is_image_file(p)


@dataclass
class PhotoList:
    """What ``data.queries`` names: image files (with their report names) or dataset views."""

    paths: List[Path]
    names: List[str]
    views: Optional[List[Any]] = None  # dataset View objects (then paths are their images)
    dataset: Optional[Path] = None

    def __len__(self) -> int:
        return len(self.names)


def _dataset_kind(p: Path) -> Optional[str]:
    from ..io.datasets import DatasetError, detect_dataset_kind

    try:
        kind = detect_dataset_kind(p)
    except DatasetError:
        return None
    return kind if kind in DATASET_KINDS else None


def _expand(spec: str, what: str) -> List[Path]:
    p = Path(spec).expanduser()
    if _GLOB.search(spec):
        hits = [Path(h) for h in glob.glob(str(p), recursive=True)]
        out = [h for h in hits if _is_image(h)]
        if not out:
            raise ProblemError(f"{what}: no image files match the pattern {spec!r}")
        return sorted(out, key=lambda x: natural_key(str(x)))
    if p.is_dir():
        out = [c for c in p.iterdir() if _is_image(c)]
        if not out:
            raise ProblemError(f"{what}: no image files (png, jpg, ...) in the folder {p}")
        return sorted(out, key=lambda x: natural_key(x.name))
    if not p.exists():
        raise ProblemError(f"{what}: no such file or folder: {p}")
    if _is_image(p):
        return [p]
    try:
        lines = p.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise ProblemError(
            f"{what}: {p} is neither an image nor a readable list file ({e})"
        ) from None
    out = []
    for n, line in enumerate(lines, 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        q = Path(line).expanduser()
        q = q if q.is_absolute() else p.parent / q
        if not _is_image(q):
            raise ProblemError(
                f"{what}: line {n} of the list file {p} names {line!r}, which is not an "
                "image file"
            )
        out.append(q)
    if not out:
        raise ProblemError(f"{what}: the list file {p} names no images")
    return out


def list_photos(
    spec, what: str = "data.queries", split: str = "all", white_background: Optional[bool] = None,
    principal_point: str = "dataset",
) -> PhotoList:
    """The photos named by ``spec`` (see the module docstring), in order.

    Args:
        spec: a path / glob / list file string, or a list of them.
        what: the config key, for messages.
        split: with a dataset folder: ``train``, ``test`` or ``all`` (train then test).
        white_background: composite RGBA dataset images over white (Blender scenes).
        principal_point: a dataset's views' principal point (``read_dataset``'s): the model's
            (``ModelFolder.principal_point``).
    """
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        raise ProblemError(
            f"{what} is empty: give a folder, a glob, a list file or a dataset folder"
        )
    if isinstance(spec, str):
        root = Path(spec).expanduser()
        if not _GLOB.search(spec) and root.is_dir() and _dataset_kind(root):
            return _dataset_photos(root, what, split, white_background, principal_point)
        specs = [spec]
    elif isinstance(spec, (list, tuple)):
        specs = [str(s) for s in spec]
    else:
        raise ProblemError(
            f"{what} must be a path, a glob or a list of them, got {type(spec).__name__}"
        )
    paths: List[Path] = []
    for s in specs:
        paths += _expand(s, what)
    seen, uniq = set(), []
    for p in paths:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            uniq.append(p)
    base = os.path.commonpath([str(p.resolve().parent) for p in uniq])
    names = [Path(os.path.relpath(p.resolve(), base)).as_posix() for p in uniq]
    return PhotoList(uniq, names)


def _dataset_photos(
    root: Path, what: str, split: str, white_background: Optional[bool], principal_point: str
) -> PhotoList:
    from ..io.datasets import read_dataset

    if split not in ("train", "test", "all"):
        raise ProblemError(f"data.queries_split must be train, test or all, got {split!r}")
    try:
        scene = read_dataset(root, white_background=white_background,
                             principal_point=principal_point)
    except ValueError as e:
        raise ProblemError(f"{what}: {e}") from None
    views = {"train": scene.train, "test": scene.test, "all": scene.train + scene.test}[split]
    views = sorted(views, key=lambda v: natural_key(str(v.name)))
    if not views:
        raise ProblemError(f"{what}: the dataset {root} has no {split} views")
    return PhotoList([v.image_path for v in views], [str(v.name) for v in views], views, root)


# ---------------------------------------------------------------------------------- starts


def init_group(ini) -> Optional[Dict[str, Any]]:
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


def perturbed_start(gt: np.ndarray, ini: Dict[str, Any], scene_centre) -> np.ndarray:
    """``gt`` rotated by ``init.rot_deg`` about ``init.pivot`` and moved by ``init.trans``.

    ``scene_centre``: the pivot ``scene_center`` (``scene_centre_of`` a model).
    """
    rng = np.random.default_rng(int(ini.get("seed") or 0))
    pivot = ini.get("pivot") or "scene_center"
    if pivot not in INIT_PIVOTS:
        raise ProblemError(f"data.init.pivot must be one of {INIT_PIVOTS}, got {pivot!r}")
    if pivot == "scene_center":
        pivot = scene_centre
    try:
        return perturb_pose(
            gt, float(ini["rot_deg"]), float(ini.get("trans") or 0.0), rng, pivot=pivot
        )
    except ValueError as e:
        raise ProblemError(f"data.init: {e}") from None


def start_poses(
    ini_cfg, names: Sequence[str], gts: Sequence[Optional[np.ndarray]], cameras: Sequence[Any],
    scene_centre: Optional[np.ndarray] = None,
) -> Tuple[str, List[Optional[np.ndarray]], List[Optional[str]]]:
    """(mode, start c2w per photo, error per photo) from the ``data.init`` group.

    none (``data.init=none``): no start pose; constant: ``camera`` / ``c2w_file``; per_photo:
    ``poses_file`` / ``cameras_json`` looked up by name (``missing: none`` searches the candidate
    views for a photo the file lacks, ``fail`` records it as failed); perturbed: the truth turned
    by ``rot_deg`` (seed ``seed + index``) about ``pivot`` (``scene_centre`` for
    ``scene_center``). ``cameras``: the model's ``cameras.json`` entries. The one rule for start
    poses: single photos, batches and sequences use it.
    """
    from ..io.cameras_json import find_entry

    ini = init_group(ini_cfg)
    n = len(names)
    if ini is None:
        return "none", [None] * n, [None] * n
    chosen = [k for k in INIT_KEYS if ini.get(k) is not None]
    if len(chosen) != 1:
        raise ProblemError(
            "choose exactly one start pose for the photos: data.init.poses_file, "
            "data.init.cameras_json, data.init.c2w_file, data.init.camera or data.init.rot_deg, or "
            f"none with data.init=none (got {chosen or 'none of them'})"
        )
    key = chosen[0]
    if key == "camera":
        if not cameras:
            raise ProblemError(
                f"data.init.camera={ini['camera']!r}: the model folder has no cameras.json"
            )
        try:
            c2w = np.asarray(find_entry(cameras, ini["camera"]).c2w, np.float64)
        except ValueError as e:
            raise ProblemError(f"data.init.camera: {e}") from None
        return "constant", [c2w] * n, [None] * n
    if key == "c2w_file":
        c2w = read_c2w_file(ini["c2w_file"], "data.init.c2w_file")
        return "constant", [c2w] * n, [None] * n
    if key == "rot_deg":
        out, errs = [], []
        for i, gt in enumerate(gts):
            if gt is None:
                out.append(None)
                errs.append(
                    "data.init.rot_deg perturbs the ground truth, which is unknown for this photo "
                    "(set data.gt.poses_file, or use a dataset folder as data.queries)"
                )
                continue
            sub = dict(ini, seed=int(ini.get("seed") or 0) + i)
            out.append(perturbed_start(gt, sub, scene_centre))
            errs.append(None)
        return "perturbed", out, errs
    missing = str(ini.get("missing") or "fail")
    if missing not in ("fail", "none"):
        raise ProblemError(f"data.init.missing must be fail or none, got {missing!r}")
    what = f"data.init.{key}"
    table = read_poses_file(ini[key], what)
    out, errs = [], []
    for name in names:
        c2w = table.get(name)
        out.append(c2w)
        errs.append(
            None
            if c2w is not None or missing == "none"
            else f"no start pose for {name!r} in {what} ({table.source}); add it, or set "
            "data.init.missing=none to search the candidate views"
        )
    return "per_photo", out, errs


def truths(gt_cfg, names: Sequence[str], views) -> List[Optional[np.ndarray]]:
    """The true pose of each photo (``data.gt``, else the dataset view's), or None."""
    g = gt_cfg or {}
    for k in ("camera", "c2w_file"):
        if g.get(k) is not None:
            raise ProblemError(
                f"data.gt.{k} is one pose for one photo; for a batch use data.gt.poses_file "
                "or data.gt.cameras_json (poses by name)"
            )
    table: Optional[PoseTable] = None
    for k in ("poses_file", "cameras_json"):
        if g.get(k) is not None:
            table = read_poses_file(g[k], f"data.gt.{k}")
    out = []
    for i, name in enumerate(names):
        gt = table.get(name) if table is not None else None
        if gt is None and views is not None and views[i] is not None:
            gt = np.asarray(views[i].c2w, np.float64)
        out.append(gt)
    return out


# ---------------------------------------------------------------------------------- intrinsics


def photo_intrinsics(
    size: Tuple[int, int], it: Dict[str, Any], cameras: Sequence[Any],
    camera: Optional[Intrinsics] = None,
) -> Intrinsics:
    """Intrinsics of a photo of ``size`` (W, H) from the ``data.intrinsics`` group.

    ``fx`` (with ``fy``, ``cx``, ``cy``) are for the size ``width x height`` when those are set,
    else for the photo's own size; a photo of another size is refused. ``camera`` takes a
    cameras.json entry, or ``camera`` (that entry's full camera from the source dataset,
    ``problem.photo_camera``) when given, scaled to the photo when the aspect ratio agrees (1 %).

    Raises:
        ProblemError: naming the key: no intrinsics given, a photo of another size or shape.
    """
    W, H = size
    it = it or {}
    if it.get("fx") is not None:
        w0 = int(it["width"]) if it.get("width") is not None else W
        h0 = int(it["height"]) if it.get("height") is not None else H
        if (w0, h0) != (W, H):
            raise PhotoMismatch(
                f"the photo is {W}x{H} but data.intrinsics.width/height say {w0}x{h0} "
                "(resize the photo, or give intrinsics for its size)"
            )
        fy = it.get("fy") if it.get("fy") is not None else it["fx"]
        try:
            return Intrinsics(
                W,
                H,
                float(it["fx"]),
                float(fy),
                None if it.get("cx") is None else float(it["cx"]),
                None if it.get("cy") is None else float(it["cy"]),
            )
        except ValueError as e:
            raise ProblemError(f"data.intrinsics: {e}") from None
    if it.get("camera") is not None:
        from ..io.cameras_json import entry_to_intrinsics, find_entry

        if not cameras:
            raise ProblemError(
                f"data.intrinsics.camera={it['camera']!r}: the model folder has no cameras.json"
            )
        try:
            src = camera or entry_to_intrinsics(find_entry(cameras, it["camera"]))
        except ValueError as e:
            raise ProblemError(f"data.intrinsics.camera: {e}") from None
        return fit_intrinsics(src, size, f"data.intrinsics.camera={it['camera']!r}")
    raise ProblemError(
        "the photos' intrinsics are unknown: set data.intrinsics.fx (and fy, cx, cy, "
        "width, height) or data.intrinsics.camera (a cameras.json entry)"
    )


def fit_intrinsics(src: Intrinsics, size: Tuple[int, int], what: str) -> Intrinsics:
    """``src`` for a photo of ``size`` (W, H): as is, or scaled when the aspect ratio agrees (1 %).

    Raises:
        PhotoMismatch: another aspect ratio (naming ``what``).
    """
    W, H = size
    if (src.width, src.height) == (W, H):
        return src
    if not math.isclose(src.width / src.height, W / H, rel_tol=0.01):
        raise PhotoMismatch(
            f"the photo is {W}x{H} but {what} is {src.width}x{src.height} (another aspect ratio)"
        )
    return src.resized_to(W, H)


#: Why a lens distortion is refused for dataset views.
VIEWS_UNDISTORTED = (
    "data.intrinsics.distortion is for photo files and frames (data.query.image, a folder or "
    "list of photos, data.sequence): a dataset's views are undistorted by their reader with the "
    "dataset's own coefficients; leave it null")


@dataclass(frozen=True)
class LensDistortion:
    """The lens distortion of raw photos or frames (``data.intrinsics.distortion``).

    The model renders pinhole images, so a photo is remapped to the pinhole camera with the same
    intrinsics before it is localized, as the dataset readers do with their views
    (``io.datasets.undistort_image``); pixels filled from outside the photo are marked invalid.
    On fox's own phone photos (k1 = 0.058) tracked as a folder with their principal point,
    leaving the distortion in put the poses 0.145 deg off (median), against 0.038 undistorted
    (docs/BATCHES.md).

    coefficients: OpenCV's (k1, k2, p1, p2[, k3[, k4, k5, k6]]) for ``model`` "opencv", or
        (k1, k2, k3, k4) for "fisheye". Resolution-free: they act on normalised coordinates.
    """

    coefficients: Tuple[float, ...]
    model: str = "opencv"

    @classmethod
    def from_config(cls, it: Optional[Dict[str, Any]]) -> Optional["LensDistortion"]:
        """The ``data.intrinsics`` group's distortion, or None (none given, or all zero).

        Raises:
            ProblemError: naming ``data.intrinsics.distortion`` / ``distortion_model``.
        """
        from ..io.datasets.base import DISTORTION_MODELS

        it = it or {}
        raw = it.get("distortion")
        if raw is None:
            return None
        model = str(it.get("distortion_model") or "opencv")
        if model not in DISTORTION_MODELS:
            raise ProblemError(f"data.intrinsics.distortion_model must be one of "
                               f"{list(DISTORTION_MODELS)}, got {model!r}")
        sizes = (4,) if model == "fisheye" else (4, 5, 8)
        try:
            coeffs = tuple(float(v) for v in raw)
        except (TypeError, ValueError):
            coeffs = ()
        if len(coeffs) not in sizes or not all(math.isfinite(v) for v in coeffs):
            what = ("k1, k2, k3, k4" if model == "fisheye"
                    else "k1, k2, p1, p2[, k3[, k4, k5, k6]]")
            raise ProblemError(f"data.intrinsics.distortion must be {' or '.join(map(str, sizes))} "
                               f"finite numbers ({what}) for the {model} model, got {raw!r}")
        return cls(coeffs, model) if any(coeffs) else None

    def undistort(self, rgb, alpha, intrinsics: Intrinsics):
        """``(rgb [3, H, W], alpha [1, H, W] or None, valid [1, H, W])`` of a raw photo.

        ``rgb`` / ``alpha``: float tensors of the photo at ``intrinsics`` (its full size).
        """
        import torch

        from ..io.datasets.base import undistort_image

        planes = rgb if alpha is None else torch.cat([rgb, alpha], 0)
        img = np.ascontiguousarray(planes.detach().cpu().float().numpy().transpose(1, 2, 0))
        out, valid = undistort_image(img, intrinsics.K().numpy(), self.coefficients, self.model)
        t = torch.from_numpy(np.ascontiguousarray(out.transpose(2, 0, 1))).clamp_(0.0, 1.0)
        return (t[:3].contiguous(), None if alpha is None else t[3:4].contiguous(),
                torch.from_numpy(valid[None].astype(np.float32)))


def intrinsics_for_photos(it: Dict[str, Any], cameras: Sequence[Any],
                          camera: Optional[Intrinsics] = None
                          ) -> Callable[[Tuple[int, int]], Intrinsics]:
    """``(W, H) -> Intrinsics`` for the photos of a batch or a video (see `photo_intrinsics`).

    The ``data.intrinsics`` group is checked now, without a photo: a missing key or camera is a
    configuration error at once; a photo of another size or shape fails that photo only
    (:class:`PhotoMismatch`).
    """
    it = it or {}
    if it.get("fx") is None and it.get("camera") is None:
        photo_intrinsics((1, 1), it, cameras)  # raises the "intrinsics unknown" error
    if it.get("camera") is not None:
        from ..io.cameras_json import find_entry

        if not cameras:
            raise ProblemError(
                f"data.intrinsics.camera={it['camera']!r}: the model folder has no cameras.json"
            )
        try:
            find_entry(cameras, it["camera"])
        except ValueError as e:
            raise ProblemError(f"data.intrinsics.camera: {e}") from None
    known: Dict[Tuple[int, int], Intrinsics] = {}

    def of(size: Tuple[int, int]) -> Intrinsics:
        if size not in known:
            known[size] = photo_intrinsics(size, it, cameras, camera)
        return known[size]

    return of
