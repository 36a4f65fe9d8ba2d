"""Poses files: camera poses by image name, and single camera-to-world files.

Poses files give one camera-to-world (OpenCV axes) per image name:

- JSON: ``{"IMG_1.jpg": [[4x4]], ...}`` (or ``{"name": {"c2w": [[4x4]]}}``, or 3x4 matrices);
  an icomma ``poses.json`` (its rows that have a pose and did not fail); a 3DGS
  ``cameras.json`` (``img_name`` -> pose);
- text: one line per image, ``name m00 m01 ... m33`` (16 numbers, row-major; or 12 for 3x4),
  ``#`` comments. Names may not contain spaces there.

A photo is looked up by its name, then by its file name, then by its stem (no extension). A
single pose file (:func:`read_c2w_file`) holds one 4x4 (or 3x4) matrix as text or ``.npy``. Every
matrix passes the one rigid-pose check (``pose.convert.as_rigid``).
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from ..pose.convert import as_rigid

__all__ = ["PoseTable", "PosesFileError", "read_c2w_file", "read_poses_file"]


class PosesFileError(ValueError):
    """A poses file that cannot be read (the message names the config key or argument)."""


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
        raise PosesFileError(f"{what}: not a numeric matrix") from None
    if n not in (12, 16):
        raise PosesFileError(
            f"{what}: expected a 4x4 (or 3x4) camera-to-world matrix, got {n} numbers"
        )
    return as_rigid(np.reshape(np.asarray(v, np.float64), (-1, 4)), what, PosesFileError)


def read_poses_file(path, what: str) -> PoseTable:
    """The poses of a poses file (module docstring); PosesFileError naming ``what`` on bad input."""
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise PosesFileError(f"{what}: file not found: {p}")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise PosesFileError(f"{what}: cannot read {p} ({e})") from None
    if p.suffix.lower() == ".json" or text.lstrip()[:1] in ("{", "["):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise PosesFileError(f"{what}: {p} is not valid JSON ({e})") from None
        poses = _json_poses(data, p, what)
    else:
        poses = _text_poses(text, p, what)
    if not poses:
        raise PosesFileError(f"{what}: {p} holds no poses")
    return PoseTable(poses, str(p))


def _json_poses(data, p: Path, what: str) -> Dict[str, np.ndarray]:
    if isinstance(data, list):  # a 3DGS cameras.json
        from .cameras_json import read_cameras_json

        try:
            return {e.img_name: np.asarray(e.c2w, np.float64) for e in read_cameras_json(p)}
        except ValueError as e:
            raise PosesFileError(f"{what}: {e}") from None
    if not isinstance(data, dict):
        raise PosesFileError(f"{what}: {p} must hold a JSON object of name -> 4x4 c2w")
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
            raise PosesFileError(
                f"{what}: line {n} of {p}: expected 'name' and 16 (or 12) numbers, got "
                f"{line[:80]!r}"
            ) from None
        if len(nums) not in (12, 16):
            raise PosesFileError(
                f"{what}: line {n} of {p}: expected 'name' and 16 (or 12) numbers, got "
                f"{len(nums)} numbers"
            )
        out[parts[0]] = _matrix(nums, f"{what}: line {n} of {p}")
    return out


def read_c2w_file(path, what: str) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world from a text or .npy file; PosesFileError naming ``what``."""
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise PosesFileError(f"{what}: file not found: {p}")
    try:
        arr = np.load(p) if p.suffix == ".npy" else np.loadtxt(p, ndmin=2)
    except Exception as e:  # noqa: BLE001 - any parse error is a user error here
        raise PosesFileError(
            f"{what}: cannot read a 4x4 matrix from {p} ({type(e).__name__}: {e})"
        ) from None
    if np.size(arr) not in (12, 16):
        raise PosesFileError(
            f"{what}: {p} must hold a 4x4 (or 3x4) camera-to-world matrix, got {np.size(arr)} "
            "numbers"
        )
    arr = as_rigid(np.reshape(arr, (-1, 4)), f"{what}: {p}", PosesFileError)
    return arr
