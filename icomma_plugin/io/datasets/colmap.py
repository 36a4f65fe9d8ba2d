"""COLMAP sparse reconstructions (3DGS `readColmapSceneInfo`), binary and text.

Files: `<root>/sparse/0/{cameras,images,points3D}.{bin,txt}` (or directly in `<root>/sparse/`);
for each of the three, the `.bin` file is used when present, else the `.txt` one. Layouts are
COLMAP's (`src/colmap/scene/reconstruction_io.cc`, `scripts/python/read_write_model.py`), little
endian:
- cameras.bin: uint64 count; per camera int32 camera_id, int32 model_id, uint64 width,
  uint64 height, float64 x num_params(model).
- images.bin: uint64 count; per image int32 image_id, float64 qw qx qy qz tx ty tz, int32
  camera_id, NUL-terminated name, uint64 num_points2D, (float64 x, float64 y, int64 point3D_id)
  x num_points2D.
- points3D.bin: uint64 count; per point uint64 id, float64 x y z, uint8 r g b, float64 error,
  uint64 track_length, (int32 image_id, int32 point2D_idx) x track_length.

Poses: `qvec` is (w, x, y, z) and with `tvec` gives world-to-camera: `w2c = [R(q) | t]`;
`c2w = inv(w2c)`. Camera axes are OpenCV's already.

Intrinsics: COLMAP puts pixel centres at +0.5 (the image spans [0, W]); ours at integers, so
`cx = cx_colmap - 0.5` (likewise cy). A principal point off the image centre is KEPT in
`Intrinsics(cx, cy)` (None when exactly centred): the renderer carries the offset in its
projection matrix (`camera_matrices(..., cx, cy)`), whereas upstream 3DGS ignores it.
Supported models: SIMPLE_PINHOLE, PINHOLE (no distortion), SIMPLE_RADIAL, RADIAL, OPENCV,
FULL_OPENCV (distorted: the view keeps the OpenCV coefficients in `View.distortion` and
`View.load` undistorts each image to the pinhole camera with the same K and size with
`cv2.initUndistortRectifyMap` + `cv2.remap`; the border that maps from outside the image is
black). Fisheye and other models raise `DatasetError`: run `colmap image_undistorter` first.

Images are sorted by name. Registered images whose file is missing raise; files in the image
folder that COLMAP did not register are skipped (logged). Split: with `eval`, a test list (the
`test_list` argument, or `sparse/0/test.txt` when present, as newer upstream) or every
`llffhold`-th image of the sorted list (upstream: llffhold = 8).
"""
from __future__ import annotations

import logging
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from icomma_plugin.camera import Intrinsics
from icomma_plugin.pose.convert import invert_rigid

from .base import (
    DatasetError,
    PathLike,
    SceneData,
    View,
    background_of,
    holdout_split,
    is_image_file,
    name_matches,
    read_name_list,
)

logger = logging.getLogger(__name__)

# model_id -> (name, number of parameters), as in COLMAP's camera_models.h
CAMERA_MODELS: Dict[int, Tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
CAMERA_MODEL_IDS: Dict[str, int] = {name: mid for mid, (name, _) in CAMERA_MODELS.items()}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


@dataclass
class ColmapCamera:
    """One camera of cameras.bin/.txt: COLMAP's model name and parameters, as stored."""

    id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    """One registered image of images.bin/.txt: its world-to-camera pose and camera id."""

    id: int
    qvec: np.ndarray  # (w, x, y, z)
    tvec: np.ndarray
    camera_id: int
    name: str
    num_points2D: int = 0
    # with_points=True: the 2D points ([N, 2], COLMAP's pixel convention) and their 3D point ids
    # ([N] int64, -1: none); None otherwise
    xys: Optional[np.ndarray] = None
    point3D_ids: Optional[np.ndarray] = None


# ----------------------------------------------------------------------------- math

def qvec2rotmat(qvec: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z) (normalised first), as COLMAP's qvec2rotmat."""
    q = np.asarray(qvec, dtype=np.float64)
    q = q / np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * z * x + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * z * x - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y],
    ])


def rotmat2qvec(R: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z), w >= 0, of a rotation matrix (COLMAP's rotmat2qvec)."""
    R = np.asarray(R, dtype=np.float64)
    Rxx, Ryx, Rzx, Rxy, Ryy, Rzy, Rxz, Ryz, Rzz = R.flat
    K = np.array([
        [Rxx - Ryy - Rzz, 0, 0, 0],
        [Ryx + Rxy, Ryy - Rxx - Rzz, 0, 0],
        [Rzx + Rxz, Rzy + Ryz, Rzz - Rxx - Ryy, 0],
        [Ryz - Rzy, Rzx - Rxz, Rxy - Ryx, Rxx + Ryy + Rzz],
    ]) / 3.0
    eigvals, eigvecs = np.linalg.eigh(K)
    q = eigvecs[[3, 0, 1, 2], np.argmax(eigvals)]
    if q[0] < 0:
        q = -q
    return q


def colmap_w2c(qvec: Sequence[float], tvec: Sequence[float]) -> np.ndarray:
    """World-to-camera [4, 4] from COLMAP's qvec (w first) and tvec."""
    w2c = np.eye(4)
    w2c[:3, :3] = qvec2rotmat(qvec)
    w2c[:3, 3] = np.asarray(tvec, dtype=np.float64)
    return w2c


def camera_intrinsics(
    cam: ColmapCamera, where: str = ""
) -> Tuple[Intrinsics, Optional[Tuple[float, ...]]]:
    """(pinhole Intrinsics in our pixel convention, OpenCV distortion coefficients or None)."""
    p = [float(v) for v in cam.params]
    m = cam.model
    dist: Optional[Tuple[float, ...]] = None
    if m == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx = fy = f
    elif m == "PINHOLE":
        fx, fy, cx, cy = p
    elif m == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        fx = fy = f
        dist = (k, 0.0, 0.0, 0.0)
    elif m == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        dist = (k1, k2, 0.0, 0.0)
    elif m == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        dist = (k1, k2, p1, p2)
    elif m == "FULL_OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = p
        dist = (k1, k2, p1, p2, k3, k4, k5, k6)
    else:
        raise DatasetError(
            f"{where}: camera {cam.id} uses COLMAP model {m}, which is not supported (supported: "
            f"{', '.join(SUPPORTED_MODELS)}); undistort the dataset with `colmap image_undistorter`"
        )
    if dist is not None and not all(np.isfinite(dist)):
        raise DatasetError(f"{where}: camera {cam.id} ({m}) has non-finite distortion {dist}")
    if dist is not None and not any(dist):
        dist = None
    try:  # OverflowError: a width too large for a float (corrupt text file)
        cx, cy = cx - 0.5, cy - 0.5
        if abs(cx - (cam.width - 1) / 2.0) < 1e-9 and abs(cy - (cam.height - 1) / 2.0) < 1e-9:
            cx = cy = None
        intr = Intrinsics(int(cam.width), int(cam.height), fx, fy, cx, cy)
    except (ValueError, OverflowError) as e:
        raise DatasetError(f"{where}: camera {cam.id} ({m}) has invalid intrinsics: {e}") from e
    return intr, dist


# ----------------------------------------------------------------------------- binary

class _BinReader:
    """Cursor over a file's bytes; any short read raises a DatasetError naming the file."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str, what: str):
        fmt = "<" + fmt
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.data):
            raise DatasetError(
                f"truncated COLMAP binary file {self.path}: needed {n} bytes for {what} at offset "
                f"{self.pos}, only {len(self.data) - self.pos} left (file size {len(self.data)})"
            )
        out = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += n
        return out

    def skip(self, n: int, what: str):
        if self.pos + n > len(self.data):
            raise DatasetError(
                f"truncated COLMAP binary file {self.path}: needed {n} bytes for {what} at offset "
                f"{self.pos}, only {len(self.data) - self.pos} left (file size {len(self.data)})"
            )
        self.pos += n

    def read_cstring(self, what: str) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise DatasetError(
                f"truncated COLMAP binary file {self.path}: unterminated {what} "
                f"at offset {self.pos}"
            )
        raw = self.data[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise DatasetError(f"{self.path}: {what} at offset {self.pos} is not UTF-8: {e}") from e

    def check_count(self, count: int, min_bytes_each: int, what: str):
        left = len(self.data) - self.pos
        if count * min_bytes_each > left:
            raise DatasetError(
                f"truncated or corrupt COLMAP binary file {self.path}: header says {count} {what} "
                f"(at least {count * min_bytes_each} bytes) but only {left} bytes follow"
            )

    def finish(self):
        if self.pos != len(self.data):
            logger.warning("%s: %d trailing bytes ignored", self.path, len(self.data) - self.pos)


def read_cameras_binary(path: PathLike) -> Dict[int, ColmapCamera]:
    """cameras.bin: camera id -> camera.

    Raises:
        DatasetError: a truncated or malformed file, or an unknown camera model id.
    """
    r = _BinReader(Path(path))
    (n,) = r.read("Q", "the camera count")
    r.check_count(n, 24, "cameras")
    cams: Dict[int, ColmapCamera] = {}
    for i in range(n):
        cid, model_id, w, h = r.read("iiQQ", f"camera {i} header")
        if model_id not in CAMERA_MODELS:
            raise DatasetError(
                f"{path}: camera {cid} has unknown COLMAP camera model id {model_id} "
                f"(known ids: {sorted(CAMERA_MODELS)})"
            )
        name, nparams = CAMERA_MODELS[model_id]
        params = np.array(r.read("d" * nparams, f"camera {cid} parameters"), dtype=np.float64)
        cams[cid] = ColmapCamera(cid, name, int(w), int(h), params)
    r.finish()
    return cams


_POINT2D = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])


def read_images_binary(path: PathLike, with_points: bool = False) -> Dict[int, ColmapImage]:
    """images.bin: image id -> image (the 2D points only counted, unless ``with_points``).

    Raises:
        DatasetError: a truncated or malformed file.
    """
    r = _BinReader(Path(path))
    (n,) = r.read("Q", "the image count")
    r.check_count(n, 73, "images")
    images: Dict[int, ColmapImage] = {}
    for i in range(n):
        vals = r.read("idddddddi", f"image {i} header")
        name = r.read_cstring(f"image {vals[0]} name")
        (npts,) = r.read("Q", f"image {vals[0]} point count")
        raw = None
        if with_points:
            r.check_count(npts, 24, f"2D points of image {vals[0]}")
            raw = np.frombuffer(r.data, dtype=_POINT2D, count=npts, offset=r.pos)
        r.skip(24 * npts, f"image {vals[0]} 2D points")
        images[vals[0]] = ColmapImage(
            vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8], name, npts,
            None if raw is None else np.stack([raw["x"], raw["y"]], 1),
            None if raw is None else raw["id"].copy(),
        )
    r.finish()
    return images


def read_points3D_binary(path: PathLike, with_ids: bool = False):
    """points3D.bin: (xyz [N, 3] float64, rgb [N, 3] float64 in [0, 1]) (and ids).

    ``with_ids``: the points' ids too, as a third item (a list of N ints: COLMAP's are uint64).
    """
    r = _BinReader(Path(path))
    (n,) = r.read("Q", "the point count")
    r.check_count(n, 51, "points")
    xyz = np.empty((n, 3), dtype=np.float64)
    rgb = np.empty((n, 3), dtype=np.float64)
    ids = []
    for i in range(n):
        vals = r.read("QdddBBBd", f"point {i}")
        ids.append(vals[0])
        xyz[i] = vals[1:4]
        rgb[i] = vals[4:7]
        (tl,) = r.read("Q", f"point {vals[0]} track length")
        r.skip(8 * tl, f"point {vals[0]} track")
    r.finish()
    _check_points(xyz, path)
    return (xyz, rgb / 255.0, ids) if with_ids else (xyz, rgb / 255.0)


# ----------------------------------------------------------------------------- text

def _text_lines(path: Path):
    """Yield (line number, stripped line) of the non-comment lines.

    Empty lines are kept (images.txt needs them).
    """
    if not path.is_file():
        raise DatasetError(f"COLMAP text file not found: {path}")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise DatasetError(f"COLMAP text file {path} is not UTF-8 text: {e}") from None
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s.startswith("#"):
            continue
        yield no, s


def _parse(fn, tok: str, path: Path, no: int, what: str):
    try:
        return fn(tok)
    except ValueError:
        raise DatasetError(f"{path}:{no}: {what} must be a number, got {tok!r}") from None


def read_cameras_text(path: PathLike) -> Dict[int, ColmapCamera]:
    """cameras.txt: camera id -> camera.

    Raises:
        DatasetError: a malformed line (the message names the file and line).
    """
    path = Path(path)
    cams: Dict[int, ColmapCamera] = {}
    for no, s in _text_lines(path):
        if not s:
            continue
        el = s.split()
        if len(el) < 4:
            raise DatasetError(
                f"{path}:{no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {s!r}"
            )
        cid = _parse(int, el[0], path, no, "CAMERA_ID")
        model = el[1]
        if model not in CAMERA_MODEL_IDS:
            raise DatasetError(f"{path}:{no}: unknown COLMAP camera model {model!r} "
                               f"(known: {', '.join(CAMERA_MODEL_IDS)})")
        nparams = CAMERA_MODELS[CAMERA_MODEL_IDS[model]][1]
        if len(el) - 4 != nparams:
            raise DatasetError(
                f"{path}:{no}: model {model} needs {nparams} parameters, got {len(el) - 4}"
            )
        w = _parse(int, el[2], path, no, "WIDTH")
        h = _parse(int, el[3], path, no, "HEIGHT")
        params = np.array([_parse(float, t, path, no, "a camera parameter") for t in el[4:]])
        cams[cid] = ColmapCamera(cid, model, w, h, params)
    return cams


def read_images_text(path: PathLike, with_points: bool = False) -> Dict[int, ColmapImage]:
    """images.txt: image id -> image (two lines per image; the 2D points counted).

    ``with_points``: the 2D points and their 3D point ids kept too (``ColmapImage.xys``).

    Raises:
        DatasetError: a malformed line (the message names the file and line).
    """
    path = Path(path)
    images: Dict[int, ColmapImage] = {}
    it = _text_lines(path)
    for no, s in it:
        if not s:
            continue
        el = s.split()
        if len(el) < 10:
            raise DatasetError(
                f"{path}:{no}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {s!r}")
        iid = _parse(int, el[0], path, no, "IMAGE_ID")
        vals = [_parse(float, t, path, no, "a pose value") for t in el[1:8]]
        cid = _parse(int, el[8], path, no, "CAMERA_ID")
        name = " ".join(el[9:])
        pno, pts = next(it, (no + 1, ""))  # the POINTS2D line (may be empty)
        tok = pts.split()
        npts = len(tok) // 3
        im = ColmapImage(iid, np.array(vals[:4]), np.array(vals[4:7]), cid, name, npts)
        if with_points:
            if len(tok) % 3:
                raise DatasetError(f"{path}:{pno}: expected 'X Y POINT3D_ID' triples, got "
                                   f"{len(tok)} values")
            im.xys = np.array([_parse(float, t, path, pno, "X/Y") for k, t in enumerate(tok)
                               if k % 3 != 2], dtype=np.float64).reshape(-1, 2)
            try:
                im.point3D_ids = np.array([_parse(int, t, path, pno, "POINT3D_ID")
                                           for t in tok[2::3]], dtype=np.int64)
            except OverflowError:
                raise DatasetError(f"{path}:{pno}: a POINT3D_ID out of the int64 range") from None
        images[iid] = im
    return images


def read_points3D_text(path: PathLike, with_ids: bool = False):
    """points3D.txt: (xyz [N, 3] float64, rgb [N, 3] float64 in [0, 1]) (and ids [N]).

    ``with_ids``: the points' ids too, as a third item (a list of ints).

    Raises:
        DatasetError: a malformed line or non-finite coordinates.
    """
    path = Path(path)
    xyz, rgb, ids = [], [], []
    for no, s in _text_lines(path):
        if not s:
            continue
        el = s.split()
        if len(el) < 8:
            raise DatasetError(
                f"{path}:{no}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...', got {s!r}"
            )
        if with_ids:
            ids.append(_parse(int, el[0], path, no, "POINT3D_ID"))
        xyz.append([_parse(float, t, path, no, "X/Y/Z") for t in el[1:4]])
        rgb.append([_parse(int, t, path, no, "R/G/B") for t in el[4:7]])
        if not all(0 <= c <= 255 for c in rgb[-1]):
            raise DatasetError(f"{path}:{no}: R/G/B must be in 0..255, got {el[4:7]}")
    out = (np.array(xyz, dtype=np.float64).reshape(-1, 3),
           np.array(rgb, dtype=np.float64).reshape(-1, 3) / 255.0)
    if len(out[0]):
        _check_points(out[0], path)
    return out + (ids,) if with_ids else out


def _check_points(xyz: np.ndarray, path) -> None:
    """Refuse NaN/Inf point coordinates (they would become NaN Gaussians)."""
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise DatasetError(f"{path}: {int(bad.sum())} of {len(xyz)} points have non-finite "
                           f"(NaN/Inf) coordinates (first: point #{int(np.argmax(bad))})")


# ----------------------------------------------------------------------------- scene

def find_sparse_dir(root: PathLike) -> Path:
    """The folder with the COLMAP model: ``<root>/sparse/0``, else ``<root>/sparse``.

    Raises:
        DatasetError: neither has a cameras.bin or cameras.txt.
    """
    root = Path(root)
    for cand in (root / "sparse" / "0", root / "sparse"):
        if any((cand / f"cameras.{e}").is_file() for e in ("bin", "txt")):
            return cand
    raise DatasetError(
        f"no COLMAP model under {root}: looked for cameras.bin/cameras.txt in "
        f"{root / 'sparse' / '0'} and {root / 'sparse'}"
    )


def missing_model_files(root: PathLike) -> List[str]:
    """The COLMAP model files that `read_colmap` needs and `<root>/sparse` lacks.

    Looks in the folder `find_sparse_dir` would pick (sparse/0 when it exists); each missing
    file is named as ``sparse/0/images.bin`` (its .txt twin would do as well).
    """
    root = Path(root)
    folder = root / "sparse" / "0" if (root / "sparse" / "0").is_dir() else root / "sparse"
    return [
        f"{folder.relative_to(root).as_posix()}/{stem}.bin"
        for stem in ("cameras", "images")
        if not any((folder / f"{stem}.{e}").is_file() for e in ("bin", "txt"))
    ]


def _pick(sparse: Path, stem: str, required: bool = True) -> Optional[Path]:
    for ext in ("bin", "txt"):
        p = sparse / f"{stem}.{ext}"
        if p.is_file():
            return p
    if required:
        raise DatasetError(f"COLMAP model in {sparse} has no {stem}.bin or {stem}.txt")
    return None


def read_colmap_model(sparse_dir: PathLike):
    """(cameras, images, xyz or None, rgb or None) of a COLMAP model folder."""
    sparse = Path(sparse_dir)
    cp, ip = _pick(sparse, "cameras"), _pick(sparse, "images")
    cams = read_cameras_binary(cp) if cp.suffix == ".bin" else read_cameras_text(cp)
    imgs = read_images_binary(ip) if ip.suffix == ".bin" else read_images_text(ip)
    pp = _pick(sparse, "points3D", required=False)
    if pp is None:
        logger.warning("COLMAP model %s has no points3D.bin/.txt: no initial point cloud", sparse)
        xyz = rgb = None
    else:
        xyz, rgb = read_points3D_binary(pp) if pp.suffix == ".bin" else read_points3D_text(pp)
    return cams, imgs, xyz, rgb


def read_colmap(path: PathLike, images: str = "images", eval: bool = True, llffhold: int = 8,
                test_list: Union[None, PathLike, Sequence[str]] = None,
                white_background: bool = False) -> SceneData:
    """Read a COLMAP dataset folder (`<path>/sparse/0`, images in `<path>/<images>`).

    eval: split into train/test (default); False puts every view in train (upstream without --eval).
    test_list: names of the test images (a text file, one per line, or a sequence); names match
        with or without extension. Default: `sparse/0/test.txt` if present, else every
        `llffhold`-th image of the list sorted by name (index % llffhold == 0).
    white_background: background for images with an alpha channel (white, else black).
    """
    root = Path(path)
    sparse = find_sparse_dir(root)
    cams, imgs, xyz, rgb = read_colmap_model(sparse)
    img_dir = root / images
    if not img_dir.is_dir():
        raise DatasetError(f"COLMAP image folder not found: {img_dir} (argument images={images!r})")

    intr_cache: Dict[int, Tuple[Intrinsics, Optional[Tuple[float, ...]]]] = {}
    entries = []
    for im in imgs.values():
        q = np.asarray(im.qvec, dtype=np.float64)
        if not (
            np.all(np.isfinite(q)) and np.all(np.isfinite(im.tvec)) and np.linalg.norm(q) > 1e-8
        ):
            logger.warning("COLMAP image %r (id %d) has no valid pose; skipped", im.name, im.id)
            continue
        if im.camera_id not in cams:
            raise DatasetError(
                f"{sparse}: image {im.name!r} (id {im.id}) refers to camera {im.camera_id}, "
                f"which is not in the cameras file (ids: {sorted(cams)})"
            )
        if im.camera_id not in intr_cache:
            intr_cache[im.camera_id] = camera_intrinsics(cams[im.camera_id], where=str(sparse))
        image_path = img_dir / im.name
        try:
            found = image_path.is_file()
        except OSError as e:  # e.g. a corrupt name too long for the file system
            raise DatasetError(f"{sparse}: image {im.id} has an unusable name "
                               f"{im.name[:80]!r}...: {e.strerror}") from None
        if not found:
            alt = img_dir / os.path.basename(im.name)
            if not alt.is_file():
                raise DatasetError(
                    f"image file of registered COLMAP image {im.name!r} not found: {image_path}"
                )
            image_path = alt
        entries.append((im, image_path))
    entries.sort(key=lambda e: e[0].name)

    registered = {p.resolve() for _, p in entries}
    unregistered = sorted(
        p.name for p in img_dir.rglob("*") if is_image_file(p) and p.resolve() not in registered
    )
    if unregistered:
        logger.info(
            "%d image(s) in %s have no registered pose in %s and are skipped: %s%s",
            len(unregistered),
            img_dir,
            sparse,
            unregistered[:5],
            "..." if len(unregistered) > 5 else "",
        )

    names = [im.name for im, _ in entries]
    if not eval:
        is_test = [False] * len(names)
    else:
        if test_list is None and (sparse / "test.txt").is_file():
            test_list = sparse / "test.txt"
        if test_list is not None:
            wanted = set(read_name_list(test_list))
            is_test = [name_matches(n, wanted) for n in names]
            if sum(is_test) == 0 and wanted:
                logger.warning(
                    "none of the %d test-list names matches an image of %s", len(wanted), sparse
                )
        else:
            is_test = holdout_split(names, llffhold)

    bg = background_of(white_background)
    train: List[View] = []
    test: List[View] = []
    for (im, image_path), t in zip(entries, is_test):
        intr, dist = intr_cache[im.camera_id]
        c2w = invert_rigid(colmap_w2c(im.qvec, im.tvec))
        v = View(
            name=im.name,
            intrinsics=intr,
            c2w=c2w,
            image_path=image_path,
            split="test" if t else "train",
            background=bg,
            distortion=dist,
            meta={"image_id": im.id, "camera_id": im.camera_id, "model": cams[im.camera_id].model},
        )
        (test if t else train).append(v)
    logger.info(
        "COLMAP dataset %s: %d train, %d test views, %s points",
        root,
        len(train),
        len(test),
        "no" if xyz is None else len(xyz),
    )
    return SceneData(
        train=train,
        test=test,
        points=xyz,
        colors=rgb,
        white_background=white_background,
        source="colmap",
        root=root,
    )
