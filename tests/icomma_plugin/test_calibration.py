"""Per-model verdict calibration (localization/calibration.py) and the benchmark's use of it.

Rows are synthetic audit rows (the one row schema's fields the calibration reads: ``status``,
``rot_err_deg``, ``trans_err_rel``, ``camera``, ``signals``), so every number is known.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from icomma_plugin.benchmark.report import calibrated_status, verdict_stats
from icomma_plugin.localization.calibration import (
    CALIBRATION_FORMAT,
    CalibrationConfig,
    CalibrationError,
    calibrate,
    calibration_path,
    load_calibration,
    model_key,
    redecide,
    save_calibration,
    stricter,
)
from icomma_plugin.localization.candidate_cache import model_fingerprint
from icomma_plugin.localization.verify import PoseScore, VerdictConfig, decide
from tests.helpers.gaussians import random_gaussians

GLOBAL = VerdictConfig()


def _signals(inliers, matches, median_px, mean_px, spread=0.5, coverage=0.8, converged=True):
    score = PoseScore(inliers=inliers, matches=matches, median_px=median_px, mean_px=mean_px,
                      spread=spread, coverage=coverage, photometric_rmse=0.05)
    return {**score.to_json(), "converged": converged, "ambiguous": False, "rival": None}


def _row(camera, signals, rot=0.05, trans=0.001, status=None):
    s = signals
    if status is None:
        status = decide(PoseScore(**{k: s[k] for k in (
            "matches", "inliers", "median_px", "mean_px", "spread", "coverage",
            "photometric_rmse")}), GLOBAL, converged=s["converged"]).status
    return {"camera": camera, "name": camera, "status": status, "rot_err_deg": rot,
            "trans_err_rel": trans, "signals": s}


def _strong_model_rows(n=60, seed=0):
    """Right poses of a model much better than the global floor: 200-300 agreeing matches."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        m = int(rng.integers(230, 320))
        k = int(m * rng.uniform(0.9, 0.98))
        rows.append(_row(f"cam{i % 20}", _signals(k, m, rng.uniform(0.05, 0.3),
                                                  rng.uniform(0.05, 0.25))))
    return rows


#: The issue's wrong pose called ok: 5.8 deg off, 68 of 130 matches agreeing, mean 0.79 px,
#: median 1.0 px (every global ok threshold just met).
WRONG_OK = _row("held_out", _signals(68, 130, 1.0, 0.79), rot=5.8, trans=0.050)


def test_calibrated_thresholds_are_never_looser_than_global():
    weak = []  # a model WORSE than the global floor: its right poses barely reach the thresholds
    rng = np.random.default_rng(1)
    for i in range(40):
        m = int(rng.integers(55, 80))
        weak.append(_row(f"c{i}", _signals(int(m * 0.6), m, 0.9, 0.75, spread=0.045,
                                           coverage=0.12)))
    for rows in (weak, _strong_model_rows()):
        cal = calibrate(rows, GLOBAL)
        v = cal.verdict
        assert v.ok_inliers >= GLOBAL.ok_inliers and v.ok_ratio >= GLOBAL.ok_ratio
        assert v.ok_spread >= GLOBAL.ok_spread and v.ok_coverage >= GLOBAL.ok_coverage
        assert v.ok_median_px <= GLOBAL.ok_median_px and v.ok_mean_px <= GLOBAL.ok_mean_px
        for name in ("inlier_px", "fail_inliers", "fail_coverage"):
            assert getattr(v, name) == getattr(GLOBAL, name)
    assert calibrate(weak, GLOBAL).changed() == {}  # a weak model keeps the global thresholds


def test_a_calibration_rejects_the_wrong_ok_that_the_global_thresholds_accept():
    rows = _strong_model_rows()
    cal = calibrate(rows, GLOBAL)
    # the values follow the rule: 1st percentile x 0.8 of the right poses' agreeing matches
    inl = [r["signals"]["inliers"] for r in rows]
    assert cal.verdict.ok_inliers == int(np.floor(np.percentile(inl, 1.0) * 0.8))
    mean = [r["signals"]["mean_px"] for r in rows]
    assert cal.verdict.ok_mean_px == pytest.approx(max(np.percentile(mean, 99.0) / 0.8, 0.25))
    assert redecide(WRONG_OK["signals"], GLOBAL).status == "ok"
    v = redecide(WRONG_OK["signals"], cal.verdict)
    assert v.status == "uncertain" and "agreeing matches" in v.reason
    # ... and keeps (almost) all of the model's right poses ok
    kept = sum(redecide(r["signals"], cal.verdict).status == "ok" for r in rows)
    assert kept >= 0.95 * len(rows)


def test_flagged_cameras_wrong_and_doubted_poses_are_not_learnt_from():
    rows = _strong_model_rows()
    bad = [_row("flagged", _signals(40, 60, 0.9, 0.7))]  # a flagged camera's weak right pose
    wrong = [_row("cam4", _signals(45, 70, 0.9, 0.7), rot=8.0, trans=0.07)]  # not right
    doubted = [_row("cam5", _signals(35, 80, 0.9, 0.7), status="uncertain")]
    base = calibrate(rows, GLOBAL).verdict
    cal = calibrate(rows + bad + wrong + doubted, GLOBAL, flagged={"flagged"})
    assert cal.verdict == base
    assert cal.counts["used"] == len(rows) and cal.counts["flagged_cameras"] == 1
    # poses=all learns from the right poses the global verdict doubts too: looser, still >= global
    loose = calibrate(rows + doubted * 5, GLOBAL, CalibrationConfig(poses="all"))
    assert GLOBAL.ok_inliers <= loose.verdict.ok_inliers < base.ok_inliers


def test_too_few_right_poses_give_no_calibration():
    with pytest.raises(CalibrationError, match="only 5 right poses"):
        calibrate(_strong_model_rows(5), GLOBAL)
    with pytest.raises(ValueError, match="CalibrationConfig.margin"):
        CalibrationConfig(margin=1.5)
    with pytest.raises(ValueError, match="calibration.*unknown|percentil"):
        CalibrationConfig.from_dict({"percentil": 1.0})


def test_redecide_reproduces_decide_and_keeps_the_method_extras():
    s = _signals(120, 130, 0.2, 0.15)
    assert redecide(s, GLOBAL).status == "ok"
    assert redecide({**s, "converged": False}, GLOBAL).status == "uncertain"
    rival = {"rot_deg_apart": 30.0, "support": 90, "best_support": 100}
    v = redecide({**s, "ambiguous": True, "rival": rival}, GLOBAL)
    assert v.status == "uncertain" and "rival" in v.reason
    no_inlier = {**_signals(0, 20, float("inf"), float("inf")), "converged": None}
    assert no_inlier["median_px"] is None  # JSON's inf
    assert redecide(no_inlier, GLOBAL).status == "failed"
    assert redecide({"converged": None}, GLOBAL) is None  # no score: nothing to re-decide
    assert stricter("ok", "uncertain") == "uncertain" and stricter("failed", "ok") == "failed"
    assert stricter(None, "ok") == "ok"


def test_stored_and_loaded_per_model(tmp_path):
    model = random_gaussians(200, seed=0)
    other = random_gaussians(200, seed=1)
    cal = calibrate(_strong_model_rows(), GLOBAL, source={"audit": "a/audit.json"})
    p = save_calibration(cal, model, cache_dir=tmp_path)
    assert p == tmp_path / "calibration" / f"{model_key(model)}.json"
    doc = json.loads(p.read_text())
    assert doc["format"] == CALIBRATION_FORMAT and doc["model"] == model_key(model)
    assert doc["source"] == {"audit": "a/audit.json"} and doc["counts"]["used"] == 60
    assert doc["verdict"] == dataclasses.asdict(cal.verdict)
    assert load_calibration(model, cache_dir=tmp_path) == cal.verdict
    assert load_calibration(other, cache_dir=tmp_path) is None  # another model: none stored
    with pytest.raises(CalibrationError, match="for another model"):
        load_calibration(other, path=p)
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(model, path=tmp_path / "missing.json")
    p.write_text("{not json")
    assert load_calibration(model, cache_dir=tmp_path) is None  # damaged: global thresholds
    with pytest.raises(CalibrationError, match="unreadable"):
        load_calibration(model, path=p)


def test_default_folder_and_the_localizers_model(monkeypatch, tmp_path):
    monkeypatch.setenv("ICOMMA_CACHE_DIR", str(tmp_path))
    model = random_gaussians(100, degree=3, seed=2)
    model.sh_rest.zero_()  # the Localizer renders such a model at degree 0: the same key
    assert model_key(model) == model_key(model.with_sh_degree(0))
    assert model_key(model) == model_fingerprint(model.with_sh_degree(0))
    assert calibration_path("abc") == tmp_path / "calibration" / "abc.json"
    cal = calibrate(_strong_model_rows(), GLOBAL)
    save_calibration(cal, model)
    assert load_calibration(model.with_sh_degree(0)) == cal.verdict
    with pytest.raises(ValueError, match="model must be a GaussianModel"):
        model_key("model")


def test_benchmark_reports_precision_and_recall_with_both_thresholds():
    cal = calibrate(_strong_model_rows(), GLOBAL)
    right = [_row("q", _signals(250, 260, 0.1, 0.1), rot=0.1, trans=0.001) for _ in range(9)]
    records = [dict(r, trans_err_rel=r["trans_err_rel"]) for r in right + [WRONG_OK]]
    glob = verdict_stats(records, (5.0, 0.05))
    assert "verdict_precision_calibrated" not in glob
    assert glob["verdict_precision"] == pytest.approx(0.9)  # the wrong pose is called ok
    both = verdict_stats(records, (5.0, 0.05), cal.verdict)
    assert both["verdict_precision"] == pytest.approx(0.9)
    assert both["verdict_precision_calibrated"] == pytest.approx(1.0)
    assert both["verdict_recall_calibrated"] == pytest.approx(1.0)
    assert both["wrong_flagged_calibrated"] == pytest.approx(1.0)
    assert both["verdict_ok_calibrated"] == 9 and both["verdict_uncertain_calibrated"] == 1
    # a calibration never turns a recorded doubt into ok, nor a row without a score
    assert calibrated_status(dict(right[0], status="uncertain"), cal.verdict) == "uncertain"
    assert calibrated_status({"status": "failed", "signals": {}}, cal.verdict) == "failed"


def test_markdown_rows_of_the_calibrated_verdict_only_with_a_calibration():
    from icomma_plugin.benchmark.protocols import ProtocolSpec
    from icomma_plugin.benchmark.report import markdown, summarize

    spec = ProtocolSpec.from_dict({"name": "real_capture", "kind": "time", "methods": ["robust"],
                                   "intervals": [{"label": "r20-40", "rot_deg": [20, 40],
                                                  "trans": [0.0, 0.05]}],
                                   "num_queries": 1, "poses_per_query": 10})
    recs = [dict(r, interval="r20-40", method="robust", seconds=1.0, iterations=3)
            for r in [_row("q", _signals(250, 260, 0.1, 0.1))] * 9 + [WRONG_OK]]
    assert "calibrated" not in markdown(spec, summarize(spec, recs), "xfeat")
    cal = calibrate(_strong_model_rows(), GLOBAL)
    md = markdown(spec, summarize(spec, recs, cal.verdict), "xfeat")
    assert "| r20-40 | robust | verdict_precision | 10 | 90.0% |" in md
    assert "| r20-40 | robust | verdict_precision_calibrated | 10 | 100.0% |" in md


def test_the_benchmark_tool_finds_the_models_calibration(monkeypatch, tmp_path):
    import importlib.util
    import sys

    from omegaconf import OmegaConf

    from tests.helpers.paths import REPO

    name = "icomma_tools_benchmark"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "tools" / "benchmark.py")
        sys.modules[name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules[name])
    find = sys.modules[name].verdict_calibration
    monkeypatch.setenv("ICOMMA_CACHE_DIR", str(tmp_path))
    model, other = random_gaussians(50, seed=3), random_gaussians(50, seed=4)
    auto = OmegaConf.create({"calibration": "auto"})
    none = OmegaConf.create({"calibration": "none"})
    assert find(auto, model) == (None, None)  # no calibration stored for this model
    cal = calibrate(_strong_model_rows(), GLOBAL)
    p = save_calibration(cal, model)
    assert find(auto, model) == (cal.verdict, str(p))
    assert find(none, model) == (None, None)
    assert find(OmegaConf.create({"calibration": str(p)}), model)[0] == cal.verdict
    with pytest.raises(ValueError, match="calibration: .*for another model"):
        find(OmegaConf.create({"calibration": str(p)}), other)
