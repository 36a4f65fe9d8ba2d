"""Pictures of localisation runs, batches, sequences and benchmarks.

A run: overlays, match lines, convergence plots, an optimisation GIF or MP4; a batch: thumbnails
and a contact sheet coloured by verdict; a sequence: the trajectory over the scene's cameras; a
benchmark: the success curves beside the paper's numbers.

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
    "save_video",
    "VERDICT_COLOURS",
    "save_thumbnail",
    "contact_sheet",
    "plot_trajectory",
    "plot_curves_vs_paper",
]

#: Verdict -> RGB of the frame drawn around a photo.
VERDICT_COLOURS = {"ok": (40, 170, 60), "uncertain": (235, 150, 20), "failed": (210, 40, 40)}


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


def _series(trace: Sequence[Dict[str, Any]], key: str):
    xs, ys = [], []
    for r in trace:
        v = r.get(key)
        if v is not None and isinstance(v, (int, float)) and math.isfinite(v):
            xs.append(r["iteration"])
            ys.append(v)
    return np.asarray(xs), np.asarray(ys, np.float64)


def plot_convergence(
    path: PathLike,
    trace: Sequence[Dict[str, Any]],
    switch_iteration: Optional[int] = None,
    title: Optional[str] = None,
    rot_target_deg: Optional[float] = None,
    trans_target: Optional[float] = None,
) -> Path:
    """Rotation / translation error, losses and lr against the iteration (log scales).

    The stage switch is marked by a dashed vertical line. Written to ``path`` (PNG).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    has_err = any(r.get("rot_err_deg") is not None for r in trace)
    n = 3 if has_err else 2
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.4), constrained_layout=True)
    axes = list(np.atleast_1d(axes))

    def mark(ax):
        if switch_iteration is not None and switch_iteration > 0:
            ax.axvline(
                switch_iteration, color="k", ls="--", lw=1, label=f"switch @ {switch_iteration}"
            )
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
    for key, col, lab in (
        ("loss", "k", "total"),
        ("loss_compare", "C2", "L_compare"),
        ("loss_match", "C3", "L_match"),
    ):
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
    return save_figure(fig, path)


def save_figure(fig, path: PathLike, tight: bool = False) -> Path:
    """Write a matplotlib figure to ``path`` as a PNG (atomically) and close it.

    ``tight`` crops the margins (``bbox_inches="tight"``).
    """
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight" if tight else None)
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
        ims[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=ims[1:],
            duration=int(1000 / max(fps, 0.1)),
            loop=0,
        )
    return path


def save_video(path: PathLike, frames: List[ImageLike], fps: float = 8.0) -> Path:
    """MP4 of ``frames`` (``io.video.write_video``); a GIF beside it when no MP4 encoder works.

    Returns:
        The path written.
    """
    from .io.video import write_video

    return write_video(path, frames, fps=fps)


# ----------------------------------------------------------------------------------------------
# batches: thumbnails and the contact sheet
# ----------------------------------------------------------------------------------------------


def save_thumbnail(
    path: PathLike, model, query, c2w, bg, side: int = 192, backend: str = "auto"
) -> Path:
    """Half-and-half blend of the render at ``c2w`` over the photo of ``query``.

    ``query`` is a localization ``Query``; the longer side is ``side`` px; written to ``path``.
    """
    from .localization.state import resize_image
    from .render import render

    intr = query.intrinsics
    s = min(1.0, float(side) / max(intr.width, intr.height))
    small = intr.scaled(s) if s != 1.0 else intr
    photo = resize_image(query.rgb.float().cpu(), small.height, small.width).clamp(0, 1)
    w2c = torch.as_tensor(
        np.linalg.inv(np.asarray(c2w, np.float64)), dtype=model.dtype, device=model.device
    )
    with torch.no_grad():
        img = (
            render(
                model,
                small,
                w2c,
                torch.as_tensor(bg, dtype=model.dtype, device=model.device),
                backend=backend,
            )
            .color.clamp(0, 1)
            .float()
            .cpu()
        )
    return save_image(path, 0.5 * img + 0.5 * photo)


def _label(canvas: np.ndarray, text: str, xy, scale: float = 0.38, colour=(255, 255, 255)) -> None:
    import cv2

    x, y = xy
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def contact_sheet(
    path: PathLike,
    rows: Sequence[Dict[str, Any]],
    base_dir: PathLike,
    columns: int = 8,
    cell: int = 192,
    border: int = 5,
    max_photos: int = 400,
) -> Path:
    """One picture of a batch: each photo's thumbnail framed in its verdict's colour.

    Thumbnails are ``row["thumb"]``, relative to ``base_dir``; colours :data:`VERDICT_COLOURS`;
    each cell has the photo's name and, when the truth is known, its errors. Photos without a
    thumbnail get a grey cell. Rows after ``max_photos`` are left out (the sheet says so).
    """
    from PIL import Image

    if not rows:
        raise ValueError("rows is empty: no photo to put on a contact sheet")
    if isinstance(columns, bool) or not isinstance(columns, int) or columns < 1:
        raise ValueError(f"columns must be a positive int, got {columns!r}")
    shown = list(rows)[:max_photos]
    cols = min(columns, len(shown))
    nrows = (len(shown) + cols - 1) // cols
    pitch = cell + 2 * border
    header = 24
    canvas = np.full((header + nrows * pitch, cols * pitch, 3), 30, np.uint8)
    counts = {k: sum(1 for r in rows if r.get("status") == k) for k in VERDICT_COLOURS}
    title = "  ".join(f"{k} {v}" for k, v in counts.items()) + (
        f"   (first {len(shown)} of {len(rows)})" if len(rows) > len(shown) else ""
    )
    _label(canvas, title, (6, 17), 0.5)
    base = Path(base_dir)
    for i, r in enumerate(shown):
        y0, x0 = header + (i // cols) * pitch, (i % cols) * pitch
        colour = VERDICT_COLOURS.get(r.get("status"), (128, 128, 128))
        canvas[y0 : y0 + pitch, x0 : x0 + pitch] = colour
        tile = np.full((cell, cell, 3), 70, np.uint8)
        thumb = r.get("thumb")
        if thumb and (base / thumb).is_file():
            im = Image.open(base / thumb).convert("RGB")
            f = cell / max(im.size)
            im = im.resize(
                (max(1, round(im.size[0] * f)), max(1, round(im.size[1] * f))), Image.BILINEAR
            )
            a = np.asarray(im)
            oy, ox = (cell - a.shape[0]) // 2, (cell - a.shape[1]) // 2
            tile[oy : oy + a.shape[0], ox : ox + a.shape[1]] = a
        canvas[y0 + border : y0 + border + cell, x0 + border : x0 + border + cell] = tile
        name = str(r.get("name", "?"))
        _label(
            canvas,
            name if len(name) <= 26 else "..." + name[-23:],
            (x0 + border + 3, y0 + border + 13),
        )
        err = r.get("rot_err_deg")
        line = str(r.get("status", "?"))
        if err is not None:
            t = r.get("trans_err_rel")
            line += f"  {err:.2f} deg" + ("" if t is None else f"  {100 * t:.2f}%")
        _label(canvas, line, (x0 + border + 3, y0 + border + cell - 6))
    return save_image(path, canvas)


# ----------------------------------------------------------------------------------------------
# sequences: the trajectory
# ----------------------------------------------------------------------------------------------


def plot_trajectory(
    path: PathLike,
    est_c2w: Sequence[Optional[np.ndarray]],
    cameras_c2w: Sequence[np.ndarray],
    gt_c2w: Optional[Sequence[Optional[np.ndarray]]] = None,
    statuses: Optional[Sequence[str]] = None,
    title: Optional[str] = None,
) -> Path:
    """The estimated camera path (coloured by verdict) over the scene's cameras.

    The cameras are grey, with their viewing directions; shown in 3D and seen from above (the
    plane of the two widest axes); the true path dashed when known. Written to ``path`` (PNG).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    est = [None if c is None else np.asarray(c, np.float64) for c in est_c2w]
    pts = np.array([c[:3, 3] for c in est if c is not None]).reshape(-1, 3)
    cams = np.array([np.asarray(c)[:3, 3] for c in cameras_c2w]).reshape(-1, 3)
    gts = None
    if gt_c2w is not None and any(g is not None for g in gt_c2w):
        gts = np.array([np.asarray(g)[:3, 3] for g in gt_c2w if g is not None]).reshape(-1, 3)
    allp = np.concatenate(
        [a for a in (pts, cams, gts) if a is not None and len(a)] or [np.zeros((1, 3))]
    )
    span = np.ptp(allp, axis=0) if len(allp) > 1 else np.ones(3)
    ax_a, ax_b = np.argsort(-span)[:2]
    scale = 0.06 * float(max(span.max(), 1e-6))
    fig = plt.figure(figsize=(11, 5), constrained_layout=True)
    a3 = fig.add_subplot(1, 2, 1, projection="3d")
    a2 = fig.add_subplot(1, 2, 2)
    if len(cams):
        a3.scatter(cams[:, 0], cams[:, 1], cams[:, 2], s=8, c="0.6", label="scene cameras")
        a2.scatter(cams[:, ax_a], cams[:, ax_b], s=8, c="0.6", label="scene cameras")
        for c in cameras_c2w:
            c = np.asarray(c)
            p, d = c[:3, 3], c[:3, 2] * scale
            a3.plot([p[0], p[0] + d[0]], [p[1], p[1] + d[1]], [p[2], p[2] + d[2]], c="0.7", lw=0.6)
            a2.plot([p[ax_a], p[ax_a] + d[ax_a]], [p[ax_b], p[ax_b] + d[ax_b]], c="0.7", lw=0.6)
    if gts is not None and len(gts):
        a3.plot(gts[:, 0], gts[:, 1], gts[:, 2], "k--", lw=1, label="true path")
        a2.plot(gts[:, ax_a], gts[:, ax_b], "k--", lw=1, label="true path")
    if len(pts):
        a3.plot(pts[:, 0], pts[:, 1], pts[:, 2], "-", c="C0", lw=1.2, label="estimated path")
        a2.plot(pts[:, ax_a], pts[:, ax_b], "-", c="C0", lw=1.2, label="estimated path")
        st = [s for c, s in zip(est, statuses or ["ok"] * len(est)) if c is not None]
        cols = [np.asarray(VERDICT_COLOURS.get(s, (128, 128, 128))) / 255.0 for s in st]
        a3.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=10, c=cols)
        a2.scatter(pts[:, ax_a], pts[:, ax_b], s=10, c=cols)
        for c in (est[0], next((c for c in reversed(est) if c is not None), None)):
            if c is not None:
                d = c[:3, 2] * scale * 1.5
                a2.arrow(c[ax_a, 3], c[ax_b, 3], d[ax_a], d[ax_b], color="C0", width=scale * 0.05)
    names = "xyz"
    mid, half = 0.5 * (allp.max(0) + allp.min(0)), 0.55 * float(max(span.max(), 1e-6))
    a3.set_xlim(mid[0] - half, mid[0] + half)  # equal axes: a circle stays a circle
    a3.set_ylim(mid[1] - half, mid[1] + half)
    a3.set_zlim(mid[2] - half, mid[2] + half)
    a3.set_xlabel("x")
    a3.set_ylabel("y")
    a3.set_zlabel("z")
    a2.set_xlabel(names[ax_a])
    a2.set_ylabel(names[ax_b])
    a2.set_aspect("equal", adjustable="datalim")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7, loc="best")
    a2.set_title(
        "seen along the narrowest axis (verdict colours: ok green, uncertain orange, failed red)",
        fontsize=8,
    )
    if title:
        fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)


# ----------------------------------------------------------------------------------------------
# benchmarks: our curves beside the paper's numbers
# ----------------------------------------------------------------------------------------------


def _paper_number(paper, interval: str, method: str, metric: str):
    """The paper's value from a mapping keyed (interval, method, metric).

    The key may also have the protocol in front; the value is a number, None or has ``.value``.
    """
    if paper is None:
        return None
    if callable(paper):
        v = paper(interval, method, metric)
    else:
        v = paper.get((interval, method, metric))
        if v is None:
            v = next(
                (
                    x
                    for k, x in paper.items()
                    if isinstance(k, tuple) and len(k) == 4 and k[1:] == (interval, method, metric)
                ),
                None,
            )
    v = getattr(v, "value", v)
    return None if v is None else float(v)


def plot_curves_vs_paper(
    path: PathLike, summary: Dict[str, Any], paper=None, title: Optional[str] = None
) -> Path:
    """Success-rate-vs-iteration curves of a benchmark summary, with the paper's numbers.

    Args:
        path: the PNG to write.
        summary: ``icomma_plugin.benchmark.report.summarize`` output: ``cells``, each with
            ``interval``, ``method`` and ``curves`` (threshold key, e.g. ``"1deg_0.01"`` -> the
            fraction of poses under it after each iteration); cells without curves are skipped.
        paper: the paper's numbers: a mapping ``(interval, method, "success_<key>") -> value``
            (a float, None, or a ``PaperValue``; keys may carry the protocol first), or a callable
            ``(interval, method, metric) -> value``, e.g.
            ``lambda iv, m, k: paper_value(protocol, iv, m, k)``. A known value is drawn as a
            dotted horizontal line in the curve's colour, labelled at the right end; an unknown
            one is listed as "paper n/a" in the panel's legend.
        title: the figure's title (default: the summary's protocol).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    cells = [c for c in summary.get("cells", []) if c.get("curves")]
    if not cells:
        raise ValueError("summary has no cells with 'curves' (run a curves or time protocol)")
    ivs = list(dict.fromkeys(c["interval"] for c in cells))
    fig, axes = plt.subplots(1, len(ivs), figsize=(4.4 * len(ivs), 3.6), squeeze=False, sharey=True)
    styles = ["-", "--", ":", "-."]
    colour_of: Dict[str, str] = {}
    for j, iv in enumerate(ivs):
        ax = axes[0, j]
        missing = []
        for c in (c for c in cells if c["interval"] == iv):
            m = c["method"]
            col = colour_of.setdefault(m, f"C{len(colour_of)}")
            for s, (tk, ys) in enumerate(c["curves"].items()):
                ys = np.asarray(ys, np.float64)
                x = np.arange(len(ys))
                label = f"{m} ({tk.replace('deg_', ' deg, ')})"
                ax.plot(x, ys, styles[s % len(styles)], color=col, lw=1.4, label=label)
                pv = _paper_number(paper, iv, m, f"success_{tk}")
                if pv is None:
                    missing.append(label)
                else:
                    ax.axhline(pv, color=col, ls=":", lw=1.0, alpha=0.8)
                    ax.annotate(
                        f"paper {100 * pv:.0f}% ({tk.replace('deg_', ' deg, ')})",
                        (x[-1], pv),
                        fontsize=7,
                        color=col,
                        ha="right",
                        va="bottom",
                    )
        if missing:
            ax.plot([], [], " ", label="paper n/a: " + "; ".join(missing))
        ax.set_title(str(iv))
        ax.set_xlabel("iteration")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="lower right")
    axes[0, 0].set_ylabel("fraction of poses under the threshold")
    fig.suptitle(
        title
        or f"{summary.get('protocol', 'benchmark')}: ours (curves), the paper's numbers "
        "(dotted horizontal lines)",
        fontsize=9,
    )
    return save_figure(fig, path, tight=True)
