"""instant-ngp / nerfstudio captures: one `transforms.json` beside the images.

File layout (instant-ngp `scripts/colmap2nerf.py`, nerfstudio `ns-process-data`):
`{"fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2", ..., "camera_model",
"frames": [{"file_path": "images/0001.jpg", "transform_matrix": [[4x4]], ...}, ...]}`.
Camera keys are read per frame first, then at the top level (a per-frame value wins).

- Poses: `transform_matrix` is camera-to-world in OpenGL camera axes (x right, y up, z back),
  in the capture's own world frame and scale (neither reader's re-centring is applied); it is
  converted to OpenCV axes with `c2w[:3, 1:3] *= -1`.
- Intrinsics: `fl_x`, `fl_y` in pixels, else from `camera_angle_x` / `camera_angle_y`
  (fx = w / (2 tan(angle_x / 2))); one focal length alone serves both axes. `cx`, `cy` put
  pixel centres at +0.5 (a W-wide image spans [0, W]); ours at integers, so 0.5 is subtracted.
  No `cx` / `cy` means the image centre. `w`, `h` are required to match the image file; when
  absent they are read from the image header.
- Lens (`camera_model`, nerfstudio; instant-ngp has none, but `is_fisheye`):
  - perspective: "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL" (and no
    `camera_model`): radial `k1 k2 k3` (r^2, r^4, r^6) and tangential `p1 p2`, i.e. OpenCV
    coefficients (k1, k2, p1, p2, k3); nerfstudio's r^8 term `k4` has no OpenCV equivalent and
    must be 0. (instant-ngp itself ignores `k3` in this mode; it is honoured here, as nerfstudio
    does.)
  - "OPENCV_FISHEYE" (or `is_fisheye: true`): OpenCV's fisheye model with `k1 k2 k3 k4`;
    `p1 p2` must be 0.
  - other nerfstudio models (FISHEYE624, EQUIRECTANGULAR, OMNIDIRECTIONALSTEREO_L/R, VR180_L/R)
    and unknown names raise `DatasetError`.
  Distorted views are undistorted at load time to the pinhole camera with the same K
  (`View.load_image` returns the mask of pixels that are real image content).
- `file_path` is relative to the json's folder, with or without extension. Frames whose image
  file is absent are skipped with one warning that lists them.
- Split (with `eval`): the present frames sorted by name; a test list (`test_list`) or every
  `llffhold`-th frame (index % llffhold == 0, upstream 3DGS for real scenes) is test.
- Initial points: the PLY named by nerfstudio's `ply_file_path` (same world frame as the
  poses), else `random_points` uniform in a cube centred on the point nearest to all optical
  axes and holding every camera (`SceneData.init_box`).

Any malformed value raises `DatasetError` naming the file, the frame and the key.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from icomma_plugin.camera import Intrinsics
from icomma_plugin.pose.convert import as_rigid

from .base import (
    IMAGE_EXTENSIONS,
    IMAGE_SUFFIXES,
    DatasetError,
    PathLike,
    SceneData,
    View,
    background_of,
    holdout_split,
    image_size,
    name_matches,
    random_points,
    read_name_list,
)

logger = logging.getLogger(__name__)

TRANSFORMS_FILE = "transforms.json"

PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
SUPPORTED_CAMERA_MODELS = PERSPECTIVE_MODELS + FISHEYE_MODELS
UNSUPPORTED_CAMERA_MODELS = ("FISHEYE624", "EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L",
                             "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R")


@dataclass
class FrameCamera:
    """The camera of one frame: pinhole intrinsics (our pixel convention) and its lens."""

    intrinsics: Intrinsics
    distortion: Optional[Tuple[float, ...]]
    distortion_model: str  # "opencv" | "fisheye"
    camera_model: str


def load_transforms(path: Path) -> Dict[str, Any]:
    """The parsed JSON object of a transforms file, with a 'frames' list."""
    if not path.is_file():
        raise DatasetError(f"transforms file not found: {path}")
    try:
        data = json.loads(path.read_bytes())
    except (ValueError, RecursionError) as e:  # also too deep, or an int of > 4300 digits
        raise DatasetError(f"malformed JSON in {path}: {type(e).__name__}: {str(e)[:200]}") from e
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object with key 'frames', got "
                           f"{type(data).__name__}")
    if "frames" not in data:
        raise DatasetError(f"{path}: missing key 'frames' (the list of posed images)")
    if not isinstance(data["frames"], list):
        raise DatasetError(f"{path}: key 'frames' must be a list of frames, got "
                           f"{type(data['frames']).__name__}")
    return data


class _Keys:
    """Per-frame-then-top-level lookup of one frame's camera keys, with located errors."""

    def __init__(self, data: Dict[str, Any], frame: Dict[str, Any], where: str):
        self.data, self.frame, self.where = data, frame, where

    def raw(self, key: str) -> Tuple[Any, str]:
        """(value or None, 'frame' | 'top level')."""
        if self.frame.get(key) is not None:
            return self.frame[key], "frame"
        return self.data.get(key), "top level"

    def num(self, key: str) -> Optional[float]:
        v, level = self.raw(key)
        if v is None:
            return None
        try:
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
        except OverflowError:  # an int beyond the float range
            ok = False
        if not ok:
            raise DatasetError(f"{self.where}: key {key!r} ({level}) must be a finite number, "
                               f"got {v!r}")
        return float(v)

    def error(self, key: str, msg: str) -> DatasetError:
        level = self.raw(key)[1]
        return DatasetError(f"{self.where}: key {key!r} ({level}) {msg}")


def frame_pose(frame: Dict[str, Any], where: str) -> np.ndarray:
    """OpenCV camera-to-world [4, 4] of a frame's OpenGL `transform_matrix`."""
    if "transform_matrix" not in frame or frame["transform_matrix"] is None:
        raise DatasetError(f"{where}: missing key 'transform_matrix' (camera-to-world 4x4)")
    try:
        m = np.array(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:  # OverflowError: an int beyond float
        raise DatasetError(f"{where}: key 'transform_matrix' is not a numeric matrix: {e}") from e
    if m.shape not in ((4, 4), (3, 4)):
        raise DatasetError(f"{where}: key 'transform_matrix' must be 4x4 (or 3x4), got shape "
                           f"{m.shape}")
    c2w = as_rigid(m, f"{where}: key 'transform_matrix'", DatasetError)
    c2w[:3, 1:3] *= -1.0  # OpenGL (y up, z back) -> OpenCV (y down, z forward)
    return c2w


def _camera_model(keys: _Keys) -> Tuple[str, str]:
    """(nerfstudio camera model name, our distortion model) of a frame."""
    model, _ = keys.raw("camera_model")
    if model is None:
        fisheye, _ = keys.raw("is_fisheye")  # instant-ngp
        return ("OPENCV_FISHEYE", "fisheye") if fisheye is True else ("OPENCV", "opencv")
    if not isinstance(model, str):
        raise keys.error("camera_model", f"must be a string, got {model!r}")
    if model in UNSUPPORTED_CAMERA_MODELS:
        raise keys.error("camera_model", f"is {model!r}, which is not supported (supported: "
                         f"{', '.join(SUPPORTED_CAMERA_MODELS)}); undistort the images to a "
                         "pinhole camera first")
    if model not in SUPPORTED_CAMERA_MODELS:
        raise keys.error("camera_model", f"is {model!r}, an unknown camera model (supported: "
                         f"{', '.join(SUPPORTED_CAMERA_MODELS)})")
    return model, "fisheye" if model in FISHEYE_MODELS else "opencv"


def frame_camera(data: Dict[str, Any], frame: Dict[str, Any], where: str,
                 image_path: Optional[Path] = None) -> FrameCamera:
    """Intrinsics and lens of one frame (keys per frame first, then top level).

    Args:
        data: the whole transforms object (top-level keys).
        frame: the frame object.
        where: "<file>, frame <i> (<file_path>)" for error messages.
        image_path: the frame's image; read for its size when `w` / `h` are absent, and checked
            against `w` / `h` when present.
    """
    keys = _Keys(data, frame, where)
    w, h = keys.num("w"), keys.num("h")
    for key, v in (("w", w), ("h", h)):
        if v is not None and (v <= 0 or v != int(v)):
            raise keys.error(key, f"must be a positive integer image size, got {v:g}")
    if image_path is not None:
        iw, ih = image_size(image_path)
        if (w is not None and int(w) != iw) or (h is not None and int(h) != ih):
            bad = "w" if (w is not None and int(w) != iw) else "h"
            raise keys.error(bad, f"says the image is {int(w) if w else iw}x{int(h) if h else ih} "
                             f"(w x h), but {image_path} is {iw}x{ih}")
        w = float(iw) if w is None else w
        h = float(ih) if h is None else h
    if w is None or h is None:
        raise keys.error("w" if w is None else "h", "is missing (the image size)")
    w, h = int(w), int(h)

    fx, fy = keys.num("fl_x"), keys.num("fl_y")
    for key, size, axis in (("camera_angle_x", w, "x"), ("camera_angle_y", h, "y")):
        angle = keys.num(key)
        if angle is None or (fx if axis == "x" else fy) is not None:
            continue
        if not 0.0 < angle < math.pi:
            raise keys.error(key, f"must be in (0, pi) radians, got {angle}")
        f = size / (2.0 * math.tan(angle / 2.0))
        fx, fy = (f, fy) if axis == "x" else (fx, f)
    if fx is None and fy is None:
        raise DatasetError(f"{where}: no focal length: missing key 'fl_x' (or 'fl_y', "
                           "'camera_angle_x', 'camera_angle_y'), per frame or at the top level")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    cx, cy = keys.num("cx"), keys.num("cy")
    cx = None if cx is None else cx - 0.5  # +0.5 pixel-centre convention -> ours
    cy = None if cy is None else cy - 0.5
    for key, f in (("fl_x", fx), ("fl_y", fy)):
        if not f > 0:
            raise keys.error(key, f"must give a positive focal length, got {f}")
    intr = Intrinsics(w, h, fx, fy, cx, cy)

    model, dmodel = _camera_model(keys)
    k = {name: keys.num(name) or 0.0 for name in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if dmodel == "fisheye":
        for name in ("p1", "p2"):
            if k[name] != 0.0:
                raise keys.error(name, f"is {k[name]}, but the fisheye model ({model}) has no "
                                 "tangential distortion")
        dist: Tuple[float, ...] = (k["k1"], k["k2"], k["k3"], k["k4"])
    else:
        if k["k4"] != 0.0:
            raise keys.error("k4", f"is {k['k4']}: the r^8 radial term of nerfstudio's perspective "
                             "model has no OpenCV equivalent (supported: k1, k2, k3, p1, p2)")
        dist = (k["k1"], k["k2"], k["p1"], k["p2"], k["k3"])  # OpenCV order
        if dist[4] == 0.0:
            dist = dist[:4]
    return FrameCamera(intr, dist if any(dist) else None, dmodel, model)


def resolve_image(root: Path, file_path: str) -> Optional[Path]:
    """The image file of `file_path` (relative to `root`, with or without extension), or None."""
    rel = file_path.replace("\\", "/")
    cand = root / rel
    if cand.is_file() and cand.suffix.lower() in IMAGE_SUFFIXES:
        return cand
    for ext in IMAGE_EXTENSIONS:
        alt = root / (rel + ext)
        if alt.is_file():
            return alt
    return None


def view_name(file_path: str) -> str:
    """3DGS image_name: the file name without its image extension."""
    p = Path(file_path.replace("\\", "/"))
    return p.stem if p.suffix.lower() in IMAGE_SUFFIXES else p.name


def _relative(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:  # an absolute file_path outside the folder
        return path.as_posix()


def camera_box(c2ws: Sequence[np.ndarray]) -> Tuple[np.ndarray, float]:
    """(centre, half_extent) of a cube that holds every camera, centred where they look.

    The centre is the point nearest (least squares) to all optical axes, or the mean camera
    centre when the axes are near parallel (a forward-facing capture); the half extent is the
    largest per-axis distance from it to a camera centre.
    """
    centres = np.stack([m[:3, 3] for m in c2ws])
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for m in c2ws:
        d = m[:3, 2] / np.linalg.norm(m[:3, 2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ m[:3, 3]
    ev = np.linalg.eigvalsh(A)
    centre = centres.mean(axis=0)
    if ev[0] > 1e-3 * max(ev[-1], 1e-12):
        focus = np.linalg.solve(A, b)
        # in front of most cameras (not behind a forward-facing rig)
        if np.mean([(focus - m[:3, 3]) @ m[:3, 2] > 0 for m in c2ws]) > 0.5:
            centre = focus
    half = float(np.abs(centres - centre).max())
    if not half > 0:
        half = 1.0
    return centre, half


def _read_ply_points(root: Path, data: Dict[str, Any], path: Path):
    from ..ply import read_points_ply

    rel = data["ply_file_path"]
    if not isinstance(rel, str) or not rel:
        raise DatasetError(f"{path}: key 'ply_file_path' (top level) must be a file path, got "
                           f"{rel!r}")
    ply = root / rel
    try:
        xyz, rgb = read_points_ply(ply)
    except ValueError as e:
        raise DatasetError(f"{path}: key 'ply_file_path' names {ply}, which cannot be read: "
                           f"{e}") from e
    if len(xyz) == 0:
        raise DatasetError(f"{path}: key 'ply_file_path' names {ply}, which holds no points")
    return xyz, (np.full_like(xyz, 0.5) if rgb is None else rgb)  # no colours: grey


def read_transforms_json(path: PathLike, white_background: bool = False, eval: bool = True,
                         llffhold: int = 8, test_list: Union[None, PathLike, Sequence[str]] = None,
                         transforms_file: str = TRANSFORMS_FILE, random_init_points: int = 100_000,
                         seed: int = 0) -> SceneData:
    """Read an instant-ngp / nerfstudio capture folder (see the module docstring).

    Args:
        path: the folder holding `transforms_file`.
        white_background: the background RGBA images are composited over (black if False).
        eval: hold out a test split (else every frame is train).
        llffhold: every llffhold-th frame of the name-sorted list is test (upstream: 8).
        test_list: names of the test frames instead (a text file, one per line, or a list).
        transforms_file: the JSON file name inside `path`.
        random_init_points: how many random points to draw when there is no `ply_file_path`.
        seed: seed of the random points.
    """
    root = Path(path)
    tf = root / transforms_file
    data = load_transforms(tf)
    if isinstance(random_init_points, bool) or not isinstance(random_init_points, int) or \
            random_init_points < 1:
        raise ValueError(f"random_init_points must be a positive int, got {random_init_points!r}")

    entries: List[Tuple[str, str, np.ndarray, FrameCamera, Path]] = []
    missing: List[str] = []
    for i, frame in enumerate(data["frames"]):
        if not isinstance(frame, dict):
            raise DatasetError(f"{tf}, frame {i}: expected an object, got {type(frame).__name__}")
        fp = frame.get("file_path")
        if "file_path" not in frame:
            raise DatasetError(f"{tf}, frame {i}: missing key 'file_path'")
        if not isinstance(fp, str) or not fp:
            raise DatasetError(f"{tf}, frame {i}: key 'file_path' must be a non-empty string, "
                               f"got {fp!r}")
        where = f"{tf}, frame {i} ({fp})"
        c2w = frame_pose(frame, where)
        image = resolve_image(root, fp)
        if image is None:
            missing.append(fp)
            continue
        cam = frame_camera(data, frame, where, image)
        entries.append((view_name(fp), fp, c2w, cam, image))
    if missing:
        logger.warning("%s: %d of %d frames name an absent image and are skipped: %s", tf,
                       len(missing), len(data["frames"]), ", ".join(missing))
    if not entries:
        raise DatasetError(f"{tf}: none of its {len(data['frames'])} frames has an image file "
                           f"under {root}")
    entries.sort(key=lambda e: (e[0], e[1]))
    names = [e[0] for e in entries]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise DatasetError(f"{tf}: several frames share the image name(s) {dup[:5]} (key "
                           "'file_path'); view names must be unique")

    if not eval:
        is_test = [False] * len(names)
    elif test_list is not None:
        wanted = set(read_name_list(test_list))
        is_test = [name_matches(fp, wanted) or name_matches(_relative(image, root), wanted)
                   for _, fp, _, _, image in entries]
        if wanted and not any(is_test):
            logger.warning("none of the %d test-list names matches a frame of %s", len(wanted), tf)
    else:
        is_test = holdout_split(names, llffhold)

    bg = background_of(white_background)
    train: List[View] = []
    test: List[View] = []
    for (name, fp, c2w, cam, image), t in zip(entries, is_test):
        v = View(name=name, intrinsics=cam.intrinsics, c2w=c2w, image_path=image,
                 split="test" if t else "train", background=bg, distortion=cam.distortion,
                 distortion_model=cam.distortion_model,
                 meta={"file_path": fp, "camera_model": cam.camera_model})
        (test if t else train).append(v)

    init_box = None
    if data.get("ply_file_path") is not None:
        points, colors = _read_ply_points(root, data, tf)
    else:
        centre, half = camera_box([e[2] for e in entries])
        points, colors = random_points(random_init_points, seed=seed, extent=half, center=centre)
        if not np.isfinite(points).all():
            raise DatasetError(f"{tf}: camera centres (key 'transform_matrix') are too large to "
                               f"place random initial points around (box half-size {half:g})")
        init_box = (tuple(float(c) for c in centre), half)
    logger.info("transforms.json dataset %s: %d train, %d test views, %d %s points", root,
                len(train), len(test), len(points), "random" if init_box else "PLY")
    return SceneData(train=train, test=test, points=points, colors=colors,
                     white_background=white_background, source="transforms_json", root=root,
                     init_box=init_box)
