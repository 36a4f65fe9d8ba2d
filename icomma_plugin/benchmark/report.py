"""Summaries, markdown tables beside the paper's numbers, and plots.

``summarize(spec, records, calibration=None)`` reduces the per-run records of one protocol to
per-(interval, method) numbers (the verdict's precision and recall also with a model's calibrated
thresholds when one is given: ``localization/calibration.py``); ``markdown(...)`` writes them
next to the paper's cells (:mod:`.paper`) with the paper's source and a Δ column (ours - paper,
only where the paper's value is known); ``save_plots(...)`` draws the success-vs-iteration
curves and the AUC / success / failure bars.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from ..pose.precision import WITHIN_SIGMAS
from .metrics import failure_stats, mean_or_none, pose_auc, success_curve, success_mask
from .paper import NOT_FOUND, PaperValue, paper_value
from .protocols import METHODS, ProtocolSpec
from .runner import threshold_key

__all__ = ["calibrated_status", "summarize", "table_rows", "markdown", "save_plots",
           "paper_method", "record_stats", "verdict_stats"]

PERCENT_METRICS = (
    "success_rate",
    "failure_rate",
    "verdict_precision",
    "verdict_recall",
    "wrong_flagged",
    "verdict_precision_calibrated",
    "verdict_recall_calibrated",
    "wrong_flagged_calibrated",
    "within_record",
)

#: The metrics of the verdict with a model's calibrated thresholds (in a cell only when the
#: summary was given a calibration).
CALIBRATED_METRICS = ("verdict_precision_calibrated", "verdict_recall_calibrated",
                      "wrong_flagged_calibrated")

#: The metrics of the queries' records' own precision (in a cell only when the capture has
#: COLMAP tracks: ``io/datasets/colmap_tracks.py``).
RECORD_METRICS = ("median_record_rot_std_deg", "within_record")


def record_stats(records: Sequence[Dict[str, Any]]) -> Dict[str, Any]:
    """How precisely the capture's tracks fix the queries' records, beside the errors.

    ``median_record_rot_std_deg``: the median of the runs' record rms rotation uncertainty;
    ``within_record``: the share of those runs whose pose lies within its record's uncertainty
    (``record_sigmas``, the rotation's Mahalanobis distance, at most ``WITHIN_SIGMAS``; a run
    without a pose is not). Empty when no run's query has a record precision.
    """
    rs = [r for r in records if r.get("record_rot_std_deg")]
    if not rs:
        return {}
    within = [r.get("record_sigmas") is not None and r["record_sigmas"] <= WITHIN_SIGMAS
              for r in rs]
    return {"median_record_rot_std_deg": float(np.median([r["record_rot_std_deg"] for r in rs])),
            "within_record": float(np.mean(within))}


def _groups(spec: ProtocolSpec, records: Sequence[Dict[str, Any]]):
    g: "OrderedDict[tuple, list]" = OrderedDict()
    for iv in spec.intervals:
        for m in spec.methods:
            g[(iv.label, m)] = []
    for r in records:
        k = (r["interval"], r["method"])
        if k in g:
            g[k].append(r)
    return g


def summarize(spec: ProtocolSpec, records: Sequence[Dict[str, Any]],
              calibration=None) -> Dict[str, Any]:
    """Per-(interval, method) numbers of one protocol (JSON-ready).

    ``calibration``: a model's calibrated ``VerdictConfig`` (or None): the verdict statistics are
    then also given with it (:func:`verdict_stats`).
    """
    out: Dict[str, Any] = {"protocol": spec.name, "kind": spec.kind, "cells": []}
    L = spec.max_iterations + 1
    for (iv, m), rs in _groups(spec, records).items():
        cell: Dict[str, Any] = {"interval": iv, "method": m, "n": len(rs)}
        rot = [r.get("rot_err_deg") for r in rs]
        trans = [r.get("trans_err_rel") for r in rs]
        cell["mean_init_rot_deg"] = mean_or_none(r.get("init_rot_err_deg") for r in rs)
        cell["mean_init_trans"] = mean_or_none(r.get("init_trans_err_rel") for r in rs)
        if m == "essential":
            cell["num_failed_estimates"] = sum(1 for x in rot if x is None)
            cell["mean_num_matches"] = mean_or_none(r.get("num_matches") for r in rs)
        else:
            cell["mean_seconds"] = mean_or_none(r.get("seconds") for r in rs)
            secs = [r.get("seconds") for r in rs if r.get("seconds") is not None]
            cell["median_seconds"] = float(np.median(secs)) if secs else None
            cell["mean_iterations"] = mean_or_none(r.get("iterations") for r in rs)
            cell.update(verdict_stats(rs, spec.thresholds[0], calibration))
            cell.update(record_stats(rs))
        cell["num_errors"] = sum(1 for r in rs if r.get("error"))
        if spec.kind == "relative_pose":
            aucs = pose_auc(rot, spec.auc_thresholds) if rs else [None] * len(spec.auc_thresholds)
            for t, a in zip(spec.auc_thresholds, aucs):
                cell[f"auc{t:g}"] = a
            cell["median_rot_deg"] = (
                float(np.median([x if x is not None else np.inf for x in rot])) if rs else None
            )
        if m != "essential":
            for a, b in spec.thresholds:
                ok = success_mask(rot, trans, a, b) if rs else np.zeros(0, bool)
                cell["success_" + threshold_key(a, b)] = float(ok.mean()) if rs else None
                if rs and all(
                    r.get("trans_err", None) is not None or r.get("rot_err_deg") is None
                    for r in rs
                ):
                    # the same threshold read in WORLD units (for papers that do not normalise)
                    okw = success_mask(rot, [r.get("trans_err") for r in rs], a, b)
                    cell["success_" + threshold_key(a, b) + "_world_units"] = float(okw.mean())
            if spec.kind in ("curves", "time") and rs and all("curve_rot_deg" in r for r in rs):
                cell["curves"] = {
                    threshold_key(a, b): [round(float(v), 5) for v in success_curve(
                        [r["curve_rot_deg"] for r in rs], [r["curve_trans"] for r in rs], a, b, L)]
                    for a, b in spec.thresholds}
            if spec.kind == "time":
                a, b = spec.thresholds[0]
                tk = threshold_key(a, b)
                ok = success_mask(rot, trans, a, b) if rs else np.zeros(0, bool)
                cell["success_rate"] = float(ok.mean()) if rs else None
                cell["seconds_to_success"] = mean_or_none(
                    r.get("time_to_success", {}).get(tk) for r, s in zip(rs, ok) if s)
                cell["seconds_total_success"] = mean_or_none(
                    r.get("seconds") for r, s in zip(rs, ok) if s
                )
            if spec.kind == "ablation":
                a, b = spec.thresholds[0]
                cell.update({k: v for k, v in failure_stats(rot, trans, a, b).items() if k != "n"})
        out["cells"].append(cell)
    return out


def _trust(verdicts: Sequence[Optional[str]], ok: np.ndarray, suffix: str = ""
           ) -> Dict[str, Any]:
    """Counts, precision, recall and wrong poses flagged of ``verdicts`` against ``ok``."""
    called = np.array([v == "ok" for v in verdicts], bool)
    out: Dict[str, Any] = {
        f"verdict_{k}{suffix}": sum(1 for v in verdicts if v == k)
        for k in ("ok", "uncertain", "failed")
    }
    n_called, n_right, n_wrong = int(called.sum()), int(ok.sum()), int((~ok).sum())
    out[f"verdict_precision{suffix}"] = float((called & ok).sum() / n_called) if n_called else None
    out[f"verdict_recall{suffix}"] = float((called & ok).sum() / n_right) if n_right else None
    flagged = np.array([v in ("uncertain", "failed") for v in verdicts], bool)
    out[f"wrong_flagged{suffix}"] = float((flagged & ~ok).sum() / n_wrong) if n_wrong else None
    return out


def calibrated_status(record: Dict[str, Any], calibration) -> Optional[str]:
    """A record's verdict under a model's calibrated thresholds.

    Re-decided from its ``signals`` (``calibration.redecide``); the stricter of that and the
    recorded status (a calibration never turns a doubt into ``ok``). As recorded when the record
    has no score to re-decide from.
    """
    from ..localization.calibration import redecide, stricter

    status = record.get("status")
    v = redecide(record.get("signals") or {}, calibration)
    return status if v is None else stricter(status, v.status)


def verdict_stats(records: Sequence[Dict[str, Any]], threshold, calibration=None
                  ) -> Dict[str, Any]:
    """How far the verdict can be trusted, against ground truth.

    Counts of ok / uncertain / failed, precision (right among the poses called ok), recall (called
    ok among the right poses), the share of wrong poses flagged (called uncertain or failed), and
    the median final rotation error (all runs, and the successes). With ``calibration`` (a
    model's calibrated ``VerdictConfig``), the counts, precision, recall and wrong poses flagged
    again with each verdict re-decided under it (:func:`calibrated_status`; keys ``*_calibrated``).
    """
    a, b = threshold
    rot = [r.get("rot_err_deg") for r in records]
    trans = [r.get("trans_err_rel") for r in records]
    ok = success_mask(rot, trans, a, b) if records else np.zeros(0, bool)
    out = _trust([r.get("status") for r in records], ok)
    if calibration is not None:
        out.update(_trust([calibrated_status(r, calibration) for r in records], ok,
                          "_calibrated"))
    r_all = [x for x in rot if x is not None]
    out["median_rot_deg"] = float(np.median(r_all)) if r_all else None
    r_ok = [x for x, s in zip(rot, ok) if s and x is not None]
    out["median_rot_deg_success"] = float(np.median(r_ok)) if r_ok else None
    return out


def paper_method(method: str, matcher: Optional[str]) -> str:
    """Our method name -> the paper's row for it (the essential baseline by matcher family)."""
    if method != "essential":
        return method
    name = (matcher or "").lower()
    if "loftr" in name:
        return "essential_loftr"
    if "lightglue" in name or "xfeat" in name or "glue" in name:
        return "essential_lightglue"
    return "essential_" + (name or "unknown")


def _metrics_of(spec: ProtocolSpec, method: str) -> List[str]:
    extra = (
        []
        if method == "essential"
        else [
            "median_rot_deg",
            "median_seconds",
            "verdict_precision",
            "verdict_recall",
            "wrong_flagged",
            *CALIBRATED_METRICS,
            *RECORD_METRICS,
            "num_errors",
        ]
    )
    if spec.kind == "curves":
        return ["success_" + threshold_key(a, b) for a, b in spec.thresholds] + extra
    if spec.kind == "time":
        return ["success_rate", "seconds_to_success", "seconds"] + extra
    if spec.kind == "relative_pose":
        return [f"auc{t:g}" for t in spec.auc_thresholds] + extra
    if spec.kind == "ablation":
        return ["failure_rate", "mean_rot_deg", "mean_trans"] + extra
    return []


def _our_value(cell: Dict[str, Any], metric: str):
    if metric == "seconds":
        return cell.get("mean_seconds")
    return cell.get(metric)


def table_rows(
    spec: ProtocolSpec, summary: Dict[str, Any], matcher: Optional[str]
) -> List[Dict[str, Any]]:
    """Rows (interval, method, metric, ours, paper, source, delta) for the markdown / JSON."""
    rows = []
    for cell in summary["cells"]:
        pm = paper_method(cell["method"], matcher)
        for metric in _metrics_of(spec, cell["method"]):
            if cell["method"] == "essential" and not metric.startswith("auc"):
                continue
            if metric in CALIBRATED_METRICS + RECORD_METRICS and metric not in cell:
                continue  # no calibration given, or no tracks to tell a record's precision
            pmetric = "success_rate" if metric == "success_rate" else metric
            pv: PaperValue = paper_value(
                spec.name, cell["interval"], pm, pmetric, spec.paper_dataset
            )
            ours = _our_value(cell, metric)
            delta = (ours - pv.value) if (ours is not None and pv.value is not None) else None
            rows.append({"interval": cell["interval"], "method": cell["method"], "paper_method": pm,
                         "metric": metric, "n": cell["n"], "ours": ours, "paper": pv.value,
                         "paper_note": pv.note, "source": pv.source, "delta": delta})
    return rows


def _fmt(v, metric: str) -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf"
    if metric.startswith("success") or metric in PERCENT_METRICS:
        return f"{100.0 * v:.1f}%"
    if metric.startswith("auc"):
        return f"{100.0 * v:.1f}"
    if "seconds" in metric:
        return f"{v:.2f} s"
    if metric == "num_errors":
        return str(int(v))
    return f"{v:.4g}"


def markdown(spec: ProtocolSpec, summary: Dict[str, Any], matcher: Optional[str],
             header: Optional[Dict[str, Any]] = None) -> str:
    """One protocol's markdown section: the setup line and the side-by-side table."""
    lines = [f"## {spec.name} ({spec.kind})", ""]
    if spec.description:
        lines += [spec.description, ""]
    h = header or {}
    size = (
        f"{spec.num_queries} queries x {spec.poses_per_query} poses x {len(spec.intervals)} "
        "intervals, "
        f"max {spec.max_iterations} iterations" + (" (quick)" if spec.quick else " (full size)")
    )
    lines.append(f"- size: {size}")
    for k, v in h.items():
        lines.append(f"- {k}: {v}")
    lines.append(
        "- thresholds: " + ", ".join(f"< {a:g} deg and < {b:g}" for a, b in spec.thresholds)
    )
    lines.append("- methods: " + "; ".join(f"`{m}` = {METHODS[m]}" for m in spec.methods))
    lines.append("")
    rows = table_rows(spec, summary, matcher)
    lines.append(
        "| interval | method | metric | n | ours | paper | Δ (ours − paper) | paper source |"
    )
    lines.append("|---|---|---|---|---|---|---|---|")
    missing = 0
    for r in rows:
        known = r["paper"] is not None
        missing += not known
        paper_txt = _fmt(r["paper"], r["metric"]) if known else "–"
        delta = _fmt(r["delta"], r["metric"]) if r["delta"] is not None else "–"
        source = r["source"] if known else "–"
        lines.append(f"| {r['interval']} | {r['method']} | {r['metric']} | {r['n']} | "
                     f"{_fmt(r['ours'], r['metric'])} | {paper_txt} | {delta} | {source} |")
    if missing:
        lines += ["", f"A – in the paper's columns: {NOT_FOUND} ({missing} of {len(rows)} rows)."]
    if any(r["metric"] in RECORD_METRICS for r in rows):
        lines += ["", "`median_record_rot_std_deg`: how precisely the capture's own COLMAP tracks "
                  "fix the queries' recorded poses (rms rotation, first order, the points free); "
                  "a perfect method would land about 0.9x this from them (median). "
                  "`within_record`: the runs whose rotation lies within its record's uncertainty "
                  f"(Mahalanobis distance <= {WITHIN_SIGMAS:g}, 99 %; docs/AUDIT.md)."]
    lines.append("")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# plots (matplotlib, Agg)
# ----------------------------------------------------------------------------------------------


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_plots(
    spec: ProtocolSpec, summary: Dict[str, Any], out_dir, matcher: Optional[str] = None
) -> List[str]:
    """Write the protocol's PNGs into ``out_dir``; returns their file names."""
    from ..pictures import save_figure

    plt = _plt()
    out_dir = Path(out_dir)
    files: List[str] = []
    cells = summary["cells"]
    ivs = [iv.label for iv in spec.intervals]
    meths = list(spec.methods)

    if spec.kind in ("curves", "time") and any("curves" in c for c in cells):
        fig, axes = plt.subplots(
            1, len(ivs), figsize=(4.2 * len(ivs), 3.4), squeeze=False, sharey=True
        )
        styles = ["-", "--", ":", "-."]
        for j, iv in enumerate(ivs):
            ax = axes[0, j]
            for c in cells:
                if c["interval"] != iv or "curves" not in c:
                    continue
                for s, (tk, ys) in enumerate(c["curves"].items()):
                    ax.plot(np.arange(len(ys)), ys, styles[s % len(styles)],
                            label=f"{c['method']} ({tk.replace('deg_', '°, ')})")
            ax.set_title(f"{spec.name}: {iv}")
            ax.set_xlabel("iteration")
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
        axes[0, 0].set_ylabel("fraction of poses under threshold")
        for ax in axes[0][::-1]:
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="lower right")
                break
        name = f"success_vs_iteration_{spec.name}.png"
        save_figure(fig, out_dir / name, tight=True)
        files.append(name)
        # the same curves with the paper's final numbers drawn beside them (where it has them)
        from ..pictures import plot_curves_vs_paper

        def paper(iv, m, metric):
            key = "success_rate" if spec.kind == "time" else metric
            return paper_value(spec.name, iv, paper_method(m, matcher), key, spec.paper_dataset)

        name = f"curves_vs_paper_{spec.name}.png"
        plot_curves_vs_paper(
            out_dir / name,
            summary,
            paper,
            title=f"{spec.name}: ours (lines) and the paper (dotted, where it reports a number)",
        )
        files.append(name)

    def bars(metric_keys: List[str], title: str, name: str, ylabel: str, scale: float = 1.0):
        fig, axes = plt.subplots(
            1, len(ivs), figsize=(4.2 * len(ivs), 3.2), squeeze=False, sharey=True
        )
        width = 0.8 / max(1, len(meths))
        for j, iv in enumerate(ivs):
            ax = axes[0, j]
            x = np.arange(len(metric_keys))
            for i, m in enumerate(meths):
                c = next((c for c in cells if c["interval"] == iv and c["method"] == m), None)
                vals = [scale * (c.get(k) or 0.0) if c else 0.0 for k in metric_keys]
                ax.bar(x + (i - (len(meths) - 1) / 2) * width, vals, width, label=m)
            ax.set_xticks(x)
            ax.set_xticklabels(metric_keys)
            ax.set_title(f"{title}: {iv}")
            ax.grid(axis="y", alpha=0.3)
        axes[0, 0].set_ylabel(ylabel)
        axes[0, -1].legend(fontsize=7)
        save_figure(fig, out_dir / name, tight=True)
        files.append(name)

    if spec.kind == "relative_pose":
        bars(
            [f"auc{t:g}" for t in spec.auc_thresholds],
            "rotation AUC",
            f"auc_{spec.name}.png",
            "AUC (%)",
            100.0,
        )
    if spec.kind == "time":
        bars(
            ["success_rate"], "success", f"success_rate_{spec.name}.png", "success rate (%)", 100.0
        )
    if spec.kind == "ablation":
        bars(
            ["failure_rate"], "failure", f"failure_rate_{spec.name}.png", "failure rate (%)", 100.0
        )
    return files
