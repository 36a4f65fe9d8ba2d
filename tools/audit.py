#!/usr/bin/env python
r"""Audit a trained 3DGS model: localize its own training photos, compare with their recorded poses.

    python tools/audit.py model_path=output/bird                   # every training photo
    python tools/audit.py model_path=output/bird sample=40 starts=5 dataset=data/bird
    python tools/audit.py model_path=... output.dir=outputs/audit_bird starts=5  # resume, add

Each photo is localized from ``starts`` perturbed starts around its recorded pose and from none,
with the recorded pose as the truth (its own camera is left out of its candidate views). Cameras
whose photo disagrees with the record are flagged: ``registration`` (confident poses agree with
each other, not with the record), ``no_trustworthy_pose`` (no start gave an ``ok`` pose: a region
the model renders badly), ``inconsistent`` (confident poses disagree). From the right poses of the
unflagged cameras the verdict's thresholds are calibrated for this model and stored where the
Localizer and the benchmark find them (docs/AUDIT.md).

Outputs (Hydra's folder, or ``output.dir``): audit.json (settings, one row per run, one summary
per camera with its flag, totals, the calibration), audit.jsonl (the journal a rerun resumes
from), contact_sheet.png, trajectory.png, thumbs/. ``main`` returns the number of flagged cameras.

Configuration: conf/audit.yaml (groups matcher, optimizer, renderer).
"""
from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any, Dict

if __package__:
    from . import _common as common
    from ._paths import CONFIG_DIR
else:  # run as a script from a checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tools import _common as common
    from tools._paths import CONFIG_DIR

import hydra  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

log = logging.getLogger("audit")


def _plan_and_rule(cfg: DictConfig):
    """(AuditPlan, FlagRule) of the config; UserError naming the key on bad values."""
    from icomma_plugin.app.audit import AuditPlan, FlagRule

    rot = common.container(cfg.rot_deg)
    try:
        plan = AuditPlan(starts=cfg.starts, no_start=cfg.no_start,
                         rot_deg=tuple(rot) if isinstance(rot, list) else rot,
                         trans=float(cfg.trans), pivot=str(cfg.pivot), seed=cfg.seed,
                         sample=cfg.get("sample"), control=cfg.get("control", True),
                         focal_step=float(cfg.focal.step) if cfg.focal.enabled else None)
        f = cfg.flag
        rule = FlagRule(rot_deg=float(f.rot_deg), trans=float(f.trans), min_ok=f.min_ok,
                        focal_min_drop=float(cfg.focal.min_drop))
    except ValueError as e:
        raise common.UserError(str(e)) from None
    if plan.focal_step is not None and (cfg.get("optimizer") or {}).get("refine", {}).get("focal"):
        raise common.UserError("focal.enabled compares the loss at given focal lengths: it needs "
                               "optimizer.refine.focal=false (which estimates the focal length)")
    return plan, rule


def _model_path(cfg: DictConfig) -> str:
    """``model_path``, checked: UserError when it is missing or not a folder."""
    from omegaconf import OmegaConf

    if OmegaConf.is_missing(cfg, "model_path") or not cfg.model_path:
        raise common.UserError("model_path is required: the 3DGS output folder to audit "
                               "(cfg_args, cameras.json, point_cloud/)")
    if not Path(str(cfg.model_path)).expanduser().is_dir():
        raise common.UserError(f"model_path: model folder not found: {cfg.model_path}")
    return str(cfg.model_path)


def _cache_dir(cfg: DictConfig):
    """The Localizer's candidate cache folder (``cache`` group; False: none)."""
    c = common.container(cfg.get("cache")) or {}
    if c.get("enabled") is False:
        return False
    return c.get("dir") or None


def _photos_to_audit(cfg: DictConfig, mf, white: bool):
    """(the dataset folder, its train views) of ``dataset`` or cfg_args source_path."""
    from icomma_plugin.io.datasets import read_dataset

    root = cfg.get("dataset") or mf.cfg.get("source_path")
    if not root or not Path(str(root)).expanduser().is_dir():
        raise common.UserError(
            f"dataset: the photos the model was fitted from are needed (cfg_args source_path "
            f"{mf.cfg.get('source_path')!r} is not a folder here): set dataset=<folder>")
    root = Path(str(root)).expanduser()
    try:
        scene = read_dataset(root, white_background=white, principal_point=mf.principal_point)
    except ValueError as e:
        raise common.UserError(f"dataset: {e}") from None
    if not scene.train:
        raise common.UserError(f"dataset: {root} has no train views (the photos the model was "
                               "fitted from)")
    return root, scene.train


def _localizer(cfg: DictConfig, mf, white: bool, views, backend: str):
    """The Localizer the audit runs: the method's own (global) verdict, never a calibration.

    The photos are localized with their recorded intrinsics as given (``focal_retry`` off): the
    audit judges the records, and its focal check compares losses at focal lengths it sets.
    """
    import dataclasses

    from icomma_plugin.localization.localizer import Localizer

    method = common.build_optimizer(cfg.optimizer)
    if getattr(method, "focal_retry", False):
        method = dataclasses.replace(method, focal_retry=False)
    matcher, _ = common.build_matcher(cfg.get("matcher"))
    problem = method.needs(matcher)
    if problem:
        raise common.UserError(problem)
    if method.needs_start and cfg.no_start:
        raise common.UserError(f"optimizer={method.name} needs a start pose: set no_start=false "
                               "(and starts >= 1), or use optimizer=robust")
    mode = str(cfg.get("photos") or "none").lower()
    if mode not in ("auto", "none"):
        raise common.UserError(f"photos must be auto or none, got {cfg.get('photos')!r}")
    return Localizer.from_model_folder(
        mf, matcher, method, white_background=white, backend=backend,
        cache_dir=_cache_dir(cfg), photos=list(views) if mode == "auto" else None,
        verdict=method.verdict)


def _digest(mapping) -> str:
    """A short hash of a config mapping (what a resumed audit must share with the first run)."""
    import hashlib
    import json

    text = json.dumps(mapping, sort_keys=True, default=str)
    return hashlib.blake2b(text.encode(), digest_size=8).hexdigest()


def _thumbnail_writer(out: Path, localizer, side: int, backend: str):
    """on_camera hook: ``thumbs/<camera>.png``, the photo blended with its recorded-pose render."""
    from icomma_plugin.app.batch.records import safe_name
    from icomma_plugin.pictures import save_thumbnail

    def write(view, query, summary) -> None:
        p = out / "thumbs" / f"{safe_name(summary['camera'])}.png"
        if not p.is_file():
            save_thumbnail(p, localizer.model, query, view.c2w, localizer.background, side,
                           backend)

    return write


def run(cfg: DictConfig, output_dir: Path) -> Dict[str, Any]:
    """The body of the tool: audit, pictures, calibration; returns audit.json's content."""
    with common.torch_threads(cfg.get("threads")):
        return _run(cfg, common.output_dir_of(cfg, output_dir))


def _run(cfg: DictConfig, out: Path) -> Dict[str, Any]:
    from icomma_plugin.app.audit import audit_pictures, run_audit, select_views
    from icomma_plugin.app.problem import open_model_folder, scene_centre_of
    from icomma_plugin.io.atomic import write_json_atomic
    from icomma_plugin.io.datasets.colmap_tracks import record_precision
    from icomma_plugin.localization.calibration import model_key
    from icomma_plugin.pose.convert import cameras_extent

    common.seed_everything(int(cfg.seed))
    backend = common.check_backend(str(cfg.renderer.backend))
    plan, rule = _plan_and_rule(cfg)
    calibration = _calibration_settings(cfg)
    mf, white = open_model_folder({"model_path": _model_path(cfg), "iteration": cfg.iteration,
                                   "white_background": cfg.white_background,
                                   "principal_point": cfg.get("principal_point")})
    root, train = _photos_to_audit(cfg, mf, white)
    records = record_precision(root)  # {} unless the capture has COLMAP tracks
    views = select_views(train, plan.sample)
    localizer = _localizer(cfg, mf, white, train, backend)
    scale = cameras_extent([e.c2w for e in mf.cameras] or [v.c2w for v in train])
    fixed = cfg.get("image_scale")

    def image_scale(view) -> float:
        return float(fixed) if fixed else mf.training_scale(view.intrinsics.width)

    oc = common.container(cfg.output)
    identity = {"model_path": str(Path(mf.path).resolve()), "model": model_key(mf.model),
                "dataset": str(root.resolve()), "method": _digest(localizer.method.to_dict()),
                "matcher": _digest(common.container(cfg.get("matcher"))), "photos": cfg.photos}
    hook = _thumbnail_writer(out, localizer, int(oc.get("thumb_side") or 160), backend) \
        if oc.get("contact_sheet") else None
    doc = run_audit(localizer, views, plan, rule, out, scene_scale=scale,
                    scene_centre=scene_centre_of(mf.model), image_scale=image_scale,
                    settings={"config": common.container(cfg), **identity,
                              "model_principal_point": mf.principal_point,
                              "train_photos": len(train)},
                    identity=identity, on_camera=hook, progress=bool(oc.get("progress")),
                    records=records)
    doc["calibration"] = _calibrate(cfg, doc, mf.model, out, calibration)
    doc["files"] = audit_pictures(out, doc, [e.c2w for e in mf.cameras] or None,
                                  sheet=bool(oc.get("contact_sheet")),
                                  trajectory=bool(oc.get("trajectory_plot")))
    write_json_atomic(out / "audit.json", doc)
    doc["output_dir"] = str(out)
    return doc


def _calibration_settings(cfg: DictConfig):
    """(CalibrationConfig or None when disabled, the file to store it at or None), checked."""
    from icomma_plugin.localization.calibration import CalibrationConfig

    c = dict(common.container(cfg.calibration) or {})
    enabled, path = c.pop("enabled", True), c.pop("path", None)
    try:
        ccfg = CalibrationConfig.from_dict(c)
    except ValueError as e:
        raise common.UserError(str(e)) from None
    return (ccfg if enabled else None), path


def _calibrate(cfg: DictConfig, doc: Dict[str, Any], model, out: Path, settings
               ) -> Dict[str, Any]:
    """Calibrate the verdict from the audit and store it; what happened, for audit.json."""
    from icomma_plugin.localization.calibration import CalibrationError, calibrate, save_calibration

    ccfg, path = settings
    if ccfg is None:
        return {"stored": None, "reason": "calibration.enabled is false"}
    method = common.build_optimizer(cfg.optimizer)
    try:
        cal = calibrate(doc["rows"], method.verdict, ccfg, doc["summary"]["flagged"],
                        source={"audit": str((out / "audit.json").resolve())})
    except CalibrationError as e:
        log.warning("no calibration: %s", e)
        return {"stored": None, "reason": str(e)}
    cache = _cache_dir(cfg)
    stored = save_calibration(cal, model, path, cache if cache else None)
    return {"stored": str(stored), "verdict": cal.to_json()["verdict"], "changed": cal.changed(),
            "measured": cal.measured, "counts": cal.counts}


def summary(doc: Dict[str, Any]) -> str:
    """The console summary: totals, the flagged cameras and why, the calibration."""
    s, cal = doc["summary"], doc.get("calibration") or {}
    lines = ["=" * 72,
             f"audit of {s['cameras']} photos, {s['runs']} runs: verdicts "
             + "  ".join(f"{k} {v}" for k, v in s["verdicts"].items()),
             f"  flagged {len(s['flagged'])}: "
             + ", ".join(f"{k} {v}" for k, v in s["flags"].items() if v)]
    for c in doc["cameras"]:
        if c.get("flag"):
            lines.append(f"    {c['camera']}: {c['flag']}: {c['reason']}")
    if s.get("median_rot_err_deg_unflagged") is not None:
        scatter = s.get("median_ok_scatter_deg")
        lines.append(f"  unflagged cameras: median rotation off the record "
                     f"{s['median_rot_err_deg_unflagged']:.3f} deg; ok poses off the record "
                     f"{s['ok_off_record_unflagged']}" + ("" if scatter is None else
                     f"; a photo's ok poses within {scatter:.3f} deg of each other (median)"))
    control = s.get("median_control_rot_err_deg")
    if control is not None:
        lines.append(f"  control: the model's renders at the records come back to "
                     f"{control:.3f} deg (median): "
                     + _control_reading(s.get("median_rot_err_deg_unflagged"), control))
    record = s.get("median_record_rot_std_deg")
    if record is not None:
        how = ("the reconstruction's points free" if s.get("record_points_free")
               else "the points held fixed: a lower bound")
        lines.append(f"  records: the capture's own tracks fix a recorded rotation to {record:.3f} "
                     f"deg (median rms, first order, {how}); {s['unflagged_within_record']} of "
                     f"{s['unflagged_with_record']} unflagged photos lie within their record's "
                     "uncertainty (99 %)")
    if s.get("focal_checked") is not None:
        lines.append(f"  focal lengths: {len(s['focal_disagreeing'])} of {s['focal_checked']} "
                     "photos explained better at another focal length than their record's"
                     + "".join(f"\n    {c['camera']}: {_focal_reading(c['focal'])}"
                               for c in doc["cameras"] if (c.get("focal") or {}).get("disagrees")))
    from icomma_plugin.app.lens import LensConfig

    rule = LensConfig()  # what a batch adopts from
    lens = s.get("lens")
    if lens:
        k = ", ".join(f"{v:.4f}" for v in lens["coefficients"])
        lines.append(
            f"  lens: the photos' refits agree on a distortion their dataset does not remove "
            f"(k1, k2, p1, p2 = {k}; {lens['shift_px']:.2f} px, {100 * lens['agree']:.0f} % of "
            f"{lens['views']} runs): check the capture's camera model" if lens["distorted"] else
            f"  lens: the photos' refits do not agree on a distortion left in them (their medians "
            f"{lens['shift_px']:.2f} px, {100 * lens['agree']:.0f} % of {lens['views']} runs "
            f"pointing that way; a batch adopts from {rule.min_shift_px:g} px and "
            f"{100 * rule.agree:.0f} %)")
    centre = s.get("principal_point")
    if centre:
        move = (f"{centre['shift_px']:.2f} px from the image centre, {100 * centre['agree']:.0f} % "
                f"of {centre['views']} runs that way")
        fitted_centred = (doc.get("settings") or {}).get("model_principal_point") == "centre"
        why = ("the model was fitted with the image centre (upstream 3DGS's camera; "
               "principal_point=dataset if its trainer took the dataset's)" if fitted_centred
               else "the dataset gives none")
        lines.append(
            f"  principal point: {why}, and the photos' refits put it {move}: check the "
            "capture's camera model" + (" or the model's principal_point" if fitted_centred
                                        else "") if centre["off"] else
            f"  principal point: {why}; the photos' refits put it {move} (a batch adopts from "
            f"{rule.min_centre_move:g} focal lengths, {rule.min_shift_px:g} px and "
            f"{100 * rule.agree:.0f} %)")
    if cal.get("stored"):
        moved = ", ".join(f"{k} {a:g} -> {b:g}" for k, (a, b) in cal["changed"].items())
        lines.append(f"  calibration ({cal['counts']['used']} right ok poses): "
                     f"{moved or 'the global thresholds hold'}; stored in {cal['stored']}")
    else:
        lines.append(f"  no calibration: {cal.get('reason')}")
    lines += [f"  outputs in {doc.get('output_dir')}", "=" * 72]
    return "\n".join(lines)


def _focal_reading(focal: Dict[str, Any]) -> str:
    """One camera's focal check in words."""
    best = focal.get("best_scale")
    where = f"best at x{best:.3f} of its recorded focal length" if best is not None else \
        "no minimum within the scales tried"
    rots = ", ".join("-" if r is None else f"{r:.2f}" for r in focal["rot_err_deg"])
    return (f"{where}; the final loss {100 * focal['loss_drop']:.0f} % lower at the better of "
            f"x{focal['scales'][0]:.2f} / x{focal['scales'][2]:.2f} (rotation off the record at "
            f"the three scales: {rots} deg)")


#: Photos this close to their records (median, deg) agree with them, whatever the control says.
AGREE_DEG = 0.05


def _control_reading(photos_deg, control_deg) -> str:
    """What the control runs say about the photos' distance to their records."""
    if photos_deg is None:
        return "no unflagged photo to compare with"
    if photos_deg < AGREE_DEG:
        return f"the photos agree with their records ({photos_deg:.3f} deg)"
    if photos_deg > 2.0 * control_deg + 0.02:
        return (f"the photos' {photos_deg:.3f} deg off their records is the photos' disagreement "
                "with their records on this model (the records, or the model fitted on them), "
                "not the method's precision")
    return (f"the photos' {photos_deg:.3f} deg off their records is of the method's own "
            "precision on this model")


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="audit")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: audit, print the summary, return the number of flagged cameras."""
    hc = HydraConfig.get()
    multirun = str(hc.mode) == "RunMode.MULTIRUN"
    doc = common.run_or_exit(lambda: run(cfg, Path(hc.runtime.output_dir)), multirun, log)
    print(summary(doc))
    return float(len(doc["summary"]["flagged"]))


if __name__ == "__main__":
    main()
