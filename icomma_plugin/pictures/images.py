"""Images of one localization: overlays of render and photo, match lines, animations."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import List

import numpy as np
import torch

from ..io.atomic import atomic_path
from ..io.video import ImageLike, PathLike, to_uint8

logger = logging.getLogger(__name__)


__all__ = [
    "VERDICT_COLOURS",
    "match_lines_image",
    "overlay_panel",
    "save_gif",
    "save_image",
    "save_match_lines",
    "save_overlay",
    "save_video",
]

#: Verdict -> RGB of the frame drawn around a photo.
VERDICT_COLOURS = {"ok": (40, 170, 60), "uncertain": (235, 150, 20), "failed": (210, 40, 40)}


def _resize_like(a: np.ndarray, h: int, w: int) -> np.ndarray:
    if a.shape[:2] == (h, w):
        return a
    from PIL import Image

    return np.asarray(Image.fromarray(a).resize((w, h), Image.BILINEAR))



def overlay_panel(
    render: ImageLike, query: ImageLike, diff_gain: float = 3.0, alpha: float = 0.5
) -> np.ndarray:
    """``[H, 4W, 3]`` uint8: render | query | blend (``alpha`` render) | |render - query| x gain."""
    r = to_uint8(render)
    q = _resize_like(to_uint8(query), r.shape[0], r.shape[1])
    rf, qf = r.astype(np.float32), q.astype(np.float32)
    blend = alpha * rf + (1 - alpha) * qf
    diff = np.clip(np.abs(rf - qf) * diff_gain, 0, 255)
    sep = np.full((r.shape[0], 2, 3), 255, np.uint8)
    return np.concatenate([r, sep, q, sep, blend.astype(np.uint8), sep, diff.astype(np.uint8)], 1)


def match_lines_image(
    render: ImageLike,
    query: ImageLike,
    kpts_render,
    kpts_query,
    confidence=None,
    max_lines: int = 150,
    scale: float = 2.0,
) -> np.ndarray:
    """render | query side by side with a line per match (colour = confidence, viridis).

    Returns ``[H', W', 3]`` uint8. Keypoints are (x, y) pixels (centres at integers).
    """
    import cv2

    r, q = to_uint8(render), to_uint8(query)
    k0 = _np2(kpts_render)
    k1 = _np2(kpts_query)
    if k0.shape != k1.shape:
        raise ValueError(
            f"kpts_render and kpts_query must have the same shape, got {k0.shape} and {k1.shape}"
        )
    conf = np.ones(len(k0)) if confidence is None else np.asarray(_np1(confidence), np.float64)
    if len(k0) > max_lines:
        idx = np.argsort(-conf)[:max_lines]
        k0, k1, conf = k0[idx], k1[idx], conf[idx]
    H = max(r.shape[0], q.shape[0])
    canvas = np.zeros((H, r.shape[1] + 4 + q.shape[1], 3), np.uint8)
    canvas[: r.shape[0], : r.shape[1]] = r
    canvas[:, r.shape[1] : r.shape[1] + 4] = 255
    off = r.shape[1] + 4
    canvas[: q.shape[0], off:] = q
    s = float(scale)
    canvas = cv2.resize(
        canvas,
        (int(round(canvas.shape[1] * s)), int(round(canvas.shape[0] * s))),
        interpolation=cv2.INTER_NEAREST,
    )
    cmap = _viridis()
    for (x0, y0), (x1, y1), c in zip(k0, k1, conf):
        col = tuple(int(v) for v in cmap[int(np.clip(c, 0, 1) * 255)])
        p0 = (int(round((x0 + 0.5) * s)), int(round((y0 + 0.5) * s)))
        p1 = (int(round((x1 + off + 0.5) * s)), int(round((y1 + 0.5) * s)))
        cv2.line(canvas, p0, p1, col, 1, cv2.LINE_AA)
        cv2.circle(canvas, p0, 2, col, -1, cv2.LINE_AA)
        cv2.circle(canvas, p1, 2, col, -1, cv2.LINE_AA)
    cv2.putText(
        canvas,
        f"render  ({len(k0)} matches shown)",
        (4, 14),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.45,
        (255, 255, 255),
        1,
        cv2.LINE_AA,
    )
    cv2.putText(
        canvas,
        "query",
        (int(off * s) + 4, 14),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.45,
        (255, 255, 255),
        1,
        cv2.LINE_AA,
    )
    return canvas


def _np2(k) -> np.ndarray:
    if isinstance(k, torch.Tensor):
        k = k.detach().cpu().double().numpy()
    k = np.asarray(k, np.float64).reshape(-1, 2)
    return k


def _np1(k) -> np.ndarray:
    if isinstance(k, torch.Tensor):
        k = k.detach().cpu().double().numpy()
    return np.asarray(k, np.float64).reshape(-1)


def _viridis() -> np.ndarray:
    from matplotlib import colormaps

    return (colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)


def save_image(path: PathLike, img: ImageLike) -> Path:
    """Write a PNG (or another PIL format by extension) atomically."""
    from PIL import Image

    path = Path(path)
    fmt = {".jpg": "JPEG", ".jpeg": "JPEG", ".gif": "GIF"}.get(path.suffix.lower(), "PNG")
    with atomic_path(path) as tmp:
        Image.fromarray(to_uint8(img)).save(tmp, format=fmt)
    return path


def save_overlay(
    path: PathLike, render: ImageLike, query: ImageLike, diff_gain: float = 3.0
) -> Path:
    """:func:`overlay_panel` written to ``path``."""
    return save_image(path, overlay_panel(render, query, diff_gain=diff_gain))


def save_match_lines(
    path: PathLike,
    render: ImageLike,
    query: ImageLike,
    kpts_render,
    kpts_query,
    confidence=None,
    max_lines: int = 150,
) -> Path:
    """:func:`match_lines_image` written to ``path``."""
    return save_image(
        path,
        match_lines_image(render, query, kpts_render, kpts_query, confidence, max_lines=max_lines),
    )



def save_gif(path: PathLike, frames: List[ImageLike], fps: float = 8.0) -> Path:
    """Animated GIF of ``frames`` (``io.video.write_gif``), looping; written atomically."""
    from ..io.video import write_gif

    return write_gif(path, frames, fps=fps)


def save_video(path: PathLike, frames: List[ImageLike], fps: float = 8.0) -> Path:
    """MP4 of ``frames`` (``io.video.write_video``); a GIF beside it when no MP4 encoder works.

    Returns:
        The path written.
    """
    from ..io.video import write_video

    return write_video(path, frames, fps=fps)

