"""LLFF datasets: `poses_bounds.npy` + `images/` (the format of NeRF's `load_llff_data`).

`poses_bounds.npy` is float [N, 17]: per image a row-major 3x5 matrix `[R | t | hwf]` followed by
(near, far) depth bounds. `[R | t]` is camera-to-world with LLFF camera axes (x down, y right,
z backwards); `hwf` = (image height, image width, focal length) in pixels at the full resolution.
OpenCV axes (x right, y down, z forward) are columns (y_llff, x_llff, -z_llff):
`c2w_cv[:, 0] = c2w[:, 1]`, `c2w_cv[:, 1] = c2w[:, 0]`, `c2w_cv[:, 2] = -c2w[:, 2]`.

Rows match the image files of `images/` (or `images_{factor}/` with `factor`) sorted by name.
The focal length is scaled by (actual width / hwf width) and the principal point is the image
centre. Poses are kept as stored (no recentring or rescaling as NeRF's loader does), and the
bounds are kept per view (`View.bounds`). Split (with `eval`): index % llffhold == 0 -> test.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import List, Optional

import numpy as np

from icomma_plugin.camera import Intrinsics

from .base import (
    DatasetError,
    PathLike,
    SceneData,
    View,
    background_of,
    holdout_split,
    image_size,
    is_image_file,
)
from .colmap import read_points3D_binary, read_points3D_text
from .transforms_json import camera_box

logger = logging.getLogger(__name__)


def llff_to_opencv_c2w(m: np.ndarray) -> np.ndarray:
    """[3, 4] LLFF (down, right, back) camera-to-world -> [4, 4] OpenCV camera-to-world."""
    c2w = np.eye(4)
    c2w[:3, 0] = m[:3, 1]
    c2w[:3, 1] = m[:3, 0]
    c2w[:3, 2] = -m[:3, 2]
    c2w[:3, 3] = m[:3, 3]
    return c2w


def read_poses_bounds(path: PathLike) -> np.ndarray:
    """poses_bounds.npy as a float64 [N, 17] array (3x5 pose + 2 bounds per image).

    Raises:
        DatasetError: a missing, unreadable or malformed file, or non-finite values.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"LLFF poses file not found: {path}")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - numpy raises several types for corrupt files
        raise DatasetError(f"cannot read LLFF poses file {path}: {e}") from e
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise DatasetError(
            f"{path}: expected an array of shape [N, 17] (3x5 pose + 2 bounds per image), "
            f"got shape {tuple(arr.shape)}"
        )
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"{path}: contains non-finite values")
    return arr


def sparse_points_file(root: PathLike) -> Optional[Path]:
    """The COLMAP points file beside an LLFF folder's poses (sparse/0, else sparse/), or None."""
    root = Path(root)
    for folder in (root / "sparse" / "0", root / "sparse"):
        for ext in ("bin", "txt"):
            p = folder / f"points3D.{ext}"
            if p.is_file():
                return p
    return None


def read_sparse_points(root: PathLike):
    """(xyz [N, 3], rgb [N, 3] in [0, 1]) of the COLMAP points beside the poses, or (None, None).

    An empty points file counts as none.
    """
    path = sparse_points_file(root)
    if path is None:
        return None, None
    xyz, rgb = read_points3D_binary(path) if path.suffix == ".bin" else read_points3D_text(path)
    if xyz is None or len(xyz) == 0:
        logger.warning("%s holds no points: no initial point cloud", path)
        return None, None
    logger.info("LLFF dataset %s: %d initial points from %s", root, len(xyz), path)
    return xyz, rgb


def read_llff(path: PathLike, factor: Optional[int] = None, eval: bool = True, llffhold: int = 8,
              white_background: bool = False) -> SceneData:
    """Read an LLFF folder.

    `factor`: use `images_{factor}/` (downsampled copies) instead of `images/`.
    """
    root = Path(path)
    arr = read_poses_bounds(root / "poses_bounds.npy")
    folder = root / ("images" if factor in (None, 1) else f"images_{factor}")
    if not folder.is_dir():
        raise DatasetError(
            f"LLFF image folder not found: {folder}"
            + (
                f" (factor={factor}; create the downsampled copies first)"
                if factor not in (None, 1)
                else ""
            )
        )
    files = sorted((p for p in folder.iterdir() if is_image_file(p)), key=lambda p: p.name)
    if len(files) != len(arr):
        raise DatasetError(f"{root / 'poses_bounds.npy'} has {len(arr)} poses but {folder} has "
                           f"{len(files)} image files")
    poses = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:17]
    is_test = holdout_split([p.name for p in files], llffhold) if eval else [False] * len(files)
    bg = background_of(white_background)
    train: List[View] = []
    test: List[View] = []
    for i, (f, pose, bd, t) in enumerate(zip(files, poses, bounds, is_test)):
        h0, w0, focal = pose[:, 4]
        if h0 <= 0 or w0 <= 0 or focal <= 0:
            raise DatasetError(
                f"{root / 'poses_bounds.npy'} row {i}: hwf must be positive, "
                f"got {pose[:, 4].tolist()}"
            )
        w, h = image_size(f)
        s = w / w0
        intr = Intrinsics(int(w), int(h), float(focal * s), float(focal * h / h0))
        c2w = llff_to_opencv_c2w(pose[:, :4])
        v = View(
            name=f.stem,
            intrinsics=intr,
            c2w=c2w,
            image_path=f,
            split="test" if t else "train",
            background=bg,
            bounds=(float(bd[0]), float(bd[1])),
            meta={"index": i},
        )
        (test if t else train).append(v)
    logger.info("LLFF dataset %s: %d train, %d test views", root, len(train), len(test))
    points, colors = read_sparse_points(root)
    init_box = None
    if points is None:
        centre, half = camera_box([v.c2w for v in train + test])
        init_box = (tuple(float(c) for c in centre), half)
    return SceneData(
        train=train,
        test=test,
        points=points,
        colors=colors,
        white_background=white_background,
        source="llff",
        root=root,
        init_box=init_box,
    )
