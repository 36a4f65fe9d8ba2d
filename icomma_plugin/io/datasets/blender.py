"""NeRF-synthetic / Blender datasets: `transforms_{train,val,test}.json`.

As 3DGS's `readNerfSyntheticInfo`.

File layout: `{"camera_angle_x": ..., "frames": [{"file_path": "./train/r_0", "transform_matrix":
[[4x4]]}, ...]}`. `transform_matrix` is camera-to-world in Blender/OpenGL camera axes (x right,
y up, z back); it is converted to OpenCV axes with `c2w[:3, 1:3] *= -1` as 3DGS does.

Intrinsics: fx = W / (2 tan(camera_angle_x / 2)); fy = fx (3DGS: FovY = focal2fov(fx, H)) unless
`camera_angle_y` is given. instant-ngp / nerfstudio camera keys (`fl_x, fl_y, cx, cy, w, h`,
distortion, `camera_model`) are honoured when present, globally or per frame (per frame wins),
exactly as the single-file reader does (`transforms_json.frame_camera`, one home for both);
their `cx, cy` put pixel centres at +0.5, so 0.5 is subtracted to reach our convention.
W, H come from `w, h` when given (and must match the image file), else from the image file.

`file_path` may carry an extension or not (then `extension`, default ".png", then any common image
extension is tried). Images with alpha are composited over white (`white_background=True`) or
black, as 3DGS does.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Dict, List, Union

from .base import (
    IMAGE_SUFFIXES,
    DatasetError,
    PathLike,
    SceneData,
    View,
    background_of,
    find_image,
    random_points,
)
from .transforms_json import frame_camera, frame_pose

logger = logging.getLogger(__name__)


def _load_json(path: Path) -> Dict[str, Any]:
    if not path.is_file():
        raise DatasetError(f"Blender transforms file not found: {path}")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"malformed JSON in {path}: {e}") from e
    if not isinstance(data, dict):
        raise DatasetError(
            f"{path}: expected a JSON object with 'frames', got {type(data).__name__}"
        )
    frames = data.get("frames")
    if not isinstance(frames, list):
        raise DatasetError(
            f"{path}: expected key 'frames' with a list of frames, got {type(frames).__name__}"
        )
    return data


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


def read_blender_split(
    root: PathLike,
    transforms_file: str,
    split: str,
    white_background: bool = False,
    extension: str = ".png",
) -> List[View]:
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
        c2w = frame_pose(frame, where)
        image_path = _resolve_image(root, fp, extension, where)
        cam = frame_camera(data, frame, where, image_path)
        name = Path(fp).stem if Path(fp).suffix.lower() in IMAGE_SUFFIXES else Path(fp).name
        views.append(View(name=name, intrinsics=cam.intrinsics, c2w=c2w, image_path=image_path,
                          split=split, background=bg, distortion=cam.distortion,
                          distortion_model=cam.distortion_model, meta={"file_path": fp}))
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
            raise ValueError(
                f"random_init_points must be True or a positive count, got {random_init_points!r}"
            )
        points, colors = random_points(n, seed=seed)
    logger.info("Blender dataset %s: %d train, %d test views", root, len(train), len(test))
    return SceneData(train=train, test=test, points=points, colors=colors,
                     white_background=white_background, source="blender", root=root)
