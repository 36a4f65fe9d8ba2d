"""NeRF-synthetic / Blender datasets: `transforms_{train,val,test}.json` (3DGS `readNerfSyntheticInfo`).

File layout: `{"camera_angle_x": ..., "frames": [{"file_path": "./train/r_0", "transform_matrix":
[[4x4]]}, ...]}`. `transform_matrix` is camera-to-world in Blender/OpenGL camera axes (x right,
y up, z back); it is converted to OpenCV axes with `c2w[:3, 1:3] *= -1` as 3DGS does.

Intrinsics: fx = W / (2 tan(camera_angle_x / 2)); fy = fx (3DGS: FovY = focal2fov(fx, H)) unless
`camera_angle_y` is given. instant-ngp / nerfstudio keys `fl_x, fl_y, cx, cy, w, h` (and
distortion `k1, k2, k3, p1, p2`) are honoured when present, globally or per frame (per frame
wins); their `cx, cy` put pixel centres at +0.5, so 0.5 is subtracted to reach our convention.
W, H come from `w, h` when given, else from the image file.

`file_path` may carry an extension or not (then `extension`, default ".png", then any common image
extension is tried). Images with alpha are composited over white (`white_background=True`) or
black, as 3DGS does.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

import numpy as np

from icomma_plugin.camera import Intrinsics

from .base import (
    IMAGE_SUFFIXES,
    DatasetError,
    PathLike,
    SceneData,
    View,
    background_of,
    check_pose,
    find_image,
    image_size,
    random_points,
)

logger = logging.getLogger(__name__)

_DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")


def _load_json(path: Path) -> Dict[str, Any]:
    if not path.is_file():
        raise DatasetError(f"Blender transforms file not found: {path}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"malformed JSON in {path}: {e}") from e
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object with 'frames', got {type(data).__name__}")
    frames = data.get("frames")
    if not isinstance(frames, list):
        raise DatasetError(f"{path}: expected key 'frames' with a list of frames, got {type(frames).__name__}")
    return data


def _num(d: Dict[str, Any], key: str, path: Path, where: str) -> Optional[float]:
    if key not in d or d[key] is None:
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise DatasetError(f"{path}: {where} key {key!r} must be a finite number, got {v!r}")
    return float(v)


def _resolve_image(root: Path, file_path: str, extension: str, where: str) -> Path:
    rel = file_path.replace("\\", "/")
    cand = root / rel
    if cand.is_file():
        return cand
    if extension:
        cand = root / (rel + extension)
        if cand.is_file():
            return cand
    p = Path(rel)
    return find_image(root / p.parent, p.name, what=where)


def read_blender_split(root: PathLike, transforms_file: str, split: str, white_background: bool = False,
                       extension: str = ".png") -> List[View]:
    """Views of one transforms file (frames in file order)."""
    root = Path(root)
    path = root / transforms_file
    data = _load_json(path)
    bg = background_of(white_background)
    views: List[View] = []
    for i, frame in enumerate(data["frames"]):
        where = f"{path} frame {i}"
        if not isinstance(frame, dict):
            raise DatasetError(f"{where}: expected an object, got {type(frame).__name__}")
        fp = frame.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise DatasetError(f"{where}: missing or empty 'file_path'")
        if "transform_matrix" not in frame:
            raise DatasetError(f"{where}: missing 'transform_matrix'")
        try:
            m = np.array(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise DatasetError(f"{where}: 'transform_matrix' is not a numeric matrix: {e}") from e
        if m.shape not in ((4, 4), (3, 4)):
            raise DatasetError(f"{where}: 'transform_matrix' must be 4x4, got shape {m.shape}")
        c2w = check_pose(m, where).copy()
        c2w[:3, 1:3] *= -1.0  # OpenGL/Blender (y up, z back) -> OpenCV (y down, z forward)

        image_path = _resolve_image(root, fp, extension, where)

        def get(key):  # per-frame value wins over the global one
            v = _num(frame, key, path, f"frame {i}")
            return v if v is not None else _num(data, key, path, "top-level")

        w, h = get("w"), get("h")
        if w is None or h is None:
            iw, ih = image_size(image_path)
            w = float(iw) if w is None else w
            h = float(ih) if h is None else h
        if w <= 0 or h <= 0 or w != int(w) or h != int(h):
            raise DatasetError(f"{where}: image size must be positive integers, got w={w}, h={h}")
        w, h = int(w), int(h)
        fx, fy = get("fl_x"), get("fl_y")
        angle_x, angle_y = get("camera_angle_x"), get("camera_angle_y")
        if fx is None and angle_x is not None:
            if not 0.0 < angle_x < math.pi:
                raise DatasetError(f"{path}: camera_angle_x must be in (0, pi) radians, got {angle_x}")
            fx = w / (2.0 * math.tan(angle_x / 2.0))
        if fy is None and angle_y is not None:
            if not 0.0 < angle_y < math.pi:
                raise DatasetError(f"{path}: camera_angle_y must be in (0, pi) radians, got {angle_y}")
            fy = h / (2.0 * math.tan(angle_y / 2.0))
        if fx is None and fy is None:
            raise DatasetError(f"{where}: no focal length: expected 'camera_angle_x' (or 'fl_x')")
        fx = fy if fx is None else fx
        fy = fx if fy is None else fy
        cx, cy = get("cx"), get("cy")
        cx = None if cx is None else cx - 0.5
        cy = None if cy is None else cy - 0.5
        try:
            intr = Intrinsics(w, h, fx, fy, cx, cy)
        except ValueError as e:
            raise DatasetError(f"{where}: bad intrinsics: {e}") from e
        dist = [get(k) or 0.0 for k in _DIST_KEYS]
        distortion = tuple(dist) if any(dist) else None
        name = Path(fp).stem if Path(fp).suffix.lower() in IMAGE_SUFFIXES else Path(fp).name
        views.append(View(name=name, intrinsics=intr, c2w=c2w, image_path=image_path, split=split,
                          background=bg, distortion=distortion, meta={"file_path": fp}))
    return views


def read_blender(path: PathLike, white_background: bool = False, eval: bool = True,
                 test_split: str = "test", extension: str = ".png",
                 random_init_points: Union[bool, int] = False, seed: int = 0) -> SceneData:
    """Read a NeRF-synthetic / Blender folder.

    test_split: "test" (`transforms_test.json`, upstream 3DGS) or "val" (`transforms_val.json`,
        as iComMa's reader does).
    eval: keep the test split apart (default); False merges it into train, as upstream does
        without `--eval`.
    random_init_points: False (points = None), True (100 000 points) or a count: upstream's random
        init cloud in [-1.3, 1.3]^3 (grey colours), from `seed`.
    """
    root = Path(path)
    if test_split not in ("test", "val"):
        raise ValueError(f"test_split must be 'test' or 'val', got {test_split!r}")
    if not (root / "transforms_train.json").is_file():
        raise DatasetError(f"not a Blender dataset: {root / 'transforms_train.json'} not found")
    train = read_blender_split(root, "transforms_train.json", "train", white_background, extension)
    test_file = root / f"transforms_{test_split}.json"
    if test_file.is_file():
        test = read_blender_split(root, test_file.name, "test", white_background, extension)
    else:
        logger.warning("%s not found: the test split is empty", test_file)
        test = []
    if not eval:
        for v in test:
            v.split = "train"
        train, test = train + test, []
    points = colors = None
    if random_init_points:
        n = 100_000 if random_init_points is True else int(random_init_points)
        if n <= 0:
            raise ValueError(f"random_init_points must be True or a positive count, got {random_init_points!r}")
        points, colors = random_points(n, seed=seed)
    logger.info("Blender dataset %s: %d train, %d test views", root, len(train), len(test))
    return SceneData(train=train, test=test, points=points, colors=colors,
                     white_background=white_background, source="blender", root=root)
