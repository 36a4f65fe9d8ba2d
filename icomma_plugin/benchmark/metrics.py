"""Benchmark metrics: success fractions (per iteration), pose AUC, failures, time to success.

Conventions: rotation errors in degrees (the angle of ``R_est R_gt^T``, iComMa's metric, computed
well-conditioned by ``pose.convert.rotation_error_deg``), translation errors as camera-centre
distances in the benchmark's translation unit (world distance / translation scale; the scale is 1
in world units; see docs/BENCHMARK.md). Success is strict: ``rot < rot_thr and trans <
trans_thr``. A missing value (None / NaN, e.g. a failed baseline) counts as a failure and as an
infinite error.
"""
from __future__ import annotations

import math
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

__all__ = ["as_errors", "success_mask", "pad_curves", "success_curve", "pose_auc",
           "failure_stats", "time_to_success", "mean_or_none"]


def as_errors(values: Iterable) -> np.ndarray:
    """Float64 array with None / NaN replaced by +inf."""
    arr = np.array([np.inf if v is None else float(v) for v in values], dtype=np.float64)
    arr[np.isnan(arr)] = np.inf
    return arr


def success_mask(rot, trans, rot_thr: float, trans_thr: Optional[float]) -> np.ndarray:
    """``rot < rot_thr`` and (``trans < trans_thr`` unless ``trans_thr`` is None)."""
    r = as_errors(np.ravel(rot))
    ok = r < float(rot_thr)
    if trans_thr is not None:
        t = as_errors(np.ravel(trans))
        if t.shape != r.shape:
            raise ValueError(
                f"rot and trans must have the same length, got {r.shape} and {t.shape}"
            )
        ok &= t < float(trans_thr)
    return ok


def pad_curves(curves: Sequence[Sequence[float]], length: Optional[int] = None) -> np.ndarray:
    """Stack per-run curves ``[N][T_i]`` into ``[N, length]``, each run's last value carried on.

    A run that stopped early keeps its final pose. ``length`` defaults to the longest.
    """
    if len(curves) == 0:
        return np.zeros((0, length or 0))
    L = max(len(c) for c in curves) if length is None else int(length)
    out = np.empty((len(curves), L), dtype=np.float64)
    for i, c in enumerate(curves):
        a = as_errors(c)
        if len(a) == 0:
            out[i] = np.inf
            continue
        n = min(len(a), L)
        out[i, :n] = a[:n]
        out[i, n:] = a[n - 1] if n == len(a) else a[L - 1]
    return out


def success_curve(rot_curves, trans_curves, rot_thr: float, trans_thr: Optional[float],
                  length: Optional[int] = None) -> np.ndarray:
    """Fraction of runs whose pose meets (rot_thr, trans_thr) after each iteration.

    ``rot_curves[i][k]`` is run i's rotation error after k iterations (k = 0 is the initial pose).

    Returns:
        ``[length]`` (0 rows -> zeros).
    """
    R = pad_curves(rot_curves, length)
    if R.shape[0] == 0:
        return np.zeros(R.shape[1])
    T = pad_curves(trans_curves, R.shape[1])
    ok = R < float(rot_thr)
    if trans_thr is not None:
        ok &= T < float(trans_thr)
    return ok.mean(axis=0)


def pose_auc(errors, thresholds: Sequence[float]) -> List[float]:
    """Area under the recall-vs-error curve up to each threshold, divided by the threshold.

    SuperGlue / LoFTR ``pose_auc``; the relative-pose AUC@5/10/20 of image matching papers.
    A perfect method scores 1; None / NaN / inf errors count as failures (never recalled).
    """
    e = np.sort(as_errors(errors))
    n = len(e)
    out = []
    for t in thresholds:
        t = float(t)
        if n == 0:
            out.append(0.0)
            continue
        recall = np.arange(1, n + 1, dtype=np.float64) / n
        ee = np.concatenate([[0.0], e])
        rr = np.concatenate([[0.0], recall])
        last = int(np.searchsorted(ee, t))
        r = np.concatenate([rr[:last], [rr[last - 1]]])
        x = np.concatenate([ee[:last], [t]])
        out.append(float(np.trapezoid(r, x=x) / t) if hasattr(np, "trapezoid")
                   else float(np.trapz(r, x=x) / t))
    return out


def mean_or_none(values) -> Optional[float]:
    """Mean of the finite values (None values skipped); None when there are none."""
    a = np.asarray([v for v in values if v is not None and math.isfinite(float(v))], np.float64)
    return float(a.mean()) if a.size else None


def failure_stats(
    rot, trans, rot_thr: float, trans_thr: Optional[float]
) -> Dict[str, Optional[float]]:
    """Failure rate and the mean errors of the successes (the paper's ablation columns)."""
    r, t = as_errors(np.ravel(rot)), as_errors(np.ravel(trans))
    ok = success_mask(r, t, rot_thr, trans_thr)
    n = int(r.size)
    return {
        "n": n,
        "successes": int(ok.sum()),
        "failures": int(n - ok.sum()),
        "failure_rate": (float(1.0 - ok.mean()) if n else None),
        "success_rate": (float(ok.mean()) if n else None),
        "mean_rot_deg": mean_or_none(r[ok]),
        "mean_trans": mean_or_none(t[ok]),
        "median_rot_deg": float(np.median(r[ok])) if ok.any() else None,
        "median_trans": float(np.median(t[ok])) if ok.any() else None,
    }


def time_to_success(rot_curve, trans_curve, cum_seconds, rot_thr: float,
                    trans_thr: Optional[float]) -> Optional[float]:
    """Seconds until the pose first meets the thresholds (None if it never does).

    ``rot_curve[k]`` / ``trans_curve[k]`` are the errors after k iterations and ``cum_seconds[k]``
    the time spent to get there (``cum_seconds[0] = 0``).
    """
    ok = success_mask(rot_curve, trans_curve, rot_thr, trans_thr)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return None
    k = int(idx[0])
    cs = list(cum_seconds)
    if not cs:
        return None
    return float(cs[min(k, len(cs) - 1)])
