"""The model audit (icomma-audit: tools/audit.py, icomma_plugin/app/audit.py).

End to end: a small capture whose recorded poses are corrupted on purpose for two cameras (the
demo scene's model, its 12 ring photos rendered at the true poses; ring_004 and ring_009 recorded
8 deg / 0.3 units off) is audited; exactly the corrupted cameras are flagged, as registration
errors at 8 deg. The flag rule is tested on synthetic rows, case by case.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from icomma_plugin.app.audit import (
    AuditJournal,
    AuditPlan,
    FlagRule,
    attach_record,
    audit_starts,
    audit_summary,
    evenly_spread,
    focal_agreement,
    focal_label,
    select_views,
    summarize_camera,
)
from icomma_plugin.localization.types import ROW_FIELDS
from icomma_plugin.pose.convert import (
    look_at_c2w,
    perturb_pose,
    rotation_error_deg,
    translation_error,
)
from tests.helpers.demo import demo_model, photo
from tests.helpers.paths import REPO
from tests.helpers.tools import compose

SIZE = 96
CORRUPTED = {"ring_004": (8.0, 0.3), "ring_009": (8.0, 0.3)}  # (deg, world units) off the truth

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def audit_tool():
    """tools/audit.py as a module."""
    name = "icomma_tools_audit"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "tools" / "audit.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


# ---------------------------------------------------------------------------------- the flag rule

SCALE = 4.4
RECORDED = look_at_c2w(np.array([4.0, 0.0, 2.2]), np.array([0.0, 0.0, 0.4]))


def _run(c2w, status="ok", start="none", recorded=RECORDED):
    """A synthetic audit row: a localized pose, its verdict, its errors against the record."""
    return {"camera": "cam", "name": "cam", "start": start, "status": status,
            "c2w": np.asarray(c2w).tolist(), "gt_c2w": np.asarray(recorded).tolist(),
            "rot_err_deg": float(rotation_error_deg(c2w, recorded)),
            "trans_err_rel": float(translation_error(c2w, recorded)) / SCALE,
            "inliers": 100, "signals": {"inliers": 100}}


def _off(deg, trans=0.0, seed=0, c2w=RECORDED):
    return perturb_pose(c2w, deg, trans, np.random.default_rng(seed), pivot="camera")


TRUE = _off(8.0, 0.3)  # where the photo really is when its record is 8 deg / 0.3 units off


def _flag(rows, rule=FlagRule()):
    return summarize_camera("cam", rows, rule, SCALE)


def test_poses_agreeing_with_the_record_are_not_flagged():
    s = _flag([_run(_off(0.1, 0.001, k), start=f"start{k}") for k in range(3)])
    assert s["flag"] is None and s["reason"] is None
    assert s["verdicts"] == {"ok": 3, "uncertain": 0, "failed": 0} and s["ok_agreeing"] == 3
    assert s["rot_err_deg"] == pytest.approx(0.1) and s["consensus"]["size"] == 3
    assert 0.0 < s["ok_scatter_deg"] <= 0.2 and s["ok_scatter_radii"] < 0.001


def test_confident_poses_that_agree_with_each_other_not_the_record_are_a_registration_error():
    rows = [_run(_off(0.05, 0.0, k, TRUE), start=f"start{k}") for k in range(3)]
    rows.append(_run(RECORDED, status="uncertain", start="none"))
    s = _flag(rows)
    assert s["flag"] == "registration"
    assert "photo cam is at 8.0" in s["reason"] and "0.068 radii" in s["reason"]
    assert s["consensus"]["size"] == 3 and s["ok_agreeing"] == 0
    # a lone ok pose at the record does not outvote three elsewhere
    s = _flag(rows[:3] + [_run(RECORDED, start="none")])
    assert s["flag"] == "registration" and s["consensus"]["size"] == 3
    # one run only (no start, no perturbed starts): one ok pose is enough
    assert _flag([_run(TRUE)])["flag"] == "registration"
    # a smaller offset than the rule's bounds is agreement
    assert _flag([_run(_off(3.0, 0.1))] * 2)["flag"] is None
    assert _flag([_run(_off(3.0, 0.1))] * 2, FlagRule(rot_deg=2.0))["flag"] == "registration"


def test_no_ok_pose_from_any_start_is_a_region_the_model_renders_badly():
    doubted = dict(_run(RECORDED, "uncertain"), reason="check this pose: mean displacement 0.82 px")
    s = _flag([doubted, _run(_off(30), "failed", "start0")])
    assert s["flag"] == "no_trustworthy_pose"
    assert "no trustworthy pose from any of 2 starts (1 uncertain, 1 failed; its poses are " \
        "15.00 deg / 0.000 radii from the record (median); best run: check this pose: mean " \
        "displacement 0.82 px)" in s["reason"]
    assert s["status"] == "uncertain"  # the summary shows the run with the most inliers


def test_confident_poses_that_disagree_are_inconsistent_unless_all_on_the_record():
    s = _flag([_run(RECORDED), _run(_off(20.0, 0.0, 1), start="start0")])
    assert s["flag"] == "inconsistent" and "do not agree with each other" in s["reason"]
    # a lone ok pose on the record (the others doubted) supports it
    lone = [_run(RECORDED), _run(_off(20.0), "uncertain", "start0"),
            _run(_off(25.0), "failed", "start1")]
    assert _flag(lone)["flag"] is None
    # ... but a lone ok pose off the record is not confirmed by another start
    lone[0] = _run(TRUE)
    assert _flag(lone)["flag"] == "inconsistent"


def test_a_records_own_precision_says_whether_a_photo_is_within_it():
    """0.1 deg off a record fixed to 0.05 deg a direction is within it; 0.3 deg is not."""
    near = _flag([_run(_off(0.1, 0.0, k), start=f"start{k}") for k in range(2)])
    far = dict(_flag([_run(_off(0.3, 0.0, k), start=f"start{k}") for k in range(2)]),
               camera="far")
    bare = dict(_flag([_run(_off(0.3))]), camera="bare")
    sd = np.radians(0.05)
    record = {"rot_std_deg": 0.0866, "centre_std_rel": 0.003, "rms_px": 1.0, "points": 300,
              "focal_free": True, "rot_cov": (np.eye(3) * sd * sd).tolist()}
    attach_record(near, record)
    attach_record(far, record)
    attach_record(bare, None)
    assert near["record"] == record and near["record_sigmas"] == pytest.approx(
        near["rot_err_deg"] / 0.05, rel=1e-3)  # isotropic: the angle in units of 0.05 deg
    assert near["within_record"] is True
    assert far["record_sigmas"] > 3.368 and far["within_record"] is False
    assert bare["record"] is None and bare["within_record"] is None
    rows = [dict(r, camera=c["camera"]) for c in (near, far, bare) for r in [{"status": "ok"}]]
    s = audit_summary([near, far, bare], rows, FlagRule())
    assert s["median_record_rot_std_deg"] == pytest.approx(0.0866)
    assert (s["unflagged_within_record"], s["unflagged_with_record"]) == (1, 2)
    doc = {"summary": s, "cameras": [near, far, bare], "calibration": {}}
    assert "records: the capture's own tracks fix a recorded rotation to 0.087 deg (median " \
        "rms, first order, the points held fixed: a lower bound); 1 of 2 unflagged photos lie " \
        "within their record's uncertainty" in audit_tool().summary(doc)
    near["record"]["points_free"] = True
    s = audit_summary([near, far, bare], rows, FlagRule())
    assert "the reconstruction's points free" in audit_tool().summary(dict(doc, summary=s))
    # without tracks nothing is said about the records
    plain = audit_summary([bare], rows[2:], FlagRule())
    assert plain["median_record_rot_std_deg"] is None
    assert "records:" not in audit_tool().summary(dict(doc, summary=plain, cameras=[bare]))


def _focal_row(loss, rot=0.1, status="ok"):
    return {"status": status, "rot_err_deg": rot, "inliers": 50,
            "details": {"refine_loss": [2 * loss, loss] if loss is not None else None}}


def test_the_focal_check_reads_the_loss_at_three_focal_lengths():
    """The parabola's minimum is the preferred scale; a clear drop means the record disagrees."""
    scales = (0.97, 1.0, 1.03)
    # a parabola with its minimum at 1.015: losses (1.0 - 0.03) .. (1.0 + 0.03)
    lo, mid, hi = (100.0 * (s - 1.015) ** 2 + 1.0 for s in scales)
    f = focal_agreement([_focal_row(lo), _focal_row(mid), _focal_row(hi)], scales, 0.05)
    assert f["best_scale"] == pytest.approx(1.015)
    assert f["loss_drop"] == 0.0 and f["disagrees"] is False  # 1.03 is no better than 1.0
    assert f["scales"] == list(scales) and f["losses"] == [lo, mid, hi]
    # minimum beyond the scales tried: clamped to two steps, and a clear drop
    f = focal_agreement([_focal_row(4.0), _focal_row(2.0), _focal_row(1.0)], scales, 0.05)
    assert f["best_scale"] == pytest.approx(1.045) and f["loss_drop"] == pytest.approx(0.5)
    f = focal_agreement([_focal_row(3.0), _focal_row(2.0), _focal_row(1.05)], scales, 0.05)
    assert f["best_scale"] == pytest.approx(1.06)  # nearly straight: clamped to two steps
    assert f["disagrees"] is True
    assert focal_agreement([_focal_row(1.0), _focal_row(1.0), _focal_row(0.97)], scales,
                           0.05)["disagrees"] is False  # 3 % lower: under min_drop
    # not convex: no minimum, the drop still said
    f = focal_agreement([_focal_row(1.0), _focal_row(2.0), _focal_row(1.5)], scales, 0.05)
    assert f["best_scale"] is None and f["disagrees"] is True
    # a run without a loss (raised, or no refinement): nothing is said
    f = focal_agreement([_focal_row(1.0), dict(_focal_row(None), error="ValueError: x"),
                         _focal_row(1.0)], scales, 0.05)
    assert f["disagrees"] is None and f["best_scale"] is None and f["loss_drop"] is None
    assert focal_label(1.03) == "focal1.030"
    assert AuditPlan(focal_step=0.03).focal_scales() == (0.97, 1.0, 1.03)
    assert AuditPlan(focal_step=0.03, starts=1, no_start=False,
                     control=True).runs_per_photo() == 5
    with pytest.raises(ValueError, match="focal.step"):
        AuditPlan(focal_step=0.0)
    with pytest.raises(ValueError, match="focal.min_drop"):
        FlagRule(focal_min_drop=1.5)


def test_bad_rule_and_plan_values_name_the_argument():
    with pytest.raises(ValueError, match="rows of camera 'cam' is empty"):
        _flag([])
    with pytest.raises(ValueError, match="flag.min_ok"):
        FlagRule(min_ok=0)
    with pytest.raises(ValueError, match="rot_deg"):
        AuditPlan(rot_deg=(40, 20))
    with pytest.raises(ValueError, match="pivot"):
        AuditPlan(pivot="moon")
    with pytest.raises(ValueError, match="at least one run"):
        AuditPlan(starts=0, no_start=False)
    assert AuditPlan(rot_deg=30).rot_deg == (30.0, 30.0)


# ---------------------------------------------------------------------------------- starts, sample


def test_starts_are_drawn_per_photo_from_the_seed_and_its_name():
    plan = AuditPlan(starts=4, rot_deg=(20, 40), trans=0.05, pivot="camera", seed=3)
    a = audit_starts("IMG_1.jpg", RECORDED, plan, SCALE, None)
    assert [lab for lab, _ in a] == ["none", "start0", "start1", "start2", "start3"]
    assert a[0][1] is None
    for _, c2w in a[1:]:
        assert 20.0 <= rotation_error_deg(c2w, RECORDED) <= 40.0
        assert translation_error(c2w, RECORDED) == pytest.approx(0.05 * SCALE)
    b = audit_starts("IMG_1.jpg", RECORDED, dataclasses.replace(plan, starts=2), SCALE, None)
    np.testing.assert_array_equal(a[1][1], b[1][1])  # more starts keep the first ones
    c = audit_starts("IMG_2.jpg", RECORDED, plan, SCALE, None)
    assert not np.allclose(a[1][1], c[1][1])


def test_a_sample_is_evenly_spread_over_the_name_sorted_photos():
    assert evenly_spread(12, 6) == [0, 2, 4, 7, 9, 11]
    assert evenly_spread(3, 6) == [0, 1, 2] and evenly_spread(5, None) == [0, 1, 2, 3, 4]
    views = [type("V", (), {"name": f"f{i}"})() for i in (10, 2, 1, 30)]
    assert [v.name for v in select_views(views, 2)] == ["f1", "f30"]


def test_a_folder_of_another_audit_is_refused(tmp_path):
    j = AuditJournal(tmp_path, {"model": "a", "seed": 0})
    j.record({"camera": "x", "start": "none", "status": "ok"})
    assert AuditJournal(tmp_path, {"model": "a", "seed": 0}).has("x", "none")
    with pytest.raises(ValueError, match="belongs to another audit .*differs in seed"):
        AuditJournal(tmp_path, {"model": "a", "seed": 1})


# ---------------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A model fitted (the demo's) on 12 photos, two recorded 8 deg / 0.3 units off the truth.

    The photos are renders at the true poses; the capture's cameras.json and the model folder's
    cameras.json hold the recorded (corrupted) poses, as a wrong registration leaves them.
    """
    from icomma_plugin.io.cameras_json import entry_to_intrinsics, write_cameras_json
    from icomma_plugin.io.model_folder import load_model_folder, write_model_folder

    root = tmp_path_factory.mktemp("audit")
    scene, model = demo_model(root / "demo", SIZE)
    mf = load_model_folder(scene.path)
    cap = root / "capture"
    (cap / "images").mkdir(parents=True)
    recorded = []
    for i, e in enumerate(mf.cameras):
        Image.fromarray(photo(model, entry_to_intrinsics(e), e.c2w)).save(
            cap / "images" / f"{e.img_name}.png")
        c2w = e.c2w
        if e.img_name in CORRUPTED:
            deg, trans = CORRUPTED[e.img_name]
            c2w = perturb_pose(c2w, deg, trans, np.random.default_rng(i), pivot="camera")
        recorded.append(dataclasses.replace(e, c2w=c2w))
    write_cameras_json(cap / "cameras.json", recorded)
    write_model_folder(root / "model", model, dict(mf.cfg, source_path=str(cap)), recorded,
                       mf.iteration)
    return {"model": root / "model", "capture": cap, "root": root}


@pytest.fixture(scope="module")
def focal_capture(capture, tmp_path_factory):
    """The capture with every record right but ring_007's focal length 5 % short of the truth."""
    from icomma_plugin.io.cameras_json import read_cameras_json, write_cameras_json
    from icomma_plugin.io.model_folder import load_model_folder, write_model_folder

    root = tmp_path_factory.mktemp("audit_focal")
    cap = root / "capture"
    (cap / "images").mkdir(parents=True)
    for p in (capture["capture"] / "images").iterdir():
        (cap / "images" / p.name).write_bytes(p.read_bytes())
    mf = load_model_folder(capture["model"])
    truth = load_model_folder(capture["root"] / "demo").cameras  # the uncorrupted poses
    recorded = [dataclasses.replace(e, fx=e.fx * 0.95, fy=e.fy * 0.95)
                if e.img_name == "ring_007" else e for e in truth]
    write_cameras_json(cap / "cameras.json", recorded)
    assert read_cameras_json(cap / "cameras.json")[7].fx == pytest.approx(truth[7].fx * 0.95)
    write_model_folder(root / "model", mf.model, dict(mf.cfg, source_path=str(cap)), recorded,
                       mf.iteration)
    return {"model": root / "model", "capture": cap, "root": root}


def _audit(capture, out: Path, *extra):
    cfg = compose([f"model_path={capture['model']}", "sample=6", "starts=1", "threads=1",
                   f"output.dir={out}", "output.progress=false", f"cache.dir={capture['root']}",
                   "calibration.min_right=5", *extra], name="audit")
    return audit_tool().run(cfg, out)


def test_bad_input_is_one_error_naming_the_key(capture, tmp_path):
    tool = audit_tool()
    for overrides, message in (
        ([], "model_path is required"),
        (["model_path=/no/such/model"], "model_path: model folder not found"),
        ([f"model_path={capture['model']}", f"dataset={tmp_path}"], "dataset: unrecognised"),
        ([f"model_path={capture['model']}", "pivot=moon"], "pivot must be one of"),
        ([f"model_path={capture['model']}", "matcher=none"], "needs a matcher"),
        ([f"model_path={capture['model']}", "optimizer=icomma"], "needs a start pose"),
        ([f"model_path={capture['model']}", "calibration.margin=2"], "margin"),
        ([f"model_path={capture['model']}", "focal.enabled=true", "optimizer.refine.focal=true"],
         "focal.enabled .* needs optimizer.refine.focal=false"),
    ):
        with pytest.raises(ValueError, match=message):
            tool.run(compose(overrides + [f"output.dir={tmp_path / 'out'}"], name="audit"),
                     tmp_path)


def test_the_corrupted_cameras_are_flagged_and_the_others_are_not(capture, tmp_path):
    from icomma_plugin.io.model_folder import load_model_folder
    from icomma_plugin.localization.calibration import load_calibration
    from icomma_plugin.localization.verify import VerdictConfig

    out = tmp_path / "audit"
    doc = _audit(capture, out)
    cams = {c["camera"]: c for c in doc["cameras"]}
    assert sorted(cams) == ["ring_000", "ring_002", "ring_004", "ring_007", "ring_009",
                            "ring_011"]
    assert {n for n, c in cams.items() if c["flag"]} == set(CORRUPTED)
    for n in CORRUPTED:
        assert cams[n]["flag"] == "registration"
        assert cams[n]["rot_err_deg"] == pytest.approx(8.0, abs=0.5)
        assert f"photo {n} is at" in cams[n]["reason"]
    for n in set(cams) - set(CORRUPTED):
        assert cams[n]["rot_err_deg"] < 1.0 and cams[n]["trans_err_rel"] < 0.01
    # one row per run, in the one row schema, against the recorded pose
    assert len(doc["rows"]) == 12 and doc["summary"]["flagged"] == sorted(CORRUPTED)
    for r in doc["rows"]:
        assert set(ROW_FIELDS) <= set(r) and r["start"] in ("none", "start0")
        assert r["camera"] == r["name"] and r["gt_c2w"] is not None
    # the control runs: the model's render at each record comes back to the record, the
    # corrupted cameras' too; kept apart from the photos' runs and verdicts
    assert [c["start"] for c in doc["controls"]] == ["control"] * 6
    for n, c in cams.items():
        assert c["control"]["rot_err_deg"] < 0.5 and c["control"]["status"] != "failed", (n, c)
    # (a control whose refinement still moved at its third step, by a hair over the verdict's
    # 0.25-degree / 0.0025-depth bound, is called uncertain; its pose is right all the same)
    assert sum(c["control"]["status"] == "ok" for c in cams.values()) >= 5
    assert doc["summary"]["median_control_rot_err_deg"] < 0.2
    # a capture without COLMAP tracks: nothing said about its records' own precision
    assert doc["summary"]["median_record_rot_std_deg"] is None
    assert all(c["record"] is None and c["within_record"] is None for c in cams.values())
    assert sum(doc["summary"]["verdicts"].values()) == 12
    # the photos are pinhole renders: no lens distortion left in them (their 12 runs' refits)
    lens = doc["summary"]["lens"]
    assert lens["views"] >= 10 and lens["distorted"] is False
    # rendered at the image centre, which their dataset leaves to it: not off
    centre = doc["summary"]["principal_point"]
    assert centre["views"] >= 10 and centre["off"] is False, centre
    text = audit_tool().summary(doc)
    # (the demo folder has no metrics.json: upstream's convention, the image centre)
    assert doc["settings"]["model_principal_point"] == "centre"
    assert ("principal point: the model was fitted with the image centre (upstream 3DGS's camera;"
            in text and "; the photos' refits put it" in text)
    assert "control: the model's renders at the records come back to" in text
    assert "lens: the photos' refits do not agree on a distortion" in text
    reading = audit_tool()._control_reading
    assert "agree with their records" in reading(0.02, 0.001)
    assert "disagreement with their records" in reading(0.3, 0.01)
    assert "the method's own precision" in reading(0.1, 0.08)
    on_disk = json.loads((out / "audit.json").read_text())
    assert on_disk["status"] == "complete" and on_disk["summary"] == doc["summary"]
    # the pictures mark the flagged cameras (magenta frames on the sheet)
    sheet = np.asarray(Image.open(out / "contact_sheet.png").convert("RGB"))
    assert (np.all(sheet == (255, 0, 255), axis=-1)).sum() > 100
    assert (out / "trajectory.png").is_file() and len(list((out / "thumbs").glob("*.png"))) == 6
    # the calibration of the unflagged cameras' right poses, stored where the Localizer finds it
    model = load_model_folder(capture["model"]).model
    cal = load_calibration(model, cache_dir=capture["root"])
    assert doc["calibration"]["counts"]["used"] == 8 and cal is not None
    assert cal.ok_inliers >= VerdictConfig().ok_inliers
    # a rerun on the same folder resumes: no run is localized again
    lines = (out / "audit.jsonl").read_text().count("\n")
    again = _audit(capture, out, "output.contact_sheet=false", "output.trajectory_plot=false")
    assert (out / "audit.jsonl").read_text().count("\n") == lines
    assert again["summary"] == doc["summary"]


def test_the_pictures_mark_only_the_flagged_cameras(tmp_path):
    from icomma_plugin.pictures import contact_sheet, plot_trajectory

    rows = [{"name": f"p{i}", "status": "ok", "rot_err_deg": 0.1, "trans_err_rel": 0.001}
            for i in range(3)]
    p = contact_sheet(tmp_path / "s.png", rows, tmp_path, columns=3, cell=64, border=4,
                      flags={"p1": "registration"})
    a = np.asarray(Image.open(p).convert("RGB"))
    magenta = np.all(a == (255, 0, 255), axis=-1)
    pitch, header = 72, 24
    per_cell = [magenta[header:, i * pitch:(i + 1) * pitch].sum() for i in range(3)]
    assert per_cell[0] == 0 and per_cell[2] == 0 and per_cell[1] > 4 * 60
    cams = [RECORDED, TRUE]
    with pytest.raises(ValueError, match="flagged must have one bool per estimated pose"):
        plot_trajectory(tmp_path / "t.png", cams, cams, cams, flagged=[True])
    plot_trajectory(tmp_path / "t.png", [TRUE, RECORDED], cams, cams, flagged=[True, False],
                    labels={"truth": "recorded"})
    assert (tmp_path / "t.png").is_file()


def test_the_focal_check_finds_the_photo_whose_focal_length_is_off(focal_capture, tmp_path):
    """ring_007's recorded focal length is 5 % short: the check prefers a longer one there only."""
    out = tmp_path / "audit"
    doc = _audit(focal_capture, out, "focal.enabled=true", "no_start=false", "control=false",
                 "calibration.enabled=false", "output.contact_sheet=false",
                 "output.trajectory_plot=false")
    cams = {c["camera"]: c for c in doc["cameras"]}
    assert doc["summary"]["focal_disagreeing"] == ["ring_007"]
    assert doc["summary"]["focal_checked"] == 6
    f = cams["ring_007"]["focal"]
    assert f["disagrees"] is True and f["best_scale"] > 1.02 and f["loss_drop"] > 0.05
    for n in set(cams) - {"ring_007"}:
        assert cams[n]["focal"]["disagrees"] is False, (n, cams[n]["focal"])
    # the focal runs are kept apart from the photos' runs and verdicts
    assert len(doc["rows"]) == 6 and len(doc["focal_runs"]) == 18
    assert {r["start"] for r in doc["focal_runs"]} == {"focal0.970", "focal1.000", "focal1.030"}
    assert "focal lengths: 1 of 6 photos explained better at another focal length" in \
        audit_tool().summary(dict(doc, output_dir=str(out)))
