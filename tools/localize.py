#!/usr/bin/env python
r"""Estimate the camera pose of a query image in a trained 3DGS model.

    python tools/localize.py                                   # the built-in demo scene
    python tools/localize.py data=model_folder data.model_path=output/lego \
        data.query.dataset=data/lego data.query.index=0 data.init.rot_deg=30
    python tools/localize.py data=model_folder data.model_path=output/lego \
        data.query.image=photo.png data.intrinsics.fx=1111 data.init=none   # no start pose at all
    python tools/localize.py optimizer=icomma                  # the paper's method, as published
    python tools/localize.py -m optimizer=icomma optimizer.lambda_match=0.2,0.5,0.8

Outputs go to ``output.dir``, else Hydra's output folder (``hydra.run.dir``): result.json (pose,
verdict, errors when the truth is known), trace.json / trace.csv, overlay_initial.png,
overlay_final.png, matches_initial.png, convergence.png (optimisation.gif with
``output.gif=true``). An ``output.dir`` that already holds a result.json is refused. ``main``
returns the final rotation error in degrees, so sweepers can minimise it; without a ground truth,
the mean displacement [px] of the matches that agree with the pose (the verdict's ``mean_px``),
infinity for a failed pose.

Many photos, or a video, against one model (docs/BATCHES.md):

    python tools/localize.py data=model_folder data.model_path=output/fox \
        data.queries=photos/ data.intrinsics.fx=1500 data.init=none workers=2 \
        output.dir=outputs/fox_batch output.export=[cameras_json,colmap]
    python tools/localize.py data=model_folder data.model_path=output/lego \
        data.sequence=walk.mp4 data.intrinsics.fx=277.8 data.init.c2w_file=start.txt
    python tools/localize.py -m hydra/launcher=slurm_cluster data=model_folder ... \
        data.shard=0,1,2,3 data.num_shards=4          # one SLURM array task per shard

write poses.json / poses.csv (every photo journalled at once: rerun with the same output.dir to
resume), contact_sheet.png (batch), trajectory.png and tracking.mp4 (sequence), focal.png
(a focal length estimated from the photos or frames), exports/.

Configuration: conf/localize.yaml (groups data, matcher, optimizer, renderer).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

if __package__:
    from . import _common as common
    from ._paths import CONFIG_DIR
else:  # run as a script from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tools import _common as common
    from tools._paths import CONFIG_DIR

import hydra  # noqa: E402
import numpy as np  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("localize")


def is_many(cfg: DictConfig) -> bool:
    """Whether the config asks for a batch (data.queries) or a sequence (data.sequence)."""
    return bool(cfg.data.get("queries") or cfg.data.get("sequence"))


def run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    """The body of the tool: load, localise, write the outputs into ``output_dir``.

    ``cfg.threads`` applies for the duration of the call (a batch's worker processes:
    ``threads`` each, null meaning 1).

    Returns:
        The content of result.json (a batch or a sequence: of poses.json).
    """
    out = common.output_dir_of(cfg, output_dir)
    if is_many(cfg):
        with common.torch_threads(
            cfg.get("threads") or (1 if (cfg.get("workers") or 1) > 1 else None)
        ):
            return _run_many(cfg, out)
    if cfg.output.get("dir") and (out / "result.json").exists():
        raise ValueError(f"output.dir: {out} already holds the result.json of an earlier run; "
                         "give another folder or remove it (nothing was overwritten)")
    with common.torch_threads(cfg.get("threads")):
        return _run(cfg, out)


def _cache_dir(cfg: DictConfig):
    """The Localizer's candidate cache folder from the ``cache`` group (False: none)."""
    c = common.container(cfg.get("cache")) or {}
    if c.get("enabled") is False:
        return False
    return c.get("dir") or None


def _verdict(cfg: DictConfig):
    """The Localizer's ``verdict`` argument from ``cache.calibration`` (auto | none | a file)."""
    c = common.container(cfg.get("cache")) or {}
    v = c.get("calibration", "auto")
    if v is None or str(v).lower() == "none":
        return None
    return "auto" if str(v).lower() == "auto" else str(v)


def _lod(cfg: DictConfig):
    """The Localizer's ``lod`` argument from the ``lod`` key (auto | off | LodConfig fields)."""
    v = common.container(cfg.get("lod", "auto"))
    return "off" if v is None or v is False else v  # YAML reads a bare off as false


def _step_bar(enabled: bool, total: Optional[int]):
    """(tqdm bar or None, trace-record hook updating it)."""
    if not enabled:
        return None, None
    from tqdm import tqdm

    bar = tqdm(total=total, desc="localize", unit="step", dynamic_ncols=True, leave=False)

    def hook(rec):
        post = {"stage": rec.stage.name.lower()}
        if rec.loss is not None:
            post["loss"] = f"{rec.loss:.3g}"
        if rec.inliers is not None:
            post["inliers"] = rec.inliers
        if rec.rot_err_deg is not None:
            post["rot"] = f"{rec.rot_err_deg:.3f}deg"
        bar.set_postfix(post, refresh=False)
        bar.update(1)

    return bar, hook


def _run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    from icomma_plugin.app.output import OutputOptions, write_outputs
    from icomma_plugin.app.problem import load_problem

    output_dir.mkdir(parents=True, exist_ok=True)
    common.seed_everything(int(cfg.seed))
    backend = common.check_backend(str(cfg.renderer.backend))
    method = common.build_optimizer(cfg.optimizer)
    matcher, _ = common.build_matcher(cfg.get("matcher"))
    problem = load_problem(common.container(cfg.data), backend)
    if backend == "cuda":  # the CUDA kernel renders CUDA tensors; library code never moves data
        problem.model = problem.model.to("cuda")
    localizer = problem.localizer(matcher, method, backend, _cache_dir(cfg), _verdict(cfg),
                                  lod=_lod(cfg))
    opts = OutputOptions.from_dict(common.container(cfg.output))
    bar, hook = _step_bar(bool(cfg.output.progress),
                          getattr(method, "max_iterations", None) if method.needs_start else None)
    t0 = time.perf_counter()
    try:
        result = localizer.localize(problem.query, problem.init_c2w, problem.gt_c2w, hook)
    finally:
        if bar is not None:
            bar.close()
    return write_outputs(output_dir, problem, result, matcher=matcher, options=opts,
                         backend=backend, config=common.container(cfg),
                         seconds_total=time.perf_counter() - t0)


class _Bar:
    """tqdm bar with ETA and the running ok / uncertain / failed counts (made at the start)."""

    def __init__(self, enabled: bool, unit: str):
        self.enabled, self.unit, self.bar = enabled, unit, None

    def __call__(self, ev: Dict[str, Any]) -> None:
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(
                total=ev.get("todo"), desc="localize", unit=self.unit, dynamic_ncols=True
            )
        elif ev.get("row") is None and ev.get("focal_scale", 1.0) != 1.0:
            # a batch localizing its photos again with the focal length they agree on
            self.bar.reset(total=ev.get("todo"))
            self.bar.set_description(f"localize (focal x{ev['focal_scale']:.4f})")
        if ev.get("row") is not None:
            self.bar.update(1)
        self.bar.set_postfix(ev["counts"], refresh=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _worker_setup(cfg: DictConfig, data: Dict[str, Any], out: Path, sequence: bool):
    """(WorkerSetup, model folder, matcher) of a batch or a sequence; UserError on bad input."""
    from icomma_plugin.app.batch import WorkerSetup
    from icomma_plugin.app.output import OutputOptions
    from icomma_plugin.app.problem import open_model_folder, photo_camera

    if data.get("kind") != "model_folder":
        raise common.UserError(
            "data.queries / data.sequence need a model folder: data=model_folder "
            "data.model_path=<3DGS output> (the demo scene folder is one)"
        )
    if data.get("queries") and data.get("sequence"):
        raise common.UserError("set data.queries (a batch) or data.sequence (a video), not both")
    backend = common.check_backend(str(cfg.renderer.backend))
    method = common.build_optimizer(cfg.optimizer)
    matcher, _ = common.build_matcher(cfg.get("matcher"))
    problem = method.needs(matcher)
    if problem:
        raise common.UserError(problem)
    oc = common.container(cfg.output)
    if str(data.get("photos") or "auto").lower() not in ("auto", "none"):
        raise common.UserError(f"data.photos must be auto or none, got {data.get('photos')!r}")
    mf, white = open_model_folder(data)
    setup = WorkerSetup(
        model_path=str(Path(mf.path).resolve()), method=method,
        matcher=common.container(cfg.get("matcher")), out_dir=str(out), iteration=mf.iteration,
        white_background=white, backend=backend, resize=data.get("resize"),
        folders=bool(oc.get("photo_folders")), output=OutputOptions.from_dict(oc),
        thumbs=bool(oc.get("contact_sheet")) and not sequence,  # the sheet is a batch's
        thumb_side=int(oc.get("thumb_side") or 192), config=common.container(cfg),
        seed=int(cfg.seed), cache_dir=_cache_dir(cfg),
        photos=str(data.get("photos") or "auto").lower(), verdict=_verdict(cfg), lod=_lod(cfg),
        distortion=photo_camera(data, mf, white)[1], principal_point=mf.principal_point,
        dataset=(data.get("query") or {}).get("dataset"),
    )
    return setup, mf, matcher


def _run_many(cfg: DictConfig, out: Path) -> Dict[str, Any]:
    """A batch (data.queries) or a sequence (data.sequence) into ``out``; returns poses.json."""
    from icomma_plugin.app.batch import export_rows

    data = common.container(cfg.data)
    common.seed_everything(int(cfg.seed))
    oc = common.container(cfg.output)
    workers = int(cfg.get("workers") or 1)
    shard, num_shards = int(data.get("shard") or 0), int(data.get("num_shards") or 1)
    if not (num_shards >= 1 and 0 <= shard < num_shards):
        raise common.UserError(
            f"data.shard must be in [0, data.num_shards={num_shards}), got {shard}"
        )
    if workers < 1:
        raise common.UserError(f"workers must be a positive integer, got {workers}")
    sequence = bool(data.get("sequence"))
    if sequence and (num_shards > 1 or workers > 1):
        raise common.UserError("a sequence is tracked frame after frame: data.num_shards and "
                               "workers must be 1 with data.sequence")
    if not sequence and workers > 1 and str(cfg.renderer.backend) == "cuda":
        raise common.UserError("workers > 1 shares one GPU between processes: use workers=1 "
                               "with renderer=cuda")
    setup, mf, matcher = _worker_setup(cfg, data, out, sequence)
    bar = _Bar(bool(oc.get("progress")), "frame" if sequence else "photo")
    t0 = time.perf_counter()
    try:
        run = _run_sequence if sequence else _run_batch
        res = run(cfg, data, mf, setup, matcher, out, bar)
    finally:
        bar.close()
    exports = export_rows(out, res["rows"], list(oc.get("export") or []),
                          tuple(oc.get("export_verdicts") or ("ok", "uncertain"))) \
        if oc.get("export") else {}
    doc = json.loads((out / "poses.json").read_text())
    doc["summary"] = {k: v for k, v in res.items() if k != "rows"}
    doc["summary"].update(
        {"exports": exports, "output_dir": str(out), "seconds_total": time.perf_counter() - t0}
    )
    return doc


def _run_batch(cfg, data, mf, setup, matcher, out: Path, bar) -> Dict[str, Any]:
    from icomma_plugin.app.batch import plan_batch, run_batch, run_identity
    from icomma_plugin.app.focal import BatchFocalConfig
    from icomma_plugin.app.lens import LensConfig
    from icomma_plugin.app.ledger import PosesLedger
    from icomma_plugin.app.problem import source_camera_like
    from icomma_plugin.checks import config_from_dict

    workers = int(cfg.get("workers") or 1)
    plan, _ = plan_batch(data, mf)
    first = next((t.intrinsics for t in plan.tasks if t.intrinsics is not None), None)
    like = None if first is None or plan.tasks[0].view is not None else \
        source_camera_like(data, mf, setup.white_background, first)
    group = dict(common.container(cfg.get("batch")) or {})
    lens = config_from_dict(LensConfig, group.pop("lens", None), "batch.lens")
    focal = config_from_dict(BatchFocalConfig, group, "batch")
    ledger = PosesLedger(
        out, {**run_identity("batch", data, setup.model_path), "config": common.container(cfg)},
        len(plan.tasks), int(data.get("shard") or 0), int(data.get("num_shards") or 1),
    )
    summ = run_batch(plan, setup, ledger, workers=workers,
                     threads_per_worker=int(cfg.get("threads") or 1),
                     retry_failed=bool(cfg.output.get("retry_failed")), progress=bar,
                     model_folder=mf if workers == 1 else None,
                     matcher=matcher if workers == 1 else None, focal=focal, lens=lens)
    rows = ledger.all_rows()
    if summ.focal_passes and cfg.output.get("focal_plot"):
        from icomma_plugin.pictures import plot_focal_passes

        try:
            plot_focal_passes(out / "focal.png", summ.focal_passes,
                              f"{len(plan.tasks)} photos of {data.get('queries')}")
        except Exception as e:  # noqa: BLE001 - a picture never fails the run
            log.warning("no focal.png: %s: %s", type(e).__name__, e)
    if setup.thumbs and rows:
        from icomma_plugin.pictures import contact_sheet

        try:
            contact_sheet(out / "contact_sheet.png", rows, out)
        except Exception as e:  # noqa: BLE001 - a picture never fails the run
            log.warning("no contact sheet: %s: %s", type(e).__name__, e)
    return {"kind": "batch", "done_now": summ.done_now, "skipped": summ.skipped,
            "photos_per_minute": summ.photos_per_minute, "seconds": summ.seconds,
            "focal_scale": summ.focal_scale, "focal_adoptions": summ.focal_adoptions,
            "distortion": summ.distortion, "distortion_adoptions": summ.distortion_adoptions,
            "principal_point": summ.principal_point, "centre_evidence": summ.centre_evidence,
            "source_camera": like, "redone": summ.redone, "rows": rows}


def _run_sequence(cfg, data, mf, setup, matcher, out: Path, bar) -> Dict[str, Any]:
    from icomma_plugin.app.batch import BatchWorker, run_identity
    from icomma_plugin.app.inputs import PhotoMismatch, intrinsics_for_photos
    from icomma_plugin.app.ledger import PosesLedger
    from icomma_plugin.app.problem import photo_camera, scene_centre_of, source_camera_like
    from icomma_plugin.app.tracking import (
        FrameSource,
        TrackingConfig,
        first_frame_start,
        sequence_pictures,
        sequence_truths,
        track,
    )
    from icomma_plugin.checks import config_from_dict

    source = FrameSource.open(data["sequence"], int(data.get("every") or 1), data.get("limit"))
    gt_of = sequence_truths(data)
    init_c2w = first_frame_start(data, source, mf.cameras, scene_centre_of(mf.model), gt_of)
    intrinsics_of = intrinsics_for_photos(data.get("intrinsics"), mf.cameras,
                                          photo_camera(data, mf, setup.white_background)[0])
    worker = BatchWorker(setup, mf, matcher)
    ledger = PosesLedger(
        out, {**run_identity("sequence", data, setup.model_path), "config": common.container(cfg)},
        source.count() or 0,
    )
    tc = config_from_dict(TrackingConfig, common.container(cfg.get("tracking")), "tracking")
    summ = track(worker, source, ledger, intrinsics_of, init_c2w, gt_of, tc, progress=bar)
    ledger.total = max(ledger.total, len(ledger.all_rows()))
    ledger.flush()
    rows = ledger.all_rows()
    size = next(((r["intrinsics"]["width"], r["intrinsics"]["height"]) for r in rows
                 if r.get("intrinsics")), None)
    try:  # the given camera at the frames' size (the first row's)
        like = None if size is None else source_camera_like(data, mf, setup.white_background,
                                                            intrinsics_of(size))
    except PhotoMismatch:
        like = None
    files = sequence_pictures(out, worker, source, rows, intrinsics_of,
                              common.container(cfg.output), f"{len(rows)} frames of "
                              f"{data['sequence']}")
    return {"kind": "sequence", "done_now": summ.done_now, "skipped": summ.skipped,
            "frames_per_second": summ.frames_per_second, "seconds": summ.seconds,
            "relocalized": summ.relocalized, "fast_ok": summ.fast_ok, "files": files,
            "source_camera": like,
            "focal_scale": summ.focal_scale, "focal_adoptions": summ.focal_adoptions,
            "distortion": summ.distortion, "distortion_adoptions": summ.distortion_adoptions,
            "principal_point": summ.principal_point, "centre_evidence": summ.centre_evidence,
            "redone": summ.redone, "rows": rows}


def _tracking_line(s: Dict[str, Any], rows: List[Dict[str, Any]]) -> str:
    """How a sequence was tracked: the fast mode, relocalizations, the patch search's renders."""
    line = (f"  tracking     fast mode settled {s.get('fast_ok', 0)} of {s.get('done_now', 0)} "
            f"frames this run, {s.get('relocalized', 0)} relocalized")
    searched = [(r.get("details") or {}).get("patch_search") or {} for r in rows]
    matched = sum(p.get("matched", 0) for p in searched)
    fell_back = sum(p.get("fell_back", 0) for p in searched)
    if matched or fell_back:
        line += (f"; patch search matched {matched} renders, left {fell_back} to the "
                 "descriptors")
    for extra in (_focal_line(s, "frames"), _lens_line(s, "frames")):
        line += "\n" + extra if extra else ""
    return line


def _focal_line(s: Dict[str, Any], what: str) -> str:
    """The focal length a batch or a sequence estimated from its photos ("": the given one)."""
    scale = s.get("focal_scale") or 1.0
    if scale == 1.0:
        return ""
    return (f"  focal length {scale:.4f} x the given one, estimated from the {what} "
            f"(adopted {s.get('focal_adoptions', 0)} times this run; {s.get('redone', 0)} "
            f"{what} localized again with it)")


def _lens_line(s: Dict[str, Any], what: str) -> str:
    """The lens distortion a batch or a sequence estimated from its photos ("": none)."""
    lines = []
    ev = s.get("centre_evidence")
    if s.get("principal_point"):
        cx, cy = s["principal_point"]
        lines.append(f"  lens         principal point ({cx:.2f}, {cy:.2f}) px estimated from the "
                     f"{what} (none was given); give data.intrinsics.cx={cx:.2f} "
                     f"data.intrinsics.cy={cy:.2f} for more {what} of this camera")
    elif ev and ev.get("views_centred"):  # a dataset's views at the image centre: where it is
        lines.append(f"  lens         principal point: the views were taken at the image centre "
                     f"and their refits put it {ev['shift_px']:.2f} px from it, "
                     f"{100 * ev['agree']:.0f} % of {ev['views']} the same way"
                     + (": off; if the model was fitted with the dataset's own, "
                        "data.principal_point=dataset" if ev["off"] else ""))
    elif ev:  # measured and not adopted: say so, the user gave none
        lines.append(f"  lens         principal point: none was given and the image centre is "
                     f"kept (the {what}' refits put it {ev['shift_px']:.2f} px from it, "
                     f"{100 * ev['agree']:.0f} % of {ev['views']} the same way)")
    if s.get("distortion"):
        k = ",".join(f"{v:.5f}" for v in s["distortion"])
        lines.append(f"  lens         distortion [k1,k2,p1,p2] = [{k}] estimated from the {what} "
                     f"and removed (adopted {s.get('distortion_adoptions', 0)} times this run); "
                     f"give data.intrinsics.distortion=[{k}] for more {what} of this camera")
    return "\n".join(lines)


def _source_camera_line(like: Dict[str, Any], what: str = "photos") -> str:
    """The source dataset's camera the photos look taken with (``problem.source_camera_like``)."""
    name = str(like["camera"])
    arg = f"'{name}'" if name.isdigit() and not name.startswith("0") else name  # else an id
    more = " and ".join(w for w, v in (("a principal point", like["principal_point"]),
                                        ("a lens distortion", like["distortion"])) if v)
    return (f"  camera       the model's source dataset has a camera of these {what}' size and "
            f"focal length with {more} they were not given (view {name}): if they were taken "
            f"with it, data.intrinsics.camera={arg} (instead of fx, fy) gives its calibration")


def many_summary(doc: Dict[str, Any]) -> str:
    """The console summary of a batch or a sequence (poses.json's counts, rate and errors)."""
    s = doc.get("summary", {})
    c = doc.get("counts", {})
    rows = doc.get("photos", [])
    errs = [r["rot_err_deg"] for r in rows if r.get("rot_err_deg") is not None]
    rate = (
        f"{s['photos_per_minute']:.2f} photos/min"
        if s.get("photos_per_minute")
        else (
            f"{s['frames_per_second']:.3f} frames/s"
            if s.get("frames_per_second")
            else "nothing new to do"
        )
    )
    lines = [
        "=" * 72,
        f"{s.get('kind')}: {doc.get('done')} of {doc.get('total')} done ({doc.get('status')}); "
        f"this run {s.get('done_now')} in {s.get('seconds', 0):.1f} s ({rate}), "
        f"{s.get('skipped')} skipped (resume)",
        f"  verdicts     ok {c.get('ok', 0)}  uncertain {c.get('uncertain', 0)}  "
        f"failed {c.get('failed', 0)}",
    ]
    if errs:
        lines.append(
            f"  rotation error (truth known, {len(errs)}): median {np.median(errs):.3f} deg, "
            f"max {np.max(errs):.3f} deg"
        )
    if s.get("kind") == "sequence":
        lines.append(_tracking_line(s, rows))
    elif s.get("kind") == "batch":
        lines += [x for x in (_focal_line(s, "photos"), _lens_line(s, "photos")) if x]
    if s.get("source_camera"):
        lines.append(_source_camera_line(
            s["source_camera"], "frames" if s.get("kind") == "sequence" else "photos"))
    for f, paths in (s.get("exports") or {}).items():
        lines.append(f"  export {f}: {', '.join(paths)}")
    lines.append(f"  outputs in {s.get('output_dir')} (poses.json, poses.csv)")
    lines.append("=" * 72)
    return "\n".join(lines)


def summary(res: Dict[str, Any], output_dir: Path) -> str:
    """The console summary of one localisation (result.json) and where its outputs are."""

    def f(v, fmt):
        return "n/a" if v is None else format(v, fmt)

    lines = [
        "=" * 72,
        f"localisation of {res['name']!r}: {res['method']} ({res['matcher'] or 'compare only'}, "
        f"backend {res['backend']})",
        f"  verdict      {str(res['status']).upper()}: {res['reason']}",
        f"  steps        {res['iterations']}  ({res['stop_reason']})   {res['seconds']:.2f} s",
    ]
    if res["rot_err_deg"] is not None:
        rel = res.get("trans_err_rel")
        lines += [
            f"  rotation     {f(res['init_rot_err_deg'], '8.3f')} deg -> "
            f"{res['rot_err_deg']:.4f} deg",
            f"  translation  {f(res['init_trans_err'], '8.4f')}     -> {res['trans_err']:.5f}"
            + (
                ""
                if rel is None
                else f"  ({100 * rel:.3f}% of the scene scale {res['scene_scale']:.3g})"
            ),
            f"  success (< 0.5 deg, < 1% scale): {res['success']}",
        ]
    details = res.get("details") or {}
    focal = details.get("focal_scale")
    if focal is not None:
        why = ("the verdict found the given one off" if details.get("focal_retry") == "kept"
               else "optimizer.refine.focal")
        lines.append(f"  focal length {focal:.4f} x the given one (estimated; {why})")
    c = np.asarray(res["c2w"])
    lines.append("  estimated camera-to-world (OpenCV axes):")
    lines += ["    " + " ".join(f"{x:9.5f}" for x in row) for row in c[:3]]
    lines.append(f"  outputs in {output_dir}")
    lines.append("=" * 72)
    return "\n".join(lines)


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="localize")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: run, print the summary, return the number sweepers minimise.

    That is the final rotation error in degrees (without ground truth: the mean displacement [px]
    of the matches agreeing with the pose, infinity when it failed); for a batch or a sequence,
    the failed share of the photos done.
    """
    hc = HydraConfig.get()
    output_dir = Path(hc.runtime.output_dir)
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    if is_many(cfg):
        if multirun and int(cfg.data.get("num_shards") or 1) > 1 and not cfg.output.get("dir"):
            output_dir = Path(hc.sweep.dir)  # the shards of one batch share one folder
        doc = common.run_or_exit(lambda: run(cfg, output_dir), multirun, log)
        print(many_summary(doc))
        return float(doc["counts"].get("failed", 0)) / max(1, int(doc.get("done") or 0))
    output_dir = common.output_dir_of(cfg, output_dir)
    res = common.run_or_exit(lambda: run(cfg, output_dir), multirun, log)
    print(summary(res, output_dir))
    if res["rot_err_deg"] is not None:
        return float(res["rot_err_deg"])
    mean_px = (res.get("signals") or {}).get("mean_px")
    return float(mean_px) if res["status"] != "failed" and mean_px is not None else float("inf")


if __name__ == "__main__":
    main()
