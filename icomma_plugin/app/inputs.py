"""Inputs of batches and sequences: lists of photos, poses files, the intrinsics of each photo.

Poses files give the poses by image name. Bad input raises :class:`~.problem.ProblemError`
naming the ``data`` key.

Photo lists (``data.queries``): a folder (its image files, natural order), a glob
(``photos/*.jpg``, ``**`` recursive), a list file (one path per line, relative to the list's
folder, ``#`` comments), a single image, a list of any of these, or a dataset folder (COLMAP,
Blender, transforms.json, LLFF: its views with their undistortion and ground truth).

Poses files (``data.init.poses_file``, ``data.gt.poses_file``), one camera-to-world (OpenCV
axes) per image name:

- JSON: ``{"IMG_1.jpg": [[4x4]], ...}`` (or ``{"name": {"c2w": [[4x4]]}}``, or 3x4 matrices);
  an icomma ``poses.json`` (its rows that have a pose and did not fail); a 3DGS
  ``cameras.json`` (``img_name`` -> pose);
- text: one line per image, ``name m00 m01 ... m33`` (16 numbers, row-major; or 12 for 3x4),
  ``#`` comments. Names may not contain spaces there.

A photo is looked up by its name, then by its file name, then by its stem (no extension).
"""

from __future__ import annotations

import glob
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Intrinsics
from ..pose.convert import as_rigid
from .problem import ProblemError

__all__ = [
    "PhotoList",
    "PhotoMismatch",
    "PoseTable",
    "list_photos",
    "natural_key",
    "photo_intrinsics",
    "read_poses_file",
    "DATASET_KINDS",
]

#: Dataset folders that ``data.queries`` reads as views (a plain cameras.json folder is not one).
DATASET_KINDS = ("colmap", "blender", "transforms_json", "llff")

_GLOB = re.compile(r"[*?\[]")


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
    spec, what: str = "data.queries", split: str = "all", white_background: Optional[bool] = None
) -> PhotoList:
    """The photos named by ``spec`` (see the module docstring), in order.

    Args:
        spec: a path / glob / list file string, or a list of them.
        what: the config key, for messages.
        split: with a dataset folder: ``train``, ``test`` or ``all`` (train then test).
        white_background: composite RGBA dataset images over white (Blender scenes).
    """
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        raise ProblemError(
            f"{what} is empty: give a folder, a glob, a list file or a dataset folder"
        )
    if isinstance(spec, str):
        root = Path(spec).expanduser()
        if not _GLOB.search(spec) and root.is_dir() and _dataset_kind(root):
            return _dataset_photos(root, what, split, white_background)
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
    root: Path, what: str, split: str, white_background: Optional[bool]
) -> PhotoList:
    from ..io.datasets import read_dataset

    if split not in ("train", "test", "all"):
        raise ProblemError(f"data.queries_split must be train, test or all, got {split!r}")
    try:
        scene = read_dataset(root, white_background=white_background)
    except ValueError as e:
        raise ProblemError(f"{what}: {e}") from None
    views = {"train": scene.train, "test": scene.test, "all": scene.train + scene.test}[split]
    views = sorted(views, key=lambda v: natural_key(str(v.name)))
    if not views:
        raise ProblemError(f"{what}: the dataset {root} has no {split} views")
    return PhotoList([v.image_path for v in views], [str(v.name) for v in views], views, root)


# ---------------------------------------------------------------------------------- poses files


class PoseTable:
    """Camera-to-world poses by image name, looked up by name, file name or stem."""

    def __init__(self, poses: Dict[str, np.ndarray], source: str):
        self.poses = dict(poses)
        self.source = source
        self._by_base: Dict[str, List[str]] = {}
        self._by_stem: Dict[str, List[str]] = {}
        for k in self.poses:
            b = os.path.basename(k)
            self._by_base.setdefault(b, []).append(k)
            self._by_stem.setdefault(os.path.splitext(b)[0], []).append(k)

    def __len__(self) -> int:
        return len(self.poses)

    def get(self, name: str) -> Optional[np.ndarray]:
        """The pose of ``name``: by name, else by file name, else by stem (when unambiguous)."""
        if name in self.poses:
            return self.poses[name]
        b = os.path.basename(name)
        for table, key in ((self._by_base, b), (self._by_stem, os.path.splitext(b)[0])):
            hits = table.get(key, [])
            if len(hits) == 1:
                return self.poses[hits[0]]
        return None


def _matrix(v, what: str) -> np.ndarray:
    try:
        n = np.size(np.asarray(v, np.float64))
    except (TypeError, ValueError):
        raise ProblemError(f"{what}: not a numeric matrix") from None
    if n not in (12, 16):
        raise ProblemError(
            f"{what}: expected a 4x4 (or 3x4) camera-to-world matrix, got {n} numbers"
        )
    return as_rigid(np.reshape(np.asarray(v, np.float64), (-1, 4)), what, ProblemError)


def read_poses_file(path, what: str) -> PoseTable:
    """The poses of a poses file (module docstring); ProblemError naming ``what`` on bad input."""
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise ProblemError(f"{what}: file not found: {p}")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ProblemError(f"{what}: cannot read {p} ({e})") from None
    if p.suffix.lower() == ".json" or text.lstrip()[:1] in ("{", "["):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ProblemError(f"{what}: {p} is not valid JSON ({e})") from None
        poses = _json_poses(data, p, what)
    else:
        poses = _text_poses(text, p, what)
    if not poses:
        raise ProblemError(f"{what}: {p} holds no poses")
    return PoseTable(poses, str(p))


def _json_poses(data, p: Path, what: str) -> Dict[str, np.ndarray]:
    if isinstance(data, list):  # a 3DGS cameras.json
        from ..io.cameras_json import read_cameras_json

        try:
            return {e.img_name: np.asarray(e.c2w, np.float64) for e in read_cameras_json(p)}
        except ValueError as e:
            raise ProblemError(f"{what}: {e}") from None
    if not isinstance(data, dict):
        raise ProblemError(f"{what}: {p} must hold a JSON object of name -> 4x4 c2w")
    if isinstance(data.get("photos"), list):  # an icomma poses.json
        out = {}
        for r in data["photos"]:
            if isinstance(r, dict) and r.get("c2w") is not None and r.get("status") != "failed":
                out[str(r["name"])] = _matrix(r["c2w"], f"{what}: {p}: photo {r.get('name')!r}")
        return out
    out = {}
    for k, v in data.items():
        if isinstance(v, dict):
            v = v.get("c2w", v.get("transform_matrix"))
        out[str(k)] = _matrix(v, f"{what}: {p}: entry {k!r}")
    return out


def _text_poses(text: str, p: Path, what: str) -> Dict[str, np.ndarray]:
    out = {}
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        try:
            nums = [float(x) for x in parts[1:]]
        except ValueError:
            raise ProblemError(
                f"{what}: line {n} of {p}: expected 'name' and 16 (or 12) numbers, got "
                f"{line[:80]!r}"
            ) from None
        if len(nums) not in (12, 16):
            raise ProblemError(
                f"{what}: line {n} of {p}: expected 'name' and 16 (or 12) numbers, got "
                f"{len(nums)} numbers"
            )
        out[parts[0]] = _matrix(nums, f"{what}: line {n} of {p}")
    return out


# ---------------------------------------------------------------------------------- intrinsics


def photo_intrinsics(
    size: Tuple[int, int], it: Dict[str, Any], cameras: Sequence[Any]
) -> Intrinsics:
    """Intrinsics of a photo of ``size`` (W, H) from the ``data.intrinsics`` group.

    ``fx`` (with ``fy``, ``cx``, ``cy``) are for the size ``width x height`` when those are set,
    else for the photo's own size; a photo of another size is refused. ``camera`` takes a
    cameras.json entry, scaled to the photo when the aspect ratio agrees (1 %).

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
            src = entry_to_intrinsics(find_entry(cameras, it["camera"]))
        except ValueError as e:
            raise ProblemError(f"data.intrinsics.camera: {e}") from None
        if (src.width, src.height) == (W, H):
            return src
        if not math.isclose(src.width / src.height, W / H, rel_tol=0.01):
            raise PhotoMismatch(
                f"the photo is {W}x{H} but data.intrinsics.camera={it['camera']!r} is "
                f"{src.width}x{src.height} (another aspect ratio)"
            )
        return Intrinsics(W, H, src.fx * W / src.width, src.fy * H / src.height)
    raise ProblemError(
        "the photos' intrinsics are unknown: set data.intrinsics.fx (and fy, cx, cy, "
        "width, height) or data.intrinsics.camera (a cameras.json entry)"
    )
