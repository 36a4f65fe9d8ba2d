"""Pictures of a localisation run: overlays, match lines, convergence plots, an optimisation GIF.

Images are ``[3, H, W]`` float tensors in [0, 1] (or ``[H, W, 3]`` uint8/float numpy arrays).
Every file is written atomically (``io.atomic.atomic_path``). matplotlib runs on the Agg backend
and is imported lazily, so importing this module is cheap.
"""
from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np
import torch

from .io.atomic import atomic_path

logger = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]
ImageLike = Union[torch.Tensor, np.ndarray]

__all__ = [
    "to_uint8",
    "overlay_panel",
    "match_lines_image",
    "save_image",
    "save_overlay",
    "save_match_lines",
    "plot_convergence",
    "save_gif",
]


def to_uint8(img: ImageLike) -> np.ndarray:
    """``[3, H, W]`` tensor / ``[H, W, 3]`` array (float in [0, 1] or uint8) -> ``[H, W, 3]`` uint8."""
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


def _resize_like(a: np.ndarray, h: int, w: int) -> np.ndarray:
    if a.shape[:2] == (h, w):
        return a
    from PIL import Image

    return np.asarray(Image.fromarray(a).resize((w, h), Image.BILINEAR))


def overlay_panel(render: ImageLike, query: ImageLike, diff_gain: float = 3.0,
                  alpha: float = 0.5) -> np.ndarray:
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
    """render | query side by side with a line per match (colour = confidence, viridis);
    ``[H', W', 3]`` uint8. Keypoints are (x, y) pixels (centres at integers)."""
    import cv2

    r, q = to_uint8(render), to_uint8(query)
    k0 = _np2(kpts_render)
    k1 = _np2(kpts_query)
    if k0.shape != k1.shape:
        raise ValueError(f"kpts_render and kpts_query must have the same shape, got {k0.shape} and {k1.shape}")
    conf = np.ones(len(k0)) if confidence is None else np.asarray(_np1(confidence), np.float64)
    if len(k0) > max_lines:
        idx = np.argsort(-conf)[:max_lines]
        k0, k1, conf = k0[idx], k1[idx], conf[idx]
    H = max(r.shape[0], q.shape[0])
    canvas = np.zeros((H, r.shape[1] + 4 + q.shape[1], 3), np.uint8)
    canvas[: r.shape[0], : r.shape[1]] = r
    canvas[:, r.shape[1]: r.shape[1] + 4] = 255
    off = r.shape[1] + 4
    canvas[: q.shape[0], off:] = q
    s = float(scale)
    canvas = cv2.resize(canvas, (int(round(canvas.shape[1] * s)), int(round(canvas.shape[0] * s))),
                        interpolation=cv2.INTER_NEAREST)
    cmap = _viridis()
    for (x0, y0), (x1, y1), c in zip(k0, k1, conf):
        col = tuple(int(v) for v in cmap[int(np.clip(c, 0, 1) * 255)])
        p0 = (int(round((x0 + 0.5) * s)), int(round((y0 + 0.5) * s)))
        p1 = (int(round((x1 + off + 0.5) * s)), int(round((y1 + 0.5) * s)))
        cv2.line(canvas, p0, p1, col, 1, cv2.LINE_AA)
        cv2.circle(canvas, p0, 2, col, -1, cv2.LINE_AA)
        cv2.circle(canvas, p1, 2, col, -1, cv2.LINE_AA)
    cv2.putText(canvas, f"render  ({len(k0)} matches shown)", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(canvas, "query", (int(off * s) + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (255, 255, 255), 1, cv2.LINE_AA)
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


def save_overlay(path: PathLike, render: ImageLike, query: ImageLike, diff_gain: float = 3.0) -> Path:
    """:func:`overlay_panel` written to ``path``."""
    return save_image(path, overlay_panel(render, query, diff_gain=diff_gain))


def save_match_lines(path: PathLike, render: ImageLike, query: ImageLike, kpts_render, kpts_query,
                     confidence=None, max_lines: int = 150) -> Path:
    """:func:`match_lines_image` written to ``path``."""
    return save_image(path, match_lines_image(render, query, kpts_render, kpts_query, confidence,
                                              max_lines=max_lines))


def _series(trace: Sequence[Dict[str, Any]], key: str):
    xs, ys = [], []
    for r in trace:
        v = r.get(key)
        if v is not None and isinstance(v, (int, float)) and math.isfinite(v):
            xs.append(r["iteration"])
            ys.append(v)
    return np.asarray(xs), np.asarray(ys, np.float64)


def plot_convergence(path: PathLike, trace: Sequence[Dict[str, Any]],
                     switch_iteration: Optional[int] = None, title: Optional[str] = None,
                     rot_target_deg: Optional[float] = None,
                     trans_target: Optional[float] = None) -> Path:
    """Rotation / translation error, losses and lr against the iteration (log scales); the
    stage switch is marked by a dashed vertical line. Written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    has_err = any(r.get("rot_err_deg") is not None for r in trace)
    n = 3 if has_err else 2
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), constrained_layout=True)
    axes = list(np.atleast_1d(axes))

    def mark(ax):
        if switch_iteration is not None and switch_iteration > 0:
            ax.axvline(switch_iteration, color="k", ls="--", lw=1, label=f"switch @ {switch_iteration}")
        ax.set_xlabel("iteration")
        ax.grid(True, which="both", alpha=0.3)

    i = 0
    if has_err:
        ax = axes[i]
        i += 1
        x, y = _series(trace, "rot_err_deg")
        ax.semilogy(x, np.maximum(y, 1e-4), color="C0", label="rotation error [deg]")
        x2, y2 = _series(trace, "trans_err")
        ax2 = ax.twinx()
        ax2.semilogy(x2, np.maximum(y2, 1e-6), color="C1", label="translation error")
        ax2.set_ylabel("translation error [scene units]", color="C1")
        ax.set_ylabel("rotation error [deg]", color="C0")
        if rot_target_deg:
            ax.axhline(rot_target_deg, color="C0", ls=":", lw=1)
        if trans_target:
            ax2.axhline(trans_target, color="C1", ls=":", lw=1)
        mark(ax)
        ax.legend(loc="upper right", fontsize=7)
        ax.set_title("pose error")
    ax = axes[i]
    i += 1
    for key, col, lab in (("loss", "k", "total"), ("loss_compare", "C2", "L_compare"),
                          ("loss_match", "C3", "L_match")):
        x, y = _series(trace, key)
        if len(x):
            ax.semilogy(x, np.maximum(y, 1e-12), color=col, lw=1, label=lab)
    mark(ax)
    ax.legend(fontsize=7)
    ax.set_title("losses")
    ax = axes[i]
    x, y = _series(trace, "lr")
    ax.semilogy(x, y, color="C4", label="lr")
    x2, y2 = _series(trace, "matches_used")
    if len(x2) and y2.max() > 0:
        ax2 = ax.twinx()
        ax2.plot(x2, y2, ".", ms=2, color="C5", label="matches used")
        ax2.set_ylabel("matches used", color="C5")
    ax.set_ylabel("learning rate", color="C4")
    mark(ax)
    ax.set_title("schedule")
    if title:
        fig.suptitle(title, fontsize=9)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def save_gif(path: PathLike, frames: List[ImageLike], fps: float = 8.0) -> Path:
    """Animated GIF of ``frames`` (each an image), looping; written atomically."""
    from PIL import Image

    if not frames:
        raise ValueError("frames must be a non-empty list of images")
    ims = [Image.fromarray(to_uint8(f)) for f in frames]
    path = Path(path)
    with atomic_path(path) as tmp:
        ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:],
                    duration=int(1000 / max(fps, 0.1)), loop=0)
    return path
