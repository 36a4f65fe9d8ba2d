"""A `SceneData` from a 3DGS model folder's `cameras.json` plus a folder of images.

`cameras.json` (see `icomma_plugin.io.cameras_json`) holds camera-to-world poses in OpenCV axes
and focal lengths at the original image size, but no split and no principal point (the image
centre is assumed, as 3DGS does). Each entry's `img_name` is matched to a file of the image
folder: the name as given, else with a common image extension (.png, .jpg, ...).

If an image file's size differs from the size stored in `cameras.json` (e.g. a downsampled copy)
but has the same aspect ratio (within 1%), the intrinsics are scaled to the file's size.

Split: `test_names` (a list, or a text file with one name per line) puts those views in test;
else `llffhold` (every llffhold-th view sorted by name); else every view is in train (upstream
writes test cameras first, but the file does not say how many there are).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional, Sequence, Union

from icomma_plugin.camera import Intrinsics
from icomma_plugin.io.cameras_json import entry_to_intrinsics, read_cameras_json

from .base import (
    DatasetError,
    PathLike,
    SceneData,
    View,
    background_of,
    find_image,
    holdout_split,
    image_size,
    name_matches,
    read_name_list,
)

logger = logging.getLogger(__name__)


def read_cameras_json_scene(
    path: PathLike,
    images: Optional[PathLike] = None,
    test_names: Union[None, PathLike, Sequence[str]] = None,
    llffhold: Optional[int] = None,
    white_background: bool = False,
) -> SceneData:
    """Read `<path>/cameras.json` (or `path` itself when it is the file) with images from `images`.

    images: the image folder (absolute, or relative to the model folder). Default: `<path>/images`.
    """
    path = Path(path)
    cam_file = path if path.is_file() else path / "cameras.json"
    folder = cam_file.parent
    if not cam_file.is_file():
        raise DatasetError(f"cameras.json not found: {cam_file}")
    try:
        entries = read_cameras_json(cam_file)
    except DatasetError:
        raise
    except ValueError as e:
        raise DatasetError(str(e)) from e
    if images is None:
        img_dir = folder / "images"
        if not img_dir.is_dir():
            raise DatasetError(f"no image folder for {cam_file}: {img_dir} does not exist; pass "
                               f"images=<folder with the images named as img_name>")
    else:
        img_dir = Path(images)
        if not img_dir.is_absolute() and not img_dir.is_dir():
            img_dir = folder / img_dir
        if not img_dir.is_dir():
            raise DatasetError(f"image folder not found: {images} (for {cam_file})")

    if test_names is not None:
        wanted = set(read_name_list(test_names))
        is_test = [name_matches(e.img_name, wanted) for e in entries]
        if wanted and not any(is_test):
            logger.warning(
                "none of the %d test names matches an img_name of %s", len(wanted), cam_file
            )
    elif llffhold is not None:
        order = sorted(range(len(entries)), key=lambda i: entries[i].img_name)
        flags = holdout_split([entries[i].img_name for i in order], llffhold)
        is_test = [False] * len(entries)
        for i, f in zip(order, flags):
            is_test[i] = f
    else:
        is_test = [False] * len(entries)

    bg = background_of(white_background)
    train: List[View] = []
    test: List[View] = []
    for e, t in zip(entries, is_test):
        image_path = find_image(img_dir, e.img_name, what=f"{cam_file} camera {e.id}")
        intr = entry_to_intrinsics(e)
        w, h = image_size(image_path)
        if (w, h) != (intr.width, intr.height):
            if abs(w / h - intr.width / intr.height) > 0.01 * intr.width / intr.height:
                raise DatasetError(f"image {image_path} is {w}x{h}, which does not match the size "
                                   f"{intr.width}x{intr.height} of camera {e.id} in {cam_file}")
            intr = Intrinsics(w, h, intr.fx * w / intr.width, intr.fy * h / intr.height)
        v = View(name=e.img_name, intrinsics=intr, c2w=e.c2w, image_path=image_path,
                 split="test" if t else "train", background=bg, meta={"id": e.id})
        (test if t else train).append(v)
    logger.info("cameras.json scene %s: %d train, %d test views", cam_file, len(train), len(test))
    return SceneData(
        train=train,
        test=test,
        points=None,
        colors=None,
        white_background=white_background,
        source="cameras_json",
        root=folder,
    )
