"""What a localization writes for its user.

``result.json`` (pose, verdict, errors when the truth is known, timings), the trace (JSON /
CSV), overlays of render and photo, the match lines, a convergence plot and, on request, the
optimisation as an animation.

Everything is written atomically (``io/atomic.py``); a picture that cannot be drawn is logged and
skipped, never fatal.
"""
from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from ..pose.convert import invert_rigid
from ..pose.se3 import se3_exp
from .problem import Problem
from ..localization.types import LocalizationResult, TraceRecord

logger = logging.getLogger(__name__)

__all__ = [
    "OutputOptions",
    "result_document",
    "success_of",
    "trace_w2c",
    "write_outputs",
    "write_trace",
]

#: The tool's "success" on a known ground truth (the demo's acceptance: 0.5 deg, 1 % of the scene).
SUCCESS_ROT_DEG = 0.5
SUCCESS_TRANS_REL = 0.01


@dataclass
class OutputOptions:
    """Which files to write (the tool's ``output`` group)."""

    overlays: bool = True
    match_lines: bool = True
    convergence_plot: bool = True
    gif: bool = False
    gif_every: int = 10
    mp4: bool = False  # optimisation.mp4 (same frames as the GIF; a GIF when no MP4 encoder works)
    trace_format: str = "both"  # json | csv | both | none

    @classmethod
    def from_dict(cls, d: Optional[Dict[str, Any]]) -> "OutputOptions":
        """From the tool's ``output`` group (other keys are ignored)."""
        d = {k: v for k, v in (d or {}).items() if k in cls.__dataclass_fields__}
        return cls(**d)


def trace_w2c(rec: TraceRecord, init_c2w: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """The pose (w2c) a trace record rendered (its ``w2c``, or the paper's twist ``xi``)."""
    if rec.w2c is not None:
        return np.asarray(rec.w2c, np.float64)
    if rec.xi is not None and init_c2w is not None:
        init_w2c = torch.as_tensor(invert_rigid(np.asarray(init_c2w, np.float64)))
        return (se3_exp(torch.tensor(rec.xi, dtype=torch.float64)) @ init_w2c).numpy()
    return None


def success_of(result: LocalizationResult, scene_scale: Optional[float]) -> Optional[bool]:
    """Whether the final pose is right (`SUCCESS_ROT_DEG`, `SUCCESS_TRANS_REL` x scene scale).

    None without ground truth; without a scene scale only the rotation counts.
    """
    if result.rot_err_deg is None:
        return None
    ok_t = scene_scale is None or result.trans_err < SUCCESS_TRANS_REL * scene_scale
    return bool(result.rot_err_deg < SUCCESS_ROT_DEG and ok_t)


def result_document(problem: Problem, result: LocalizationResult, *, backend: str,
                    config: Dict[str, Any], seconds_total: float) -> Dict[str, Any]:
    """The content of ``result.json``: the one row (docs/CONTRACTS.md) and the run's context."""
    from ..io.cameras_json import CameraEntry

    intr = result.intrinsics or problem.query.intrinsics  # estimated, with refine.focal
    entry = CameraEntry(id=0, img_name=problem.name, width=intr.width, height=intr.height,
                        c2w=result.c2w, fx=float(intr.fx), fy=float(intr.fy))
    doc = result.to_json(include_trace=False, scene_scale=problem.scene_scale)
    doc.update({
        "camera_entry": entry.to_json(),
        "success": success_of(result, problem.scene_scale),
        "seconds_total": seconds_total,
        "backend": backend,
        "info": problem.info,
        "config": config,
    })
    return doc


def write_trace(out: Path, trace: List[TraceRecord], fmt: str) -> List[str]:
    """trace.json and/or trace.csv (the CSV leaves out the pose columns)."""
    from ..io.atomic import write_json_atomic, write_text_atomic

    if fmt not in ("json", "csv", "both", "none"):
        raise ValueError(f"output.trace_format must be json, csv, both or none, got {fmt!r}")
    rows = [r.to_dict() for r in trace]
    written = []
    if fmt in ("json", "both"):
        write_json_atomic(out / "trace.json", rows)
        written.append("trace.json")
    if fmt in ("csv", "both"):
        keys = [k for k in (rows[0].keys() if rows else []) if k not in ("xi", "w2c")]
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r[k]) for k in keys})
        write_text_atomic(out / "trace.csv", buf.getvalue())
        written.append("trace.csv")
    return written


def _render_rgb(problem: Problem, c2w: np.ndarray, backend: str, intr=None) -> torch.Tensor:
    from ..render import render

    intr = intr or problem.query.intrinsics
    w2c = torch.as_tensor(invert_rigid(np.asarray(c2w, np.float64)), dtype=problem.model.dtype)
    with torch.no_grad():
        return render(
            problem.model, intr, w2c, problem.bg.to(problem.model.dtype), backend=backend
        ).color.clamp(0, 1).cpu()  # pictures are drawn on the CPU, beside the CPU query


def write_outputs(
    out_dir: Path,
    problem: Problem,
    result: LocalizationResult,
    *,
    matcher=None,
    options: Optional[OutputOptions] = None,
    backend: str = "auto",
    config: Optional[Dict[str, Any]] = None,
    seconds_total: Optional[float] = None,
) -> Dict[str, Any]:
    """Write every output of one localization into ``out_dir``; returns the result.json document."""
    from .. import pictures as viz
    from ..io.atomic import write_json_atomic

    opt = options or OutputOptions()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = result_document(problem, result, backend=backend, config=config or {},
                          seconds_total=result.seconds if seconds_total is None else seconds_total)
    files = ["result.json"] + write_trace(out_dir, result.trace, opt.trace_format)
    q = problem.query.rgb
    start_c2w = result.init_c2w
    try:
        if opt.overlays or opt.match_lines:
            final_img = _render_rgb(problem, result.c2w, backend, result.intrinsics)
            init_img = None if start_c2w is None else _render_rgb(problem, start_c2w, backend)
            if opt.overlays:
                if init_img is not None:
                    viz.save_overlay(out_dir / "overlay_initial.png", init_img, q)
                    files.append("overlay_initial.png")
                viz.save_overlay(out_dir / "overlay_final.png", final_img, q)
                files.append("overlay_final.png")
            if (
                opt.match_lines
                and matcher is not None
                and getattr(matcher, "name", "none") != "none"
            ):
                first = init_img if init_img is not None else final_img
                m = matcher.match(first, q.to(first.dtype))
                name = "matches_initial.png" if init_img is not None else "matches_final.png"
                viz.save_match_lines(out_dir / name, first, q, m.kpts0, m.kpts1, m.confidence)
                files.append(name)
        if opt.convergence_plot and result.trace:
            title = (
                f"{result.method} ({result.matcher or 'compare only'}): {result.stop_reason} after "
                f"{result.iterations} steps; verdict "
                f"{None if result.verdict is None else result.verdict.status}"
            )
            scale = problem.scene_scale
            viz.plot_convergence(out_dir / "convergence.png", [r.to_dict() for r in result.trace],
                                 result.details.get("switch_iteration"), title,
                                 rot_target_deg=SUCCESS_ROT_DEG,
                                 trans_target=None if scale is None else SUCCESS_TRANS_REL * scale)
            files.append("convergence.png")
        if (opt.gif or opt.mp4) and result.trace:
            frames = []
            every = max(1, int(opt.gif_every))
            for i, rec in enumerate(result.trace):
                if i % every:
                    continue
                w2c = trace_w2c(rec, result.init_c2w)
                if w2c is None:
                    continue
                img = _render_rgb(problem, invert_rigid(w2c), backend)
                frames.append(viz.overlay_panel(img, q))
            if frames and opt.gif:
                viz.save_gif(out_dir / "optimisation.gif", frames)
                files.append("optimisation.gif")
            if frames and opt.mp4:
                files.append(viz.save_video(out_dir / "optimisation.mp4", frames).name)
    except Exception as e:  # noqa: BLE001 - a picture must never fail the run
        logger.warning("could not draw every picture: %s: %s", type(e).__name__, e)
    doc["files"] = files
    write_json_atomic(out_dir / "result.json", doc)
    return doc
