"""Reader-independent types of `icomma_plugin.io.datasets`: `View`, `SceneData`, image loading.

Conventions (docs/CONTRACTS.md): `c2w` is camera-to-world, 4x4 float64, OpenCV/COLMAP camera
axes (x right, y down, z forward), column vectors. Pixel centres sit at integer coordinates, so
the centre of a W-wide image is (W - 1) / 2 and a principal point `cx, cy` is in that convention.
(COLMAP, instant-ngp and nerfstudio files put the pixel centre at +0.5; the readers subtract 0.5.)

Image loading (`View.load_image`, and `View.load` for (rgb, alpha) only) does, in this order:
1. decode the file (8- or 16-bit; grey, RGB or RGBA) to float in [0, 1];
2. undistort at full resolution when the view carries lens distortion (`View.distortion`):
   the image is remapped to the pinhole camera with the SAME calibration matrix K (same size,
   same fx, fy, cx, cy), with `cv2.initUndistortRectifyMap(K, dist, None, K)` (or
   `cv2.fisheye.initUndistortRectifyMap` for `distortion_model="fisheye"`) + `cv2.remap`
   (bilinear); pixels whose source falls outside the image become 0 (alpha 0 too if any), and
   the validity mask marks them invalid (a pixel is valid only if all its bilinear taps are
   inside the source image);
3. composite an RGBA image over the background: `rgb * a + bg * (1 - a)` (as 3DGS's readers);
4. resize to `view.intrinsics.scaled(scale)` size (cv2 INTER_AREA when shrinking, INTER_LINEAR
   when enlarging), so that the scaled intrinsics describe the returned image exactly. The mask
   is resized the same way and thresholded at `VALID_THRESHOLD` (close to 1), so a resized pixel
   is valid only if all of its source pixels were.
"""
from __future__ import annotations

import functools
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.pose.convert import as_rigid, cameras_extent, invert_rigid

logger = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".exr", ".tif", ".tiff",
                    ".bmp", ".webp")
IMAGE_SUFFIXES = {e.lower() for e in IMAGE_EXTENSIONS}

SPLITS = ("train", "test")

BackgroundLike = Union[None, float, Sequence[float], torch.Tensor]

DISTORTION_MODELS = ("opencv", "fisheye")
# A resampled validity mask keeps a pixel only if (almost) all of its source was valid.
VALID_THRESHOLD = 0.999


class DatasetError(ValueError):
    """A dataset file is missing, malformed or unsupported. The message names the file."""


def is_image_file(path: Path) -> bool:
    """Whether ``path`` is a file with an image suffix, not hidden."""
    return (
        path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".")
    )


def find_image(folder: Path, stem: str, what: str = "image") -> Path:
    """`folder/stem` if it is a file, else `folder/stem + ext` for a common image extension."""
    base = folder / stem
    if base.is_file() and base.suffix.lower() in IMAGE_SUFFIXES:
        return base
    for ext in IMAGE_EXTENSIONS:
        cand = folder / (stem + ext)
        if cand.is_file():
            return cand
    raise DatasetError(
        f"{what}: no image file for {stem!r} in {folder} (tried the name as given and with "
        f"extensions {', '.join(dict.fromkeys(e.lower() for e in IMAGE_EXTENSIONS))})"
    )


def image_size(path: Path) -> Tuple[int, int]:
    """(width, height) of an image file, reading only its header when possible."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1])
    except Exception:  # noqa: BLE001 - fall back to a full decode (e.g. EXR)
        arr = read_image_file(path)
        return int(arr.shape[1]), int(arr.shape[0])


def exif_orientation(path: PathLike) -> int:
    """The EXIF orientation tag of an image file (1, as stored, when it has none or no EXIF).

    Pixels are always read as stored (`read_image_file`), as COLMAP and upstream 3DGS read them;
    2-8 means a viewer shows the photo rotated or mirrored.
    """
    try:
        from PIL import Image

        with Image.open(path) as im:
            value = im.getexif().get(0x0112, 1)
        return int(value) if int(value) in range(1, 9) else 1
    except Exception:  # noqa: BLE001 - no header to read (EXR, unknown): nothing to say
        return 1


def read_image_file(path: PathLike) -> np.ndarray:
    """Decode an image to float32 [H, W, C] in [0, 1], C = 3 (RGB) or 4 (RGBA)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"image file not found: {path}")
    data = np.fromfile(str(path), dtype=np.uint8)
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if arr is None:
        raise DatasetError(f"cannot decode image file {path} (empty, truncated or unknown format)")
    if arr.dtype == np.uint8:
        img = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        img = arr.astype(np.float32) / 65535.0
    elif arr.dtype in (np.float32, np.float64):
        img = np.clip(arr.astype(np.float32), 0.0, 1.0)
    else:
        raise DatasetError(f"unsupported pixel type {arr.dtype} in image file {path}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] == 2:  # grey + alpha
        img = np.concatenate([np.repeat(img[:, :, :1], 3, axis=2), img[:, :, 1:2]], axis=2)
    elif img.shape[2] == 3:
        img = img[:, :, ::-1]  # BGR -> RGB
    elif img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]  # BGRA -> RGBA
    else:
        raise DatasetError(f"unsupported channel count {img.shape[2]} in image file {path}")
    return np.ascontiguousarray(img)


def undistort_image(img: np.ndarray, K: np.ndarray, dist: Sequence[float],
                    model: str = "opencv") -> Tuple[np.ndarray, np.ndarray]:
    """Remap a distorted image to the pinhole camera with the same K (same size).

    Args:
        img: float32 [H, W, C] (or [H, W]) image.
        K: 3x3 calibration matrix, pixel centres at integers (OpenCV's convention, and ours).
        dist: for model "opencv", OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]); for
            "fisheye", the four coefficients (k1, k2, k3, k4) of OpenCV's fisheye model
            (theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)).
        model: "opencv" or "fisheye".

    Returns:
        (undistorted [H, W, C] float32, valid [H, W] bool): pixels mapped from outside the source
        image are 0 in the image and False in `valid` (True only where every bilinear tap of the
        source lies inside the image).
    """
    import cv2

    if model not in DISTORTION_MODELS:
        raise ValueError(f"model must be one of {DISTORTION_MODELS}, got {model!r}")
    h, w = img.shape[:2]
    K = np.asarray(K, dtype=np.float64)
    d = np.asarray(dist, dtype=np.float64)
    if model == "fisheye" and d.shape != (4,):
        raise ValueError(f"dist must hold 4 fisheye coefficients (k1, k2, k3, k4), got "
                         f"{d.tolist()}")
    map1, map2, valid = _undistort_maps(tuple(K.ravel().tolist()), tuple(d.ravel().tolist()),
                                        model, w, h)
    out = cv2.remap(img, map1, map2, interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if out.ndim == 2:
        out = out[:, :, None]
    return out, valid.copy()


@functools.lru_cache(maxsize=4)
def _undistort_maps(K: Tuple[float, ...], dist: Tuple[float, ...], model: str, w: int, h: int):
    """(map1, map2, valid [H, W] bool) of ``undistort_image`` for one camera, made once.

    The frames of a video (and the views of one camera) share them: the maps and the validity
    remap are two thirds of an undistortion's time at 1080x1920.
    """
    import cv2

    K, d = np.asarray(K, np.float64).reshape(3, 3), np.asarray(dist, np.float64)
    if model == "fisheye":
        map1, map2 = cv2.fisheye.initUndistortRectifyMap(K, d, np.eye(3), K, (w, h), cv2.CV_32FC1)
    else:
        map1, map2 = cv2.initUndistortRectifyMap(K, d, None, K, (w, h), cv2.CV_32FC1)
    # remapping ones with the same maps gives the weight of the taps that fell inside the image
    inside = cv2.remap(np.ones((h, w), np.float32), map1, map2, interpolation=cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return map1, map2, inside >= VALID_THRESHOLD


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize [H, W, C] float32 to (width, height): INTER_AREA when shrinking, else INTER_LINEAR."""
    import cv2

    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img
    interp = cv2.INTER_AREA if (width < w and height < h) else cv2.INTER_LINEAR
    out = cv2.resize(img, (width, height), interpolation=interp)
    return out[:, :, None] if out.ndim == 2 else out


def resize_valid(valid: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a bool [H, W] validity mask conservatively.

    A pixel stays valid only if all of its source pixels were (the resampled mask is thresholded
    at `VALID_THRESHOLD`).
    """
    out = resize_image(valid.astype(np.float32), width, height)[:, :, 0]
    return out >= VALID_THRESHOLD


def _background_array(background: BackgroundLike) -> np.ndarray:
    if isinstance(background, torch.Tensor):
        bg = background.detach().to("cpu", torch.float32).reshape(-1).numpy()
    elif isinstance(background, (int, float)):
        bg = np.full(3, float(background), dtype=np.float32)
    else:
        bg = np.asarray(background, dtype=np.float32).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValueError(
            f"background must be a number or 3 finite values (RGB), got {background!r}"
        )
    return bg


@dataclass(eq=False)
class ViewImage:
    """A loaded view image (`View.load_image`).

    rgb: [3, H, W] float32 in [0, 1].
    alpha: [1, H, W] float32, or None when the file has no alpha channel.
    valid: [1, H, W] float32 in {0, 1}: 1 where the pixel is real image content (0 where
        undistortion filled it from outside the source image); None when every pixel is valid.
    """

    rgb: torch.Tensor
    alpha: Optional[torch.Tensor] = None
    valid: Optional[torch.Tensor] = None

    @property
    def valid_fraction(self) -> float:
        """Fraction of valid pixels (1.0 when `valid` is None)."""
        return 1.0 if self.valid is None else float(self.valid.mean())


@dataclass(eq=False)
class View:
    """One posed image of a dataset.

    name: image name (3DGS `image_name`: for Blender the file stem, for COLMAP the image name).
    intrinsics: pinhole intrinsics of the (undistorted) image at its full, on-disk resolution.
    c2w: [4, 4] float64 camera-to-world, OpenCV axes.
    image_path: the image file.
    split: "train" or "test".
    background: RGB the RGBA images are composited over by default (None: no compositing).
    distortion: distortion coefficients of the raw image, or None: OpenCV's (k1, k2, p1, p2[,
        k3...]) for `distortion_model` "opencv", (k1, k2, k3, k4) for "fisheye". `load` undistorts
        to `intrinsics` (same K) before anything else.
    distortion_model: "opencv" (radial-tangential) or "fisheye" (OpenCV's equidistant model).
    bounds: (near, far) scene depth bounds (LLFF), or None.
    meta: reader-specific extras (e.g. COLMAP image_id / camera_id / model).
    """

    name: str
    intrinsics: Intrinsics
    c2w: np.ndarray
    image_path: Path
    split: str = "train"
    background: Optional[Tuple[float, float, float]] = None
    distortion: Optional[Tuple[float, ...]] = None
    bounds: Optional[Tuple[float, float]] = None
    meta: Dict[str, Any] = field(default_factory=dict)
    distortion_model: str = "opencv"

    def __post_init__(self):
        self.c2w = as_rigid(self.c2w, f"view {self.name!r}: its camera-to-world", DatasetError)
        self.image_path = Path(self.image_path)
        if self.split not in SPLITS:
            raise ValueError(f"View.split must be one of {SPLITS}, got {self.split!r}")
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(f"View.distortion_model must be one of {DISTORTION_MODELS}, "
                             f"got {self.distortion_model!r}")

    @property
    def w2c(self) -> np.ndarray:
        """[4, 4] float64 world-to-camera, `inv(c2w)`.

        As 3DGS; exact also for the float32-rounded rotations of JSON files, which are rigid only
        to ~1e-7.
        """
        w2c = invert_rigid(self.c2w)
        w2c[3] = (0.0, 0.0, 0.0, 1.0)
        return w2c

    @property
    def campos(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return self.c2w[:3, 3].copy()

    @property
    def width(self) -> int:
        """Image width [px] (the intrinsics')."""
        return self.intrinsics.width

    @property
    def height(self) -> int:
        """Image height [px] (the intrinsics')."""
        return self.intrinsics.height

    @property
    def is_distorted(self) -> bool:
        """True when `load` undistorts (some distortion coefficient is non-zero)."""
        return self.distortion is not None and any(float(c) != 0.0 for c in self.distortion)

    def _load_full(self, composite: bool, background: BackgroundLike
                   ) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """Full-resolution (float32 [H, W, C] image, bool [H, W] valid mask or None)."""
        img = read_image_file(self.image_path)
        h, w = img.shape[:2]
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise DatasetError(
                f"image file {self.image_path} is {w}x{h} but view {self.name!r} expects "
                f"{self.intrinsics.width}x{self.intrinsics.height} (from the camera file)"
            )
        valid = None
        if self.is_distorted:
            img, valid = undistort_image(img, self.intrinsics.K().numpy(), self.distortion,
                                         self.distortion_model)
            if valid.all():
                valid = None
        if img.shape[2] == 4 and composite:
            bg = background if background is not None else self.background
            if bg is not None:
                bg = _background_array(bg)
                a = img[:, :, 3:4]
                rgb = img[:, :, :3] * a + bg[None, None, :] * (1.0 - a)
                img = np.concatenate([rgb, a], axis=2)
        return img, valid

    def load_array(self, composite: bool = True, background: BackgroundLike = None) -> np.ndarray:
        """Full-resolution float32 [H, W, C] image, undistorted and composited (C = 3 or 4)."""
        return self._load_full(composite, background)[0]

    def load_image(self, scale: float = 1.0, background: BackgroundLike = None,
                   composite: bool = True) -> "ViewImage":
        """Load the image with its alpha and validity mask (see the module docstring).

        Args:
            scale: size factor; the result has the size of `self.intrinsics.scaled(scale)`.
            background: what an RGBA image is composited over (a number, 3 values or a tensor);
                None: `self.background`.
            composite: False returns the straight RGB of an RGBA image.

        Returns:
            ViewImage(rgb [3, H, W], alpha [1, H, W] or None (no alpha channel), valid [1, H, W]
            float32 or None (every pixel is image content)).
        """
        if isinstance(scale, bool) or not (isinstance(scale, (int, float)) and math.isfinite(scale)
                                           and scale > 0):
            raise ValueError(f"scale must be a positive finite number, got {scale!r}")
        img, valid = self._load_full(composite, background)
        if scale != 1.0:
            target = self.intrinsics.scaled(scale)
            img = resize_image(img, target.width, target.height)
            if valid is not None:
                valid = resize_valid(valid, target.width, target.height)
        t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float().clamp_(0.0, 1.0)
        rgb = t[:3].contiguous()
        alpha = t[3:4].contiguous() if t.shape[0] == 4 else None
        mask = None if valid is None else torch.from_numpy(valid[None].astype(np.float32))
        return ViewImage(rgb=rgb, alpha=alpha, valid=mask)

    def load(self, scale: float = 1.0, background: BackgroundLike = None,
             composite: bool = True) -> Tuple[torch.Tensor, Optional[torch.Tensor]]:
        """Load the image: (rgb [3, H, W] float32 in [0, 1], alpha [1, H, W] float32 or None).

        The size is that of `self.intrinsics.scaled(scale)`. An RGBA image is composited over
        `background` (a number, 3 values or a tensor), or over `self.background` when None; with
        `composite=False` (or no background at all) the straight RGB is returned. alpha is None
        when the file has no alpha channel. `load_image` also returns the validity mask.
        """
        im = self.load_image(scale=scale, background=background, composite=composite)
        return im.rgb, im.alpha

    def __repr__(self) -> str:
        i = self.intrinsics
        return (f"View(name={self.name!r}, split={self.split!r}, {i.width}x{i.height}, "
                f"fx={i.fx:.2f}, fy={i.fy:.2f}, campos={np.round(self.campos, 4).tolist()}, "
                f"image_path={str(self.image_path)!r})")


@dataclass(eq=False)
class SceneData:
    """What a dataset reader returns (3DGS `SceneInfo`).

    train, test: the views of each split (sorted as the reader documents).
    points, colors: [N, 3] float64 initial point cloud and its colours in [0, 1], or None.
    white_background: the background RGBA images are composited over (white if True, else black).
    source: which reader made it: "blender", "colmap", "llff", "cameras_json" or
        "transforms_json".
    root: the dataset folder.
    init_box: when `points` are random (no point cloud in the dataset), the cube they were
        drawn in, as (centre [3], half_extent); a consumer may draw its own count in it
        (`random_points(n, seed, half_extent, centre)`). None otherwise.
    """

    train: List[View]
    test: List[View]
    points: Optional[np.ndarray]
    colors: Optional[np.ndarray]
    white_background: bool
    source: str
    root: Optional[Path] = None
    init_box: Optional[Tuple[Tuple[float, float, float], float]] = None

    def views(self, split: str = "train") -> List[View]:
        """Views of a split: "train", "test" or "all" (train then test)."""
        if split == "train":
            return list(self.train)
        if split == "test":
            return list(self.test)
        if split == "all":
            return list(self.train) + list(self.test)
        raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")

    def view(self, name: str, split: Optional[str] = None) -> View:
        """The view called `name` (in `split` if given; test views first otherwise)."""
        pool = self.views(split) if split else list(self.test) + list(self.train)
        for v in pool:
            if v.name == name:
                return v
        raise KeyError(f"no view named {name!r} in split {split or 'test+train'} "
                       f"(names: {[v.name for v in pool][:10]}{'...' if len(pool) > 10 else ''})")

    def _centres(self) -> np.ndarray:
        views = self.train if self.train else self.test
        if not views:
            raise ValueError("scene has no views; cannot compute its radius")
        return np.stack([v.campos for v in views])

    def scene_center(self) -> np.ndarray:
        """Mean of the train camera centres (3DGS getNerfppNorm `-translate`)."""
        return self._centres().mean(axis=0)

    def scene_radius(self) -> float:
        """3DGS getNerfppNorm radius of the train cameras (``pose.convert.cameras_extent``)."""
        views = self.train if self.train else self.test
        if not views:
            raise ValueError("scene has no views; cannot compute its radius")
        return cameras_extent([v.c2w for v in views])

    def __repr__(self) -> str:
        n = None if self.points is None else len(self.points)
        return (
            f"SceneData(source={self.source!r}, root={str(self.root)!r}, train={len(self.train)}, "
            f"test={len(self.test)}, points={n}, white_background={self.white_background})"
        )


def shared_data_root() -> Path:
    """The shared test and benchmark data folder; the one place that knows it.

    ``ICOMMA_SHARED_DATA``, default ``<repo>/../shared/data`` (data/README.md of the project's
    environment).
    """
    repo = Path(__file__).resolve().parents[3]
    return Path(os.environ.get("ICOMMA_SHARED_DATA", repo.parent / "shared" / "data")).expanduser()


def background_of(white_background: bool) -> Tuple[float, float, float]:
    """The RGB background: white or black."""
    return (1.0, 1.0, 1.0) if white_background else (0.0, 0.0, 0.0)


def holdout_split(names: Sequence[str], llffhold: int) -> List[bool]:
    """is_test flags for names in the given (sorted) order: index % llffhold == 0 (3DGS/LLFF)."""
    if not isinstance(llffhold, int) or isinstance(llffhold, bool) or llffhold <= 0:
        raise ValueError(f"llffhold must be a positive int, got {llffhold!r}")
    return [i % llffhold == 0 for i in range(len(names))]


def read_name_list(source: Union[PathLike, Sequence[str]], what: str = "test list") -> List[str]:
    """Names from a text file (a str or path: one name per line, '#' comments) or a sequence."""
    if isinstance(source, (str, os.PathLike)):
        p = Path(source)
        if not p.is_file():
            raise DatasetError(f"{what} file not found: {p}")
        lines = (ln.strip() for ln in p.read_text().splitlines())
        return [ln for ln in lines if ln and not ln.startswith("#")]
    return [str(s) for s in source]


def name_matches(name: str, wanted: set) -> bool:
    """A view name matches a listed name with or without extension / folder."""
    stem = os.path.splitext(name)[0]
    base = os.path.basename(name)
    return bool({name, stem, base, os.path.splitext(base)[0]} & wanted)


def random_points(num: int = 100_000, seed: int = 0, extent: float = 1.3,
                  center: Optional[Sequence[float]] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Upstream Blender init cloud, from a seeded generator.

    `num` points uniform in the cube `center` + [-extent, extent]^3 (center defaults to the
    origin), colours SH2RGB(U[0, 1)/255) (i.e. about 0.5 grey).
    """
    rng = np.random.default_rng(seed)
    xyz = rng.random((num, 3)) * (2.0 * extent) - extent
    if center is not None:
        xyz = xyz + np.asarray(center, dtype=np.float64).reshape(1, 3)
    shs = rng.random((num, 3)) / 255.0
    colors = shs * 0.28209479177387814 + 0.5
    return xyz.astype(np.float64), colors.astype(np.float64)
