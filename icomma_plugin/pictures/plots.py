"""Plots: a localization's convergence, a sequence's trajectory, a benchmark beside the paper."""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Dict, Optional, Sequence

import numpy as np

from ..io.atomic import atomic_path
from ..io.video import PathLike
from .images import VERDICT_COLOURS

logger = logging.getLogger(__name__)


__all__ = ["plot_convergence", "plot_curves_vs_paper", "plot_trajectory", "save_figure"]


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



def plot_focal_passes(path: PathLike, passes: Sequence[Dict[str, Any]],
                      title: Optional[str] = None) -> Path:
    """Each photo's preferred focal length, pass after pass, and the one each pass used.

    ``passes``: ``{"used": share of the given focal length, "estimates": {photo: share or
    None}}`` in order (a batch's ``poses.focal.json``); the photos in the order of the first pass.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    names = list(passes[0]["estimates"]) if passes else []
    x = {n: i for i, n in enumerate(names)}
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    ax.axhline(1.0, color="0.6", lw=1, ls=":", label="given")
    for k, p in enumerate(passes):
        colour = f"C{k % 10}"
        pts = [(x.get(n, len(x)), v) for n, v in p["estimates"].items() if v is not None]
        if pts:
            xs, ys = zip(*pts)
            ax.plot(xs, ys, "o", ms=4, color=colour, alpha=0.8,
                    label=f"pass {k + 1}: localized at {p['used']:.4f}")
        ax.axhline(p["used"], color=colour, lw=1.2)
    ax.set_xlabel("photo")
    ax.set_ylabel("focal length its matches prefer\n(share of the given one)")
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title or "the batch's focal length from its photos", fontsize=9)
    return save_figure(fig, path, tight=True)


def plot_focal_frames(path: PathLike, frames: Sequence[int], used: Sequence[float],
                      preferred: Sequence[Optional[float]], title: Optional[str] = None) -> Path:
    """A sequence's focal length frame by frame, as shares of the given one.

    ``used``: the one each frame was localized with (a line); ``preferred``: the one its
    matches prefer (dots; None: no refit).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    ax.axhline(1.0, color="0.6", lw=1, ls=":", label="given")
    pts = [(i, v) for i, v in zip(frames, preferred) if v is not None]
    if pts:
        xs, ys = zip(*pts)
        ax.plot(xs, ys, "o", ms=3, color="C0", alpha=0.7, label="the frame's matches prefer")
    ax.step(list(frames), list(used), where="mid", color="C3", lw=1.5,
            label="the frame was localized with")
    ax.set_xlabel("frame")
    ax.set_ylabel("focal length\n(share of the given one)")
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title or "the sequence's focal length from its frames", fontsize=9)
    return save_figure(fig, path, tight=True)


def plot_trajectory(
    path: PathLike,
    est_c2w: Sequence[Optional[np.ndarray]],
    cameras_c2w: Sequence[np.ndarray],
    gt_c2w: Optional[Sequence[Optional[np.ndarray]]] = None,
    statuses: Optional[Sequence[str]] = None,
    title: Optional[str] = None,
    flagged: Optional[Sequence[bool]] = None,
    labels: Optional[Dict[str, str]] = None,
) -> Path:
    """The estimated camera path (coloured by verdict) over the scene's cameras.

    The cameras are grey, with their viewing directions; shown in 3D and seen from above (the
    plane of the two widest axes); the true path dashed when known. Written to ``path`` (PNG).
    ``flagged`` (one bool per estimated pose, e.g. an audit's flagged cameras): those poses are
    ringed in magenta, joined to their ``gt_c2w`` (same order) by a magenta line when it is given.
    ``labels`` renames the legend's ``estimated``, ``truth`` and ``cameras`` entries.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    names = {"estimated": "estimated path", "truth": "true path", "cameras": "scene cameras",
             **(labels or {})}
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
        a3.scatter(cams[:, 0], cams[:, 1], cams[:, 2], s=8, c="0.6", label=names["cameras"])
        a2.scatter(cams[:, ax_a], cams[:, ax_b], s=8, c="0.6", label=names["cameras"])
        # the viewing directions as one collection per view (one artist, not two per camera)
        from matplotlib.collections import LineCollection
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        ends = cams + np.array([np.asarray(c)[:3, 2] for c in cameras_c2w]).reshape(-1, 3) * scale
        segs = np.stack([cams, ends], axis=1)  # [N, 2, 3]
        a3.add_collection3d(Line3DCollection(segs, colors="0.7", linewidths=0.6))
        a2.add_collection(LineCollection(segs[:, :, [ax_a, ax_b]], colors="0.7", linewidths=0.6))
    if gts is not None and len(gts):
        a3.plot(gts[:, 0], gts[:, 1], gts[:, 2], "k--", lw=1, label=names["truth"])
        a2.plot(gts[:, ax_a], gts[:, ax_b], "k--", lw=1, label=names["truth"])
    if len(pts):
        a3.plot(pts[:, 0], pts[:, 1], pts[:, 2], "-", c="C0", lw=1.2, label=names["estimated"])
        a2.plot(pts[:, ax_a], pts[:, ax_b], "-", c="C0", lw=1.2, label=names["estimated"])
        st = [s for c, s in zip(est, statuses or ["ok"] * len(est)) if c is not None]
        cols = [np.asarray(VERDICT_COLOURS.get(s, (128, 128, 128))) / 255.0 for s in st]
        a3.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=10, c=cols)
        a2.scatter(pts[:, ax_a], pts[:, ax_b], s=10, c=cols)
        for c in (est[0], next((c for c in reversed(est) if c is not None), None)):
            if c is not None:
                d = c[:3, 2] * scale * 1.5
                a2.arrow(c[ax_a, 3], c[ax_b, 3], d[ax_a], d[ax_b], color="C0", width=scale * 0.05)
    if flagged is not None:
        _mark_flagged(a3, a2, (ax_a, ax_b), est, gt_c2w, flagged)
    _trajectory_axes(a3, a2, allp, span, (ax_a, ax_b))
    if title:
        fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)


def _trajectory_axes(a3, a2, allp: np.ndarray, span: np.ndarray, axes2d) -> None:
    """Equal axes around every point drawn (a circle stays a circle), labels, legend, title."""
    ax_a, ax_b = axes2d
    mid, half = 0.5 * (allp.max(0) + allp.min(0)), 0.55 * float(max(span.max(), 1e-6))
    a3.set_xlim(mid[0] - half, mid[0] + half)
    a3.set_ylim(mid[1] - half, mid[1] + half)
    a3.set_zlim(mid[2] - half, mid[2] + half)
    a3.set_xlabel("x")
    a3.set_ylabel("y")
    a3.set_zlabel("z")
    a2.set_xlabel("xyz"[ax_a])
    a2.set_ylabel("xyz"[ax_b])
    a2.set_aspect("equal", adjustable="datalim")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7, loc="best")
    a2.set_title(
        "seen along the narrowest axis (verdict colours: ok green, uncertain orange, failed red)",
        fontsize=8,
    )


def _mark_flagged(a3, a2, axes2d, est, gt_c2w, flagged) -> None:
    """Ring the flagged estimated centres in magenta; join each to its truth when known."""
    if len(flagged) != len(est):
        raise ValueError(f"flagged must have one bool per estimated pose ({len(est)}), got "
                         f"{len(flagged)}")
    ax_a, ax_b = axes2d
    gts = list(gt_c2w) if gt_c2w is not None and len(gt_c2w) == len(est) else [None] * len(est)
    first = True
    for c, g, f in zip(est, gts, flagged):
        if not f or c is None:
            continue
        p = c[:3, 3]
        label = "flagged" if first else None
        first = False
        a3.scatter([p[0]], [p[1]], [p[2]], s=90, facecolors="none", edgecolors="m",
                   linewidths=1.5, label=label)
        a2.scatter([p[ax_a]], [p[ax_b]], s=90, facecolors="none", edgecolors="m",
                   linewidths=1.5, label=label)
        if g is not None:
            q = np.asarray(g, np.float64)[:3, 3]
            a3.plot([q[0], p[0]], [q[1], p[1]], [q[2], p[2]], "m-", lw=1.2)
            a2.plot([q[ax_a], p[ax_a]], [q[ax_b], p[ax_b]], "m-", lw=1.2)


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
