"""Exports of estimated poses for other tools: 3DGS cameras.json, COLMAP text, nerfstudio JSON.

    poses = [NamedPose("IMG_0001.jpg", c2w, Intrinsics(1920, 1080, 1500.0, 1500.0)), ...]
    export_poses("out/cameras.json", poses, "cameras_json")   # 3DGS viewers (SIBR, web viewers)
    export_poses("out/sparse/0", poses, "colmap")              # cameras/images/points3D.txt
    export_poses("out/transforms.json", poses, "nerfstudio")   # nerfstudio, instant-ngp, gsplat

Inputs are `NamedPose`s (or anything with `name`, `c2w` and `intrinsics`, such as a dataset
`View`, or a `CameraEntry`): camera-to-world in OpenCV axes (docs/CONTRACTS.md) and pinhole
intrinsics with pixel centres at integers. Each writer converts to its format's conventions:

- cameras.json (upstream `camera_to_JSON`, see `icomma_plugin.io.cameras_json`): C2W rotation
  and camera centre, OpenCV axes, `id` = list index, `img_name` = the pose name. It has no
  principal point: an off-centre one is dropped, with a warning.
- COLMAP text model (`cameras.txt`, `images.txt`, an empty `points3D.txt` so that COLMAP and 3DGS
  accept the folder): one PINHOLE camera per distinct intrinsics, `cx = cx_ours + 0.5` (COLMAP
  puts pixel centres at +0.5); per image the world-to-camera quaternion (w, x, y, z) and
  translation. Names must not contain whitespace (COLMAP's text format splits on it). For
  upstream `render.py`, export into `<folder>/sparse/0` and put the photos in `<folder>/images`.
- nerfstudio `transforms.json`: `transform_matrix` = C2W in OpenGL axes (y up, z back:
  `c2w[:3, 1:3] *= -1`), `cx = cx_ours + 0.5`, `file_path` = the pose name (relative to the json's
  folder), `camera_model` OPENCV without distortion. Intrinsics are written once at the top level
  when every pose shares them, else per frame (both are nerfstudio's format).

Floats are written with `repr` (shortest exact round trip), so reading an export back gives the
same c2w and intrinsics to ~1e-15 for a rigid pose (COLMAP goes through a quaternion). Every file
is written atomically (`icomma_plugin.io.atomic`).
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..camera import Intrinsics
from ..pose.convert import as_rigid, invert_rigid, opencv_to_opengl_c2w
from .atomic import write_text_atomic
from .cameras_json import CameraEntry, entry_to_intrinsics, write_cameras_json

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]

__all__ = ["NamedPose", "FORMATS", "as_named_poses", "export_poses", "export_cameras_json",
           "export_colmap", "export_nerfstudio"]

#: format name -> default file name (inside a folder given as `path`); COLMAP writes a folder.
FORMATS: Dict[str, Optional[str]] = {
    "cameras_json": "cameras.json",
    "colmap": None,
    "nerfstudio": "transforms.json",
}

# Tolerance on R^T R = I of an exported pose (as cameras_json's reader).


@dataclass(frozen=True, eq=False)
class NamedPose:
    """One estimated camera: an image name, its camera-to-world pose and its intrinsics.

    Attributes:
        name: image name, written as each format's image name / file path.
        c2w: ``[4, 4]`` (or ``[3, 4]``) camera-to-world, OpenCV axes; stored as float64 4x4.
        intrinsics: pinhole intrinsics of the image at its full size.
    """

    name: str
    c2w: np.ndarray
    intrinsics: Intrinsics

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name or "\n" in self.name:
            raise ValueError(f"NamedPose.name must be a non-empty one-line string, "
                             f"got {self.name!r}")
        if not isinstance(self.intrinsics, Intrinsics):
            raise ValueError(f"NamedPose {self.name!r}: intrinsics must be an Intrinsics, got "
                             f"{type(self.intrinsics).__name__}")
        object.__setattr__(self, "c2w", _rigid_c2w(self.c2w, f"NamedPose {self.name!r}: c2w"))


def _rigid_c2w(c2w: Any, what: str) -> np.ndarray:
    m = as_rigid(c2w, what)  # a copy: the caller's array may change later
    m.setflags(write=False)
    return m


def as_named_poses(poses: Sequence[Any]) -> List[NamedPose]:
    """`NamedPose`s of `NamedPose`s, `CameraEntry`s or objects with name / c2w / intrinsics.

    Raises:
        ValueError: `poses` is empty or not a sequence, an element has none of these forms, or
            two poses share a name (each format keys images by name).
    """
    if isinstance(poses, (str, bytes, dict)) or not hasattr(poses, "__iter__"):
        raise ValueError(f"poses must be a list of named poses, got {type(poses).__name__}")
    out: List[NamedPose] = []
    for i, p in enumerate(poses):
        if isinstance(p, NamedPose):
            out.append(p)
        elif isinstance(p, CameraEntry):
            out.append(NamedPose(p.img_name, p.c2w, entry_to_intrinsics(p)))
        elif all(hasattr(p, a) for a in ("name", "c2w", "intrinsics")):  # e.g. a dataset View
            out.append(NamedPose(p.name, p.c2w, p.intrinsics))
        else:
            raise ValueError(f"poses[{i}] must be a NamedPose, a CameraEntry or have name, c2w "
                             f"and intrinsics; got {type(p).__name__}")
    if not out:
        raise ValueError("poses is empty: nothing to export")
    seen: Dict[str, int] = {}
    for i, p in enumerate(out):
        if p.name in seen:
            raise ValueError(f"poses[{seen[p.name]}] and poses[{i}] share the name {p.name!r}; "
                             "exported images are keyed by name")
        seen[p.name] = i
    return out


def _f(v: float) -> str:
    """Shortest decimal that reads back as the same float64."""
    return repr(float(v))


def _pixel_centre_half(intr: Intrinsics) -> Tuple[float, float]:
    """(cx, cy) in the +0.5 pixel-centre convention of COLMAP and nerfstudio."""
    return intr.cx_px + 0.5, intr.cy_px + 0.5


def _file_in(path: PathLike, default_name: str) -> Path:
    """`path`, or `path/default_name` when `path` is an existing folder."""
    p = Path(path)
    return p / default_name if p.is_dir() else p


# ----------------------------------------------------------------------------- cameras.json

def export_cameras_json(path: PathLike, poses: Sequence[Any]) -> Path:
    """Write a 3DGS ``cameras.json`` (upstream layout) of `poses`; returns the file written.

    Args:
        path: the file, or a folder to write ``cameras.json`` into.
        poses: see `as_named_poses`.
    """
    poses = as_named_poses(poses)
    off = [p.name for p in poses if not _centred(p.intrinsics)]
    if off:
        log.warning("cameras.json stores no principal point: the off-centre one of %d pose(s) "
                    "(%s%s) is dropped", len(off), ", ".join(off[:3]),
                    ", ..." if len(off) > 3 else "")
    entries = [CameraEntry(i, p.name, p.intrinsics.width, p.intrinsics.height, p.c2w,
                           float(p.intrinsics.fx), float(p.intrinsics.fy))
               for i, p in enumerate(poses)]
    out = _file_in(path, "cameras.json")
    write_cameras_json(out, entries)
    return out


def _centred(intr: Intrinsics) -> bool:
    return (abs(intr.cx_px - (intr.width - 1) / 2.0) < 1e-9
            and abs(intr.cy_px - (intr.height - 1) / 2.0) < 1e-9)


# ----------------------------------------------------------------------------- COLMAP

def export_colmap(folder: PathLike, poses: Sequence[Any]) -> List[Path]:
    """Write a COLMAP text model (cameras.txt, images.txt, empty points3D.txt) into `folder`.

    Poses with equal intrinsics share one PINHOLE camera; image ids follow the order of
    `poses` (from 1). Returns the three files written.

    Raises:
        ValueError: besides `as_named_poses`' errors, a name containing whitespace.
    """
    poses = as_named_poses(poses)
    bad = [p.name for p in poses if any(c.isspace() for c in p.name)]
    if bad:
        raise ValueError(f"COLMAP images.txt cannot hold image names with whitespace: {bad[:5]}"
                         " (rename the images)")
    from .datasets.colmap import rotmat2qvec  # the reader's own conversion

    camera_ids: Dict[Tuple[Any, ...], int] = {}
    image_cam: List[int] = []
    for p in poses:
        k = p.intrinsics
        key = (k.width, k.height, float(k.fx), float(k.fy), k.cx_px, k.cy_px)
        image_cam.append(camera_ids.setdefault(key, len(camera_ids) + 1))

    cam_lines = ["# Camera list with one line of data per camera:",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                 f"# Number of cameras: {len(camera_ids)}"]
    for (w, h, fx, fy, cx, cy), cid in camera_ids.items():
        cam_lines.append(" ".join([str(cid), "PINHOLE", str(w), str(h), _f(fx), _f(fy),
                                   _f(cx + 0.5), _f(cy + 0.5)]))
    img_lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(poses)}, mean observations per image: 0"]
    for i, (p, cid) in enumerate(zip(poses, image_cam), start=1):
        w2c = invert_rigid(p.c2w)
        q = rotmat2qvec(w2c[:3, :3])
        img_lines.append(" ".join([str(i), *map(_f, q), *map(_f, w2c[:3, 3]), str(cid), p.name]))
        img_lines.append("")  # no 2D points
    pts_lines = ["# 3D point list with one line of data per point:",
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
                 "# Number of points: 0, mean track length: 0"]
    folder = Path(folder)
    written = []
    for name, lines in (("cameras.txt", cam_lines), ("images.txt", img_lines),
                        ("points3D.txt", pts_lines)):
        write_text_atomic(folder / name, "\n".join(lines) + "\n")
        written.append(folder / name)
    return written


# ----------------------------------------------------------------------------- nerfstudio

def _intrinsics_keys(intr: Intrinsics) -> Dict[str, Any]:
    cx, cy = _pixel_centre_half(intr)
    return {"fl_x": float(intr.fx), "fl_y": float(intr.fy), "cx": cx, "cy": cy,
            "w": int(intr.width), "h": int(intr.height)}


def export_nerfstudio(path: PathLike, poses: Sequence[Any],
                      shared_intrinsics: Optional[bool] = None) -> Path:
    """Write a nerfstudio ``transforms.json`` of `poses`; returns the file written.

    Args:
        path: the file, or a folder to write ``transforms.json`` into.
        poses: see `as_named_poses`.
        shared_intrinsics: True: one set of intrinsics at the top level (all poses must share
            them); False: per frame; None: top level when all poses share them, else per frame.

    Raises:
        ValueError: besides `as_named_poses`' errors, `shared_intrinsics=True` with poses whose
            intrinsics differ.
    """
    poses = as_named_poses(poses)
    if shared_intrinsics not in (None, True, False):
        raise ValueError(f"shared_intrinsics must be True, False or None, got "
                         f"{shared_intrinsics!r}")
    keys = [_intrinsics_keys(p.intrinsics) for p in poses]
    same = all(k == keys[0] for k in keys)
    if shared_intrinsics and not same:
        differ = next(p.name for p, k in zip(poses, keys) if k != keys[0])
        raise ValueError(f"shared_intrinsics=True, but the intrinsics of {differ!r} differ from "
                         f"those of {poses[0].name!r}")
    top = same if shared_intrinsics is None else shared_intrinsics
    data: Dict[str, Any] = {"camera_model": "OPENCV"}
    if top:
        data.update(keys[0])
    frames = []
    for p, k in zip(poses, keys):
        frame: Dict[str, Any] = {"file_path": p.name}
        if not top:
            frame.update(k)
        frame["transform_matrix"] = [[float(v) for v in row]
                                     for row in opencv_to_opengl_c2w(p.c2w)]
        frames.append(frame)
    data["frames"] = frames
    out = _file_in(path, "transforms.json")
    write_text_atomic(out, json.dumps(data, indent=2) + "\n")  # json writes floats with repr
    return out


# ----------------------------------------------------------------------------- dispatch

def export_poses(path: PathLike, poses: Sequence[Any], format: str) -> List[Path]:
    """Export `poses` in one format; returns the files written.

    Args:
        path: the output file for "cameras_json" / "nerfstudio" (a folder gets the standard
            file name inside it), the output folder for "colmap".
        poses: see `as_named_poses`.
        format: one of `FORMATS` ("cameras_json", "colmap", "nerfstudio").

    Raises:
        ValueError: an unknown `format`, or a writer's error.
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {sorted(FORMATS)}, got {format!r}")
    if format == "cameras_json":
        return [export_cameras_json(path, poses)]
    if format == "colmap":
        return export_colmap(path, poses)
    return [export_nerfstudio(path, poses)]
