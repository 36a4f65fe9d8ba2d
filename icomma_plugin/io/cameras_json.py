"""The ``cameras.json`` of a 3DGS model folder (upstream ``utils/camera_utils.py::camera_to_JSON``).

A JSON list of ``{id, img_name, width, height, position[3], rotation[3][3], fy, fx}`` where
``position = C2W[:3, 3]`` (camera centre in world) and ``rotation = C2W[:3, :3]`` (camera-to-world
rotation, row-major nested lists), OpenCV/COLMAP axes. ``width``/``height`` are the ORIGINAL image
sizes and ``fx``/``fy`` focal lengths in pixels at that size. Upstream writes test cameras first,
then train; ``id`` is the list index. The principal point is not stored (3DGS assumes the centre).
"""
from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import List, Sequence, Union

import numpy as np

from ..camera import Intrinsics
from ..pose.convert import rigid_problem
from .atomic import write_text_atomic

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]

__all__ = ["CameraEntry", "read_cameras_json", "write_cameras_json", "entry_to_intrinsics",
           "find_entry"]

# Tolerance on R^T R = I for a stored rotation (upstream stores float64 reprs: ~1e-15).
# Largest accepted image side: far above any camera, small enough that sizes and focal ratios
# stay exact floats; a larger width/height is a corrupt field.
_MAX_SIDE = 1 << 20


@dataclass
class CameraEntry:
    """One camera of ``cameras.json``.

    Attributes:
        id: upstream enumeration index.
        img_name: image name as stored (2023 upstream: basename without extension; newer: with it).
        width, height: original image size in pixels.
        c2w: ``[4, 4]`` float64 numpy camera-to-world, OpenCV axes.
        fx, fy: focal lengths in pixels at ``width`` x ``height``.
    """

    id: int
    img_name: str
    width: int
    height: int
    c2w: np.ndarray
    fx: float
    fy: float

    def __post_init__(self):
        self.c2w = np.asarray(self.c2w, dtype=np.float64)
        if self.c2w.shape != (4, 4):
            raise ValueError(f"CameraEntry.c2w must have shape [4, 4], got {list(self.c2w.shape)}")

    @property
    def w2c(self) -> np.ndarray:
        """``[4, 4]`` float64 world-to-camera."""
        R, t = self.c2w[:3, :3], self.c2w[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    def to_json(self) -> dict:
        """Upstream ``camera_to_JSON`` dict (same keys, same order)."""
        return {
            "id": int(self.id),
            "img_name": str(self.img_name),
            "width": int(self.width),
            "height": int(self.height),
            "position": [float(v) for v in self.c2w[:3, 3]],
            "rotation": [[float(v) for v in row] for row in self.c2w[:3, :3]],
            "fy": float(self.fy),
            "fx": float(self.fx),
        }


def _short(v, n: int = 80) -> str:
    """``repr(v)`` cut to ``n`` characters (a corrupt field can be a huge value)."""
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def _is_number(v) -> bool:
    """A finite int or float, not a bool (an int beyond the float range is not finite)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def _parse_entry(e, i: int, path) -> CameraEntry:
    where = f"cameras.json {path}: entry {i}"
    if not isinstance(e, dict):
        raise ValueError(f"{where}: expected an object, got {type(e).__name__}")
    missing = [k for k in ("id", "img_name", "width", "height", "position", "rotation", "fx", "fy")
               if k not in e]
    if missing:
        raise ValueError(f"{where}: missing fields {missing}")
    if not isinstance(e["id"], int) or isinstance(e["id"], bool):
        raise ValueError(f"{where}: field 'id' must be an int, got {_short(e['id'])}")
    if not isinstance(e["img_name"], str):
        raise ValueError(f"{where}: field 'img_name' must be a string, "
                         f"got {_short(e['img_name'])}")
    for k in ("width", "height"):
        v = e[k]
        if not isinstance(v, int) or isinstance(v, bool) or not 0 < v <= _MAX_SIDE:
            raise ValueError(f"{where}: field '{k}' must be an int in 1..{_MAX_SIDE}, "
                             f"got {_short(v)}")
    for k in ("fx", "fy"):
        v = e[k]
        if not _is_number(v) or v <= 0:
            raise ValueError(f"{where}: field '{k}' must be a positive finite number, "
                             f"got {_short(v)}")
    pos = e["position"]
    if not (isinstance(pos, list) and len(pos) == 3 and all(_is_number(v) for v in pos)):
        raise ValueError(f"{where}: field 'position' must be 3 finite numbers, "
                         f"got {_short(pos)}")
    rot = e["rotation"]
    if not (isinstance(rot, list) and len(rot) == 3
            and all(isinstance(r, list) and len(r) == 3 and all(_is_number(v) for v in r)
                    for r in rot)):
        raise ValueError(f"{where}: field 'rotation' must be a 3x3 nested list of finite numbers, "
                         f"got {_short(rot)}")
    c2w = np.eye(4)
    c2w[:3, :3] = rot
    c2w[:3, 3] = pos
    problem = rigid_problem(c2w)
    if problem is not None:
        raise ValueError(f"{where}: field 'rotation' is not a rotation matrix ({problem})")
    return CameraEntry(e["id"], e["img_name"], e["width"], e["height"], c2w,
                       float(e["fx"]), float(e["fy"]))


def read_cameras_json(path: PathLike) -> List[CameraEntry]:
    """Read and validate a ``cameras.json``.

    Returns:
        The entries in file order.

    Raises:
        ValueError: naming the file (and entry index and field) for a missing file, invalid
            JSON (also too deeply nested), a non-list top level, missing/ill-typed fields, a
            width/height outside 1..2^20, non-finite numbers or a non-rotation ``rotation``.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cameras.json {path}: file not found")
    try:
        data = json.loads(path.read_bytes())
    except (ValueError, RecursionError) as e:
        # ValueError: JSONDecodeError, UnicodeDecodeError, an int of more than 4300 digits.
        raise ValueError(f"cameras.json {path}: invalid JSON ({type(e).__name__}: "
                         f"{str(e)[:200]})") from e
    if not isinstance(data, list):
        raise ValueError(f"cameras.json {path}: expected a JSON list of cameras, "
                         f"got {type(data).__name__}")
    return [_parse_entry(e, i, path) for i, e in enumerate(data)]


def write_cameras_json(path: PathLike, entries: Sequence[CameraEntry]) -> None:
    """Write ``entries`` in the upstream layout (compact JSON list, as ``json.dump``), atomically.

    Raises:
        ValueError: if an element is not a CameraEntry.
    """
    out = []
    for i, e in enumerate(entries):
        if not isinstance(e, CameraEntry):
            raise ValueError(f"entries[{i}] must be a CameraEntry, got {type(e).__name__}")
        out.append(e.to_json())
    write_text_atomic(path, json.dumps(out))


def entry_to_intrinsics(entry: CameraEntry) -> Intrinsics:
    """Pinhole intrinsics at the entry's original size, principal point at the image centre."""
    return Intrinsics(int(entry.width), int(entry.height), float(entry.fx), float(entry.fy))


def find_entry(entries: Sequence[CameraEntry], name_or_index: Union[int, str]) -> CameraEntry:
    """Find a camera by ``id`` (int) or by image name (str).

    A name matches ``img_name`` exactly, or ignoring the extension on either side (2023 upstream
    stores names without extension, newer upstream with it).

    Raises:
        ValueError: if nothing (or, for a name, more than one entry) matches; lists a few
            available names/ids.
    """
    if isinstance(name_or_index, (int, np.integer)) and not isinstance(name_or_index, bool):
        hits = [e for e in entries if e.id == int(name_or_index)]
        if not hits:
            ids = [e.id for e in entries]
            raise ValueError(f"no camera with id {name_or_index} (ids: {_preview(ids)})")
        return hits[0]
    if not isinstance(name_or_index, str):
        raise ValueError(f"name_or_index must be an int id or an image name, got {name_or_index!r}")
    hits = [e for e in entries if e.img_name == name_or_index]
    if not hits:
        stem = os.path.splitext(os.path.basename(name_or_index))[0]
        hits = [e for e in entries if os.path.splitext(os.path.basename(e.img_name))[0] == stem]
    if len(hits) == 1:
        return hits[0]
    names = [e.img_name for e in entries]
    if not hits:
        raise ValueError(f"no camera named {name_or_index!r} (names: {_preview(names)})")
    raise ValueError(f"camera name {name_or_index!r} is ambiguous: the entries with ids "
                     f"{[e.id for e in hits]} are all named so; give one of these ids instead")


def _preview(items, n: int = 8) -> str:
    items = list(items)
    more = f", ... ({len(items)} in all)" if len(items) > n else ""
    return ", ".join(repr(x) for x in items[:n]) + more
