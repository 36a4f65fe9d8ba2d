"""Run one protocol: sample the initial poses, localise (or run the baseline), record each run.

Every finished run is handed to ``on_record`` at once (the tool writes results.json after each
one, so a partial run keeps what it computed). Runs already present in ``done`` (keyed by
:func:`record_key`) are skipped, which resumes an interrupted run with identical poses (poses
come from per-run seeds, see ``sampling.pose_seed``).
"""
from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, Dict, Iterable, List, Optional

import numpy as np
import torch

from ..localization.icomma import LocalizerConfig
from ..localization.robust import RobustConfig
from ..localization.types import blank_row
from ..pose.convert import invert_rigid
from ..pose.precision import rotation_sigmas
from .baselines import essential_matrix_baseline
from .metrics import time_to_success
from .protocols import NEEDS_START, ProtocolSpec, is_localizer_method, method_config
from .sampling import pose_seed, sample_initial_pose
from .scene import BenchScene

logger = logging.getLogger(__name__)

__all__ = ["record_key", "run_protocol", "threshold_key"]

Progress = Callable[[Dict[str, Any]], Any]


def record_key(protocol: str, interval: str, query_index: int, pose_index: int, method: str) -> str:
    """The key of one run's record (``resume`` reuses records by it)."""
    return f"{protocol}|{interval}|{int(query_index)}|{int(pose_index)}|{method}"


def threshold_key(rot: float, trans: Optional[float]) -> str:
    """The name of a (rotation, translation) threshold pair in summaries, e.g. ``5deg_0.05``."""
    return f"{rot:g}deg_{trans:g}" if trans is not None else f"{rot:g}deg"


def _round(values: Iterable, digits: int = 6) -> List[Optional[float]]:
    out = []
    for v in values:
        if v is None or not math.isfinite(float(v)):
            out.append(None)
        else:
            out.append(float(f"{float(v):.{digits}g}"))
    return out


def _localizer_record(res, scale: float, spec: ProtocolSpec) -> Dict[str, Any]:
    """One LocalizationResult as a benchmark record.

    Its row (the one row schema; translations also in the benchmark's unit: ``*_rel``), its
    curves (errors after k steps, k = 0..n) and the time to each success threshold.
    """
    rot = [r["rot_err_deg"] for r in res.trace] + [res.rot_err_deg]
    trans_w = [r["trans_err"] for r in res.trace] + [res.trans_err]
    trans = [None if t is None else t / scale for t in trans_w]
    cum = [0.0]
    for r in res.trace:
        cum.append(cum[-1] + float(r["seconds"]))
    tts = {threshold_key(a, b): time_to_success(rot, trans, cum, a, b) for a, b in spec.thresholds}
    row = res.row(scale)
    row.update({
        "hypotheses": len(res.details.get("hypotheses") or []),
        "time_to_success": tts,
        "curve_rot_deg": _round(rot),
        "curve_trans": _round(trans),
        "curve_seconds": _round(cum, 5),
    })
    return row


def _error_record(exc: BaseException) -> Dict[str, Any]:
    """A run that raised: kept, counted as a failure, with what went wrong."""
    return blank_row(status=None, error={"type": type(exc).__name__, "message": str(exc)[:2000]})


def run_protocol(
    scene: BenchScene,
    spec: ProtocolSpec,
    base_config: LocalizerConfig,
    matcher=None,
    *,
    robust_config: Optional[RobustConfig] = None,
    backend: str = "auto",
    on_record: Optional[Callable[[Dict[str, Any]], Any]] = None,
    done: Optional[Dict[str, Dict[str, Any]]] = None,
    progress: Optional[Progress] = None,
    store_curves: bool = True,
) -> List[Dict[str, Any]]:
    """Run every (interval, query, pose, method) of ``spec`` on ``scene``.

    Args:
        scene: model + queries (its first ``spec.num_queries`` queries are used), candidate views.
        spec: the protocol.
        base_config: the paper's LocalizerConfig (icomma, compare_only, match_only derive theirs).
        matcher: the matcher (needed by every method but compare_only).
        robust_config: the default method's config (``robust``); None = its defaults.
        backend: renderer backend ("auto" | "cpu" | "cuda" | "reference").
        on_record: called with each new record (dict) as soon as it is finished.
        done: records already computed, keyed by :func:`record_key`; reused, not recomputed.
        progress: called with events ``{"event": "run_start"|"iteration"|"run_end", ...}``.
        store_curves: keep per-iteration curves in the records (needed by ``curves``/``time``).

    A run that raises is recorded with its exception (type, message), counts as a failure, and
    the protocol goes on.

    Returns:
        All records of the protocol (reused and new), in run order.
    """
    done = dict(done or {})
    needs_matcher = [m for m in spec.methods if m != "compare_only"]
    if needs_matcher and matcher is None:
        raise ValueError(
            f"methods {needs_matcher} need a matcher; got matcher=None (choose e.g. matcher=xfeat)"
        )
    queries = scene.queries[: spec.num_queries]
    scale = float(scene.translation_scale)
    configs = {m: method_config(m, base_config, spec.max_iterations, robust_config)
               for m in spec.methods if is_localizer_method(m)}
    pivot = spec.pivot
    if pivot == "scene_center":
        if scene.scene_centre is None:
            raise ValueError(
                "benchmark_protocol.pivot=scene_center needs the scene's centre (a model folder "
                "scene with cameras)"
            )
        pivot = np.asarray(scene.scene_centre, np.float64)
    records: List[Dict[str, Any]] = []
    def plan(iv):
        # A run without a start pose has nothing random to vary: each takes another view instead.
        if iv.no_start:
            qs = scene.no_start_queries[: spec.num_queries * spec.poses_per_query] or queries
            return qs, 1
        return queries, spec.poses_per_query

    total = sum(
        0
        if (iv.no_start and m in NEEDS_START)
        else len(plan(iv)[0]) * min(plan(iv)[1], spec.poses_for(m))
        for iv in spec.intervals
        for m in spec.methods
    )
    count = 0
    for ii, iv in enumerate(spec.intervals):
        iv_queries, iv_poses = plan(iv)
        for q in iv_queries:
            for k in range(iv_poses):
                seed = pose_seed(spec.seed, ii, q.index, k)
                init = None
                if not iv.no_start:
                    init = sample_initial_pose(
                        q.gt_c2w,
                        iv.rot_deg,
                        iv.trans,
                        seed,
                        translation_scale=scale,
                        translation_mode=spec.translation_mode,
                        pivot=pivot,
                    )
                for method in spec.methods:
                    if k >= spec.poses_for(method) or (iv.no_start and method in NEEDS_START):
                        continue
                    key = record_key(spec.name, iv.label, q.index, k, method)
                    count += 1
                    if key in done:
                        records.append(done[key])
                        if progress:
                            progress(
                                {
                                    "event": "run_end",
                                    "key": key,
                                    "count": count,
                                    "total": total,
                                    "reused": True,
                                    "record": done[key],
                                }
                            )
                        continue
                    if progress:
                        progress(
                            {
                                "event": "run_start",
                                "key": key,
                                "count": count,
                                "total": total,
                                "method": method,
                                "interval": iv.label,
                                "query": q.name,
                                "pose": k,
                            }
                        )
                    rec: Dict[str, Any] = {
                        "key": key,
                        "protocol": spec.name,
                        "interval": iv.label,
                        "interval_index": ii,
                        "name": q.name,
                        "query_index": q.index,
                        "pose_index": k,
                        "method": method,
                        "seed": list(seed),
                        "init": None if init is None else init.to_json(),
                    }
                    if q.record is not None:
                        rec["record_rot_std_deg"] = q.record["rot_std_deg"]
                    if init is not None:
                        init_trans_w = float(np.linalg.norm(init.c2w[:3, 3] - q.gt_c2w[:3, 3]))
                        rec.update({"init_rot_err_deg": init.rot_deg,
                                    "init_trans_err": init_trans_w,
                                    "init_trans_err_rel": init_trans_w / scale})
                    t0 = time.perf_counter()
                    try:
                        rec.update(
                            _run_one(
                                scene,
                                q,
                                init,
                                method,
                                configs,
                                matcher,
                                backend,
                                spec,
                                scale,
                                seed,
                                key,
                                progress,
                            )
                        )
                    except Exception as exc:  # noqa: BLE001 - one bad run must not end the benchmark
                        logger.warning(
                            "run %s raised %s: %s (recorded as a failure)",
                            key,
                            type(exc).__name__,
                            exc,
                        )
                        rec.update(_error_record(exc))
                    if q.record is not None and rec.get("c2w") is not None:
                        rec["record_sigmas"] = _record_sigmas(rec["c2w"], q)
                    rec["method"] = method  # the protocol's variant (a row says the algorithm)
                    rec["wall_seconds"] = time.perf_counter() - t0
                    if not store_curves:
                        for c in ("curve_rot_deg", "curve_trans", "curve_seconds"):
                            rec.pop(c, None)
                    records.append(rec)
                    done[key] = rec
                    if on_record:
                        on_record(rec)
                    if progress:
                        progress({"event": "run_end", "key": key, "count": count, "total": total,
                                  "reused": False, "record": rec})
    return records


def _record_sigmas(c2w, q) -> Optional[float]:
    """``rotation_sigmas`` of a run's pose against its query's record (None: no covariance)."""
    try:
        return rotation_sigmas(invert_rigid(np.asarray(c2w, np.float64)), invert_rigid(q.gt_c2w),
                               q.record["rot_cov"])
    except ValueError:
        return None


def _run_one(
    scene, q, init, method, configs, matcher, backend, spec, scale, seed, key, progress
):
    """One run: a localization (or the essential-matrix baseline); returns its record fields."""
    if not is_localizer_method(method):
        out = essential_matrix_baseline(
            scene.model,
            q.query.rgb,
            q.query.intrinsics,
            init.c2w,
            q.gt_c2w,
            matcher,
            bg=scene.bg,
            backend=backend,
            thresh_px=spec.essential_thresh_px,
            seed=int(seed[-1]),
        )
        out = dict(out)
        out["rot_err_deg"] = out["rel_rot_err_deg"]
        out["trans_err_rel"] = None
        return out

    def hook(r, _key=key):
        if progress:
            progress({"event": "iteration", "key": _key, "record": r})

    torch.manual_seed(int(np.random.SeedSequence(list(seed)).generate_state(1)[0]))
    localizer = scene.localizer(matcher if method != "compare_only" else None, configs[method],
                                backend)
    res = localizer.localize(q.query.fresh(), None if init is None else init.c2w, q.gt_c2w, hook)
    return _localizer_record(res, scale, spec)
