"""Dataset readers: every on-disk dataset format becomes a `SceneData` of `View`s.

    scene = read_dataset("path/to/scene", white_background=True)
    view = scene.test[0]
    rgb, alpha = view.load(scale=0.5)          # [3, H, W], [1, H, W] or None
    K = view.intrinsics.scaled(0.5).K()        # matches rgb exactly
    w2c = view.w2c                             # [4, 4] float64, OpenCV axes

Conventions (docs/CONTRACTS.md): `View.c2w` is camera-to-world, float64, OpenCV camera axes
(x right, y down, z forward); pixel centres at integers (image centre (W - 1) / 2). Each reader
converts its file's conventions (Blender/OpenGL axes, LLFF axes, COLMAP's +0.5 pixel origin).

Readers (see each module's docstring for the file layout):
- `read_colmap` (colmap.py): `sparse/0` or `sparse/` (binary or text) + `images/`.
- `read_blender` (blender.py): `transforms_{train,val,test}.json`.
- `read_llff` (llff.py): `poses_bounds.npy` + `images/`.
- `read_transforms_json` (transforms_json.py): instant-ngp / nerfstudio single `transforms.json`.
- `read_cameras_json_scene` (cameras_json_reader.py): a 3DGS model folder's `cameras.json` + an
  image folder.
`read_dataset` picks one like 3DGS's `Scene` does (sparse/ first, then transforms_train.json),
then transforms.json, then poses_bounds.npy, then cameras.json.

`view.load_image(scale)` also returns the mask of valid pixels (real image content, not filled
by undistortion): `ViewImage(rgb, alpha, valid)`; `valid` is None when every pixel is valid.
"""
from __future__ import annotations

import inspect
import logging
from pathlib import Path
from typing import Any, Callable, Dict, Optional

from .base import (
    IMAGE_EXTENSIONS,
    DatasetError,
    SceneData,
    View,
    ViewImage,
    exif_orientation,
    random_points,
    read_image_file,
    shared_data_root,
    undistort_image,
)
from .blender import read_blender
from .cameras_json_reader import read_cameras_json_scene
from .colmap import missing_model_files, read_colmap
from .llff import read_llff
from .transforms_json import read_transforms_json

__all__ = [
    "DatasetError",
    "IMAGE_EXTENSIONS",
    "PRINCIPAL_POINTS",
    "READERS",
    "SceneData",
    "View",
    "ViewImage",
    "detect_dataset_kind",
    "exif_orientation",
    "random_points",
    "read_blender",
    "read_cameras_json_scene",
    "read_colmap",
    "read_dataset",
    "read_image_file",
    "read_llff",
    "shared_data_root",
    "read_transforms_json",
    "undistort_image",
]

logger = logging.getLogger(__name__)

READERS: Dict[str, Callable[..., SceneData]] = {
    "colmap": read_colmap,
    "blender": read_blender,
    "transforms_json": read_transforms_json,
    "llff": read_llff,
    "cameras_json": read_cameras_json_scene,
}

_LOOKED_FOR = (
    "sparse/ (COLMAP), transforms_train.json (Blender/NeRF-synthetic), transforms.json "
    "(instant-ngp / nerfstudio), poses_bounds.npy (LLFF), cameras.json (3DGS model folder, with "
    "an image folder)"
)


def detect_dataset_kind(path) -> str:
    """The kind of dataset folder: 'colmap', 'blender', 'transforms_json', 'llff', 'cameras_json'.

    Checked in 3DGS's dispatch order, with transforms.json after transforms_train.json. A
    `sparse/` folder whose model lacks its cameras or images file beside a `poses_bounds.npy`
    is an LLFF folder (a warning names the missing file): its poses are complete, and the
    LLFF reader still takes the model's points.
    """
    root = Path(path)
    if not root.exists():
        raise DatasetError(f"dataset path does not exist: {root}")
    if not root.is_dir():
        raise DatasetError(
            f"dataset path is not a folder: {root} (expected a folder with {_LOOKED_FOR})"
        )
    if (root / "sparse").is_dir():
        missing = missing_model_files(root)
        if not missing or not (root / "poses_bounds.npy").is_file():
            return "colmap"
        logger.warning("%s: the COLMAP model has no %s (nor its .txt twin): using the LLFF poses "
                       "of %s instead", root, " or ".join(missing), root / "poses_bounds.npy")
        return "llff"
    if (root / "transforms_train.json").is_file():
        return "blender"
    if (root / "transforms.json").is_file():
        return "transforms_json"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    if (root / "cameras.json").is_file():
        return "cameras_json"
    raise DatasetError(f"unrecognised dataset folder {root}: looked for {_LOOKED_FOR}; found none")


#: Where a dataset's views put their principal point: ``dataset``, as its files give it (a COLMAP
#: or transforms.json camera's cx, cy); ``centre``, at the image centre, as upstream 3DGS trains and
#: renders every view whatever its files say (its cameras hold field-of-view angles alone).
PRINCIPAL_POINTS = ("dataset", "centre")


def read_dataset(path, kind: Optional[str] = None, *, white_background: Optional[bool] = None,
                 principal_point: str = "dataset", **kwargs: Any) -> SceneData:
    """Read any supported dataset folder.

    Args:
        path: the dataset folder.
        kind: force a reader ('colmap', 'blender', 'transforms_json', 'llff', 'cameras_json');
            None detects it (`detect_dataset_kind`).
        white_background: composite RGBA images over white (True) or black (False); None keeps
            the reader's default. Formats whose images have no alpha ignore it.
        principal_point: ``"dataset"`` or ``"centre"`` (`PRINCIPAL_POINTS`): ``"centre"`` moves
            every view's principal point to its image centre, the camera a model fitted by
            upstream 3DGS was fitted with (the images and the lens distortion stay as read).
        **kwargs: passed to that reader.

    Raises:
        ValueError: an unknown ``kind``, or an argument the reader does not take (the message
            names the reader and what it accepts).
        DatasetError: the folder is not a dataset, or the reader's own errors.
    """
    if kind is None:
        kind = detect_dataset_kind(path)
    elif kind not in READERS:
        raise ValueError(f"kind must be one of {sorted(READERS)}, got {kind!r}")
    reader = READERS[kind]
    accepted = [p for p in inspect.signature(reader).parameters if p != "path"]
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise ValueError(f"{reader.__name__} ({kind} dataset at {path}) does not take {unknown}; "
                         f"it accepts {accepted}")
    if principal_point not in PRINCIPAL_POINTS:
        raise ValueError(f"principal_point must be one of {list(PRINCIPAL_POINTS)}, got "
                         f"{principal_point!r}")
    if white_background is not None and "white_background" in accepted:
        kwargs["white_background"] = bool(white_background)
    scene = reader(path, **kwargs)
    if principal_point == "centre":
        for view in scene.train + scene.test:
            view.intrinsics = view.intrinsics.centred()
    return scene
