"""Video files: read frames (OpenCV, a dependency, whose wheels carry FFmpeg), write MP4.

    for index, rgb in read_video_frames("walk.mp4", every=2):   # [H, W, 3] uint8 RGB
        ...
    path = write_video("out.mp4", frames, fps=10)   # MP4; or out.gif when no encoder works

Writing tries imageio's FFmpeg plugin (``imageio-ffmpeg``, H.264) when it is installed, then
OpenCV's ``mp4v`` (MPEG-4 part 2) encoder; when neither can encode, the frames go to a GIF
beside the requested name, with a warning, and the GIF's path is returned. Files are written to
a temporary name in the same folder and moved into place (a reader never sees half a video).
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path
from typing import Iterable, Iterator, List, Optional, Tuple, Union

import numpy as np
import torch

from .atomic import atomic_path

logger = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]
ImageLike = Union[torch.Tensor, np.ndarray]

__all__ = [
    "VIDEO_SUFFIXES",
    "VideoError",
    "is_video_file",
    "read_video_frames",
    "to_uint8",
    "video_info",
    "write_gif",
    "write_video",
]

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".gif")


class VideoError(ValueError):
    """A video that cannot be opened or written (the message names the file)."""


def is_video_file(path: PathLike) -> bool:
    """Whether ``path`` is a file with a video suffix (`VIDEO_SUFFIXES`)."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def _open(path: Path):
    import cv2

    if not path.is_file():
        raise VideoError(f"video file not found: {path}")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise VideoError(f"cannot open the video {path} (OpenCV/FFmpeg could not read it)")
    return cap


def video_info(path: PathLike) -> Tuple[int, int, int, float]:
    """(width, height, frame count (0 when unknown), fps) of a video file."""
    import cv2

    cap = _open(Path(path))
    try:
        return (
            int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT))),
            float(cap.get(cv2.CAP_PROP_FPS) or 0.0),
        )
    finally:
        cap.release()


def read_video_frames(
    path: PathLike, every: int = 1, start: int = 0, limit: Optional[int] = None
) -> Iterator[Tuple[int, np.ndarray]]:
    """Yield ``(frame index, [H, W, 3] uint8 RGB)`` for every ``every``-th frame from ``start``.

    At most ``limit`` frames. Frames skipped are grabbed, not decoded.
    """
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"every must be a positive int, got {every!r}")
    cap = _open(Path(path))
    try:
        i, n = 0, 0
        while limit is None or n < limit:
            if i < start or (i - start) % every:
                if not cap.grab():
                    break
                i += 1
                continue
            ok, bgr = cap.read()
            if not ok:
                break
            yield i, np.ascontiguousarray(bgr[:, :, ::-1])
            i += 1
            n += 1
    finally:
        cap.release()


def _tmp_beside(path: Path, suffix: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".partial" + suffix, dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _even(a: np.ndarray) -> np.ndarray:
    """Crop to even width and height (what MPEG encoders require)."""
    h, w = a.shape[:2]
    return a[: h - h % 2, : w - w % 2]


def _write_imageio(tmp: Path, frames: list, fps: float) -> bool:
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401 # pyflakes: ignore - the plugin's encoder binary
    except ImportError:
        return False
    try:
        with imageio.get_writer(
            str(tmp), format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=1
        ) as w:
            for f in frames:
                w.append_data(f)
        return tmp.stat().st_size > 0
    except Exception as e:  # noqa: BLE001 - fall through to the next encoder
        logger.info("imageio-ffmpeg could not write %s: %s", tmp, e)
        return False


def _write_cv2(tmp: Path, frames: list, fps: float) -> bool:
    import cv2

    h, w = frames[0].shape[:2]
    wr = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not wr.isOpened():
        return False
    try:
        for f in frames:
            wr.write(np.ascontiguousarray(f[:, :, ::-1]))
    finally:
        wr.release()
    return tmp.stat().st_size > 0


def write_video(path: PathLike, frames: Iterable, fps: float = 10.0) -> Path:
    """Write ``frames`` as an MP4 at ``path``.

    Args:
        path: the ``.mp4`` file.
        frames: ``[H, W, 3]`` uint8 RGB arrays or ``[3, H, W]`` tensors, all one size.
        fps: frames per second.

    Returns:
        The path written (a ``.gif`` when no MP4 encoder works).

    Raises:
        VideoError: no frames, or frames of different sizes.
    """
    path = Path(path)
    arr = [_even(to_uint8(f)) for f in frames]
    if not arr:
        raise VideoError(f"{path}: no frames to write")
    if any(a.shape != arr[0].shape for a in arr):
        raise VideoError(f"{path}: frames differ in size ({arr[0].shape} and others)")
    if not (isinstance(fps, (int, float)) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    if path.suffix.lower() != ".gif":
        tmp = _tmp_beside(path, ".mp4")
        try:
            for writer in (_write_imageio, _write_cv2):
                if writer(tmp, arr, fps):
                    os.replace(tmp, path)
                    return path
        finally:
            if tmp.exists():
                tmp.unlink()
        gif = path.with_suffix(".gif")
        logger.warning(
            "no MP4 encoder works here (imageio-ffmpeg missing, OpenCV's mp4v failed): "
            "wrote %s instead of %s",
            gif.name,
            path.name,
        )
        path = gif
    return write_gif(path, arr, fps=fps)


def to_uint8(img: ImageLike) -> np.ndarray:
    """An image as ``[H, W, 3]`` uint8.

    From a ``[3, H, W]`` tensor or an ``[H, W, 3]`` array, float in [0, 1] or uint8.
    """
    if isinstance(img, torch.Tensor):
        t = img.detach().cpu()
        if t.ndim != 3 or t.shape[0] not in (1, 3):
            raise ValueError(f"image tensor must be [3, H, W] or [1, H, W], got {list(t.shape)}")
        if t.shape[0] == 1:
            t = t.expand(3, -1, -1)
        a = t.permute(1, 2, 0).numpy()
    else:
        a = np.asarray(img)
        if a.ndim == 2:
            a = np.repeat(a[..., None], 3, axis=2)
        if a.ndim != 3 or a.shape[2] not in (3, 4):
            raise ValueError(f"image array must be [H, W, 3], got {list(a.shape)}")
        a = a[..., :3]
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    a = np.nan_to_num(a.astype(np.float32), nan=0.0)
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)



def write_gif(path: PathLike, frames: List[ImageLike], fps: float = 8.0) -> Path:
    """Animated GIF of ``frames`` (each an image), looping; written atomically."""
    from PIL import Image

    if not frames:
        raise ValueError("frames must be a non-empty list of images")
    ims = [Image.fromarray(to_uint8(f)) for f in frames]
    path = Path(path)
    with atomic_path(path) as tmp:
        ims[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=ims[1:],
            duration=int(1000 / max(fps, 0.1)),
            loop=0,
        )
    return path

