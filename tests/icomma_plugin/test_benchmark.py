"""Tests of icomma_plugin.benchmark and tools/benchmark.py.

Fast; no shared data needed except the one skip-if-absent lego check.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from icomma_plugin.benchmark import (
    Interval, ProtocolSpec, failure_stats, markdown, pad_curves, pose_auc, pose_seed, run_protocol,
    sample_initial_pose, success_curve, summarize, synthetic_scene, table_rows, time_to_success,
)
from icomma_plugin.benchmark import paper as paper_mod
from icomma_plugin.benchmark.baselines import (
    estimate_relative_pose,
    relative_pose_gt,
    rotation_angle_deg,
)
from icomma_plugin.benchmark.protocols import method_config
from icomma_plugin.benchmark.sampling import rotation_matrix
from icomma_plugin.localize import LocalizerConfig
from icomma_plugin.pose.convert import look_at_c2w, rotation_error_deg
from tests.helpers.paths import REPO
from tests.helpers.tools import compose

PROTOCOLS = ["curves_rotation", "curves_translation", "time_table", "relative_pose", "ablation"]


def _gt():
    return look_at_c2w([4.0, 0.5, 1.5], [0, 0, 0], up=(0, 0, 1))


# ------------------------------------------------------------------------------------ sampling


@pytest.mark.parametrize("rot", [(0.0, 20.0), (20.0, 40.0), (40.0, 60.0), (30.0, 50.0)])
@pytest.mark.parametrize("trans", [(0.0, 0.05), (0.05, 0.1), (0.0, 0.6)])
def test_sampling_angles_and_translations_within_intervals(rot, trans):
    gt = _gt()
    scale = 4.4
    for k in range(25):
        p = sample_initial_pose(gt, rot, trans, pose_seed(3, 1, 7, k), translation_scale=scale)
        assert rot[0] <= p.rot_deg <= rot[1]
        assert float(rotation_error_deg(p.c2w, gt)) == pytest.approx(p.rot_deg, abs=1e-6)
        mags = np.abs(p.offset)
        assert np.all(mags >= trans[0] - 1e-12) and np.all(mags <= trans[1] + 1e-12)
        np.testing.assert_allclose(p.offset_world, p.offset * scale)
        # origin pivot: the centre is rotated about the world origin, then offset
        R = rotation_matrix(p.axis, p.rot_deg)
        np.testing.assert_allclose(p.c2w[:3, 3], R @ gt[:3, 3] + p.offset_world, atol=1e-9)
        np.testing.assert_allclose(p.c2w[:3, :3], R @ gt[:3, :3], atol=1e-9)
        np.testing.assert_allclose(p.pivot, 0.0)


def test_sampling_norm_mode_and_camera_pivot():
    gt = _gt()
    for k in range(20):
        p = sample_initial_pose(
            gt, (10, 20), (0.1, 0.2), pose_seed(0, 0, 0, k), translation_mode="norm", pivot="camera"
        )
        assert 0.1 - 1e-12 <= np.linalg.norm(p.offset) <= 0.2 + 1e-12
        np.testing.assert_allclose(p.c2w[:3, 3], gt[:3, 3] + p.offset_world, atol=1e-12)


def test_sampling_is_seeded_and_reproducible():
    gt = _gt()
    a = sample_initial_pose(gt, (20, 40), (0, 0.2), pose_seed(0, 1, 2, 3))
    b = sample_initial_pose(gt, (20, 40), (0, 0.2), pose_seed(0, 1, 2, 3))
    c = sample_initial_pose(gt, (20, 40), (0, 0.2), pose_seed(0, 1, 2, 4))
    d = sample_initial_pose(gt, (20, 40), (0, 0.2), pose_seed(1, 1, 2, 3))
    np.testing.assert_array_equal(a.c2w, b.c2w)
    assert a.seed == (0, 1, 2, 3) and a.to_json()["seed"] == [0, 1, 2, 3]
    assert not np.allclose(a.c2w, c.c2w) and not np.allclose(a.c2w, d.c2w)
    gen = np.random.default_rng(5)
    e = sample_initial_pose(gt, (5, 5), (0.1, 0.1), gen)
    assert e.rot_deg == 5 and np.allclose(np.abs(e.offset), 0.1)


def test_sampling_rejects_bad_input():
    gt = _gt()
    with pytest.raises(ValueError, match="rot_range_deg"):
        sample_initial_pose(gt, (20, 10), (0, 0.1), np.random.default_rng(0))
    with pytest.raises(ValueError, match="trans_range"):
        sample_initial_pose(gt, (0, 10), (-1, 0.1), np.random.default_rng(0))
    with pytest.raises(ValueError, match="pivot"):
        sample_initial_pose(gt, (0, 10), (0, 0.1), np.random.default_rng(0), pivot="centre")
    with pytest.raises(ValueError, match="seed"):
        pose_seed(-1, 0, 0, 0)


# ------------------------------------------------------------------------------------- metrics


def test_success_curve_carries_final_value_forward():
    rot = [[10.0, 4.0, 0.5], [10.0, 8.0, 6.0, 3.0, 0.9]]
    trans = [[0.1, 0.04, 0.005], [0.1, 0.1, 0.1, 0.01, 0.001]]
    c5 = success_curve(rot, trans, 5.0, 0.05)
    np.testing.assert_allclose(c5, [0.0, 0.5, 0.5, 1.0, 1.0])
    c1 = success_curve(rot, trans, 1.0, 0.01)
    np.testing.assert_allclose(c1, [0.0, 0.0, 0.5, 0.5, 1.0])
    np.testing.assert_allclose(success_curve(rot, trans, 5.0, 0.05, length=7)[-2:], [1.0, 1.0])
    p = pad_curves([[1.0, None]], 3)
    assert np.all(np.isinf(p[0, 1:]))


def test_pose_auc_hand_computed():
    # e = [1, 3]: recall steps 0.5 at 1 and 1.0 at 3.
    # t=5: (0.5*1/2 + (0.5+1)/2*2 + 1*2) / 5 = (0.25 + 1.5 + 2) / 5 = 0.75
    # t=2: (0.25 + 0.5*1) / 2 = 0.375
    assert pose_auc([1.0, 3.0], [5.0, 2.0]) == pytest.approx([0.75, 0.375])
    # a failure (None) is never recalled: (0.25 + 0.5*4) / 5 = 0.45
    assert pose_auc([1.0, None], [5.0]) == pytest.approx([0.45])
    assert pose_auc([0.0, 0.0], [5.0]) == pytest.approx([1.0])
    assert pose_auc([30.0], [5.0, 10.0, 20.0]) == pytest.approx([0.0, 0.0, 0.0])
    assert pose_auc([], [5.0]) == [0.0]


def test_failure_stats_and_time_to_success():
    s = failure_stats([1.0, 10.0, 2.0, None], [0.01, 0.01, 0.2, 0.0], 5.0, 0.05)
    assert s["n"] == 4 and s["failures"] == 3
    assert s["failure_rate"] == pytest.approx(0.75)
    assert s["mean_rot_deg"] == pytest.approx(1.0) and s["mean_trans"] == pytest.approx(0.01)
    none = failure_stats([10.0], [1.0], 5.0, 0.05)
    assert none["failure_rate"] == 1.0 and none["mean_rot_deg"] is None
    assert time_to_success([9, 6, 4, 1], [0.1, 0.1, 0.04, 0.01], [0, 1.0, 2.5, 3.0], 5, 0.05) == 2.5
    assert time_to_success([9, 6], [0.1, 0.1], [0, 1.0], 5, 0.05) is None


# -------------------------------------------------------------------- essential-matrix baseline


def test_essential_matrix_recovers_known_relative_pose():
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 199.5], [0, 500.0, 199.5], [0, 0, 1]])
    c2w_a = look_at_c2w([4.0, 0.0, 1.0], [0, 0, 0], up=(0, 0, 1))
    c2w_b = look_at_c2w([3.0, 2.6, 1.4], [0.1, 0, 0], up=(0, 0, 1))
    w2c_a, w2c_b = np.linalg.inv(c2w_a), np.linalg.inv(c2w_b)
    X = rng.uniform(-1, 1, (300, 3))

    def project(w2c):
        xc = (w2c[:3, :3] @ X.T).T + w2c[:3, 3]
        uv = (K @ xc.T).T
        return uv[:, :2] / uv[:, 2:3]

    pa, pb = project(w2c_a), project(w2c_b)
    pb_noisy = pb + rng.normal(0, 0.2, pb.shape)
    est = estimate_relative_pose(pa, pb_noisy, K, K, thresh_px=1.0)
    R_gt, t_gt = relative_pose_gt(w2c_a, w2c_b)
    assert rotation_angle_deg(R_gt, np.eye(3)) > 20
    assert est is not None and est.num_inliers > 200
    assert rotation_angle_deg(est.R, R_gt) < 0.5
    assert float(np.degrees(np.arccos(np.clip(est.t @ (t_gt / np.linalg.norm(t_gt)), -1, 1)))) < 3.0
    assert estimate_relative_pose(pa[:4], pb[:4], K, K) is None


# ---------------------------------------------------------------------------------- protocols


def _compose(overrides, hydra_config=False):
    return compose(overrides, name="benchmark", hydra_config=hydra_config)


@pytest.mark.parametrize("name", PROTOCOLS)
def test_every_protocol_composes(name):
    from omegaconf import OmegaConf

    cfg = _compose([f"benchmark_protocol={name}", "seed=7"])
    d = OmegaConf.to_container(cfg.benchmark_protocol, resolve=True)
    full = ProtocolSpec.from_dict(d, quick=False)
    quick = ProtocolSpec.from_dict(d, quick=True)
    assert full.name == name and full.seed == 7
    assert quick.quick and not full.quick and quick.num_runs < full.num_runs
    LocalizerConfig.from_dict(OmegaConf.to_container(cfg.optimizer, resolve=True))
    for m in full.methods:
        if m != "essential":
            method_config(m, LocalizerConfig(), full.max_iterations)


def test_protocol_intervals_match_the_brief():
    from omegaconf import OmegaConf

    def spec(n):
        return ProtocolSpec.from_dict(
            OmegaConf.to_container(
                _compose([f"benchmark_protocol={n}"]).benchmark_protocol, resolve=True
            )
        )

    assert [iv.rot_deg for iv in spec("curves_rotation").intervals] == [(0, 20), (20, 40), (40, 60)]
    tt = spec("time_table")
    assert [iv.rot_deg for iv in tt.intervals if not iv.no_start] == [(10, 20), (20, 40), (60, 180)]
    assert all(iv.trans == (0.0, 0.2) for iv in tt.intervals if not iv.no_start)
    assert [iv.label for iv in tt.intervals if iv.no_start] == ["no_start"]
    # the paper's methods never run without a start pose; they run their first 4 starts per query
    nostart = next(iv for iv in tt.intervals if iv.no_start)
    assert tt.runs("icomma", nostart) == 0 and tt.runs("robust", nostart) == 50
    assert tt.runs("icomma", tt.intervals[0]) == 20
    ab = spec("ablation")
    assert ab.intervals[0].rot_deg == (30, 50) and ab.intervals[0].trans == (0.0, 0.6)
    assert ab.methods == ["robust", "icomma", "match_only", "compare_only"]
    assert spec("relative_pose").methods == ["robust", "icomma", "essential"]


@pytest.mark.parametrize(
    "launcher,target", [("joblib_local", "JoblibLauncher"), ("slurm_cluster", "SlurmLauncher")]
)
def test_launcher_configs_compose(launcher, target):
    # Composing checks the options against the launcher plugin's schema; the class it names
    # must be importable (the plugin installed) and be that plugin's Hydra launcher.
    from hydra.plugins.launcher import Launcher
    from hydra.utils import get_class

    cfg = _compose([f"hydra/launcher={launcher}"], hydra_config=True)
    cls = get_class(cfg.hydra.launcher._target_)
    assert issubclass(cls, Launcher) and cls.__name__ == target


def test_method_configs():
    base = LocalizerConfig(lambda_match=0.7)
    assert method_config("compare_only", base).use_matching is False
    mo = method_config("match_only", base, 12)
    assert mo.lambda_match == 1.0 and mo.switch_threshold == 0.0 and mo.max_iterations == 12
    assert method_config("icomma", base).lambda_match == 0.7
    with pytest.raises(ValueError):
        method_config("essential", base)
    with pytest.raises(ValueError, match="methods"):
        ProtocolSpec(
            name="x", kind="time", intervals=[Interval("a", (0, 1), (0, 0))], methods=["nope"]
        )


# ------------------------------------------------------------------------------------- report


def _fake_records(spec):
    recs = []
    for iv in spec.intervals:
        for k in range(2):
            for m in spec.methods:
                ok = k == 0
                recs.append(
                    {
                        "key": f"{iv.label}|{k}|{m}",
                        "interval": iv.label,
                        "method": m,
                        "query_index": 0,
                        "pose_index": k,
                        "init_rot_err_deg": 15.0,
                        "init_trans_err_rel": 0.1,
                        "rot_err_deg": 0.5 if ok else 30.0,
                        "trans_err_rel": 0.005 if ok else 0.5,
                        "status": "ok" if ok else "failed",
                        "seconds": 2.0,
                        "iterations": 3,
                        "time_to_success": {"5deg_0.05": 1.0 if ok else None},
                        "curve_rot_deg": [15.0, 4.0, 0.5] if ok else [15.0, 20.0, 30.0],
                        "curve_trans": [0.1, 0.02, 0.005] if ok else [0.1, 0.3, 0.5],
                        "curve_seconds": [0.0, 0.5, 1.0],
                    }
                )
    return recs


def test_report_markdown_has_paper_columns_and_delta(monkeypatch, tmp_path):
    spec = ProtocolSpec(
        name="time_table",
        kind="time",
        methods=["icomma", "compare_only"],
        max_iterations=2,
        intervals=ProtocolSpec.from_dict(
            {
                "name": "t",
                "kind": "time",
                "methods": ["icomma"],
                "intervals": [{"label": "r10-20", "rot_deg": [10, 20], "trans": [0, 0.2]}],
            }
        ).intervals,
    )
    summary = summarize(spec, _fake_records(spec))
    cell = summary["cells"][0]
    assert cell["success_rate"] == pytest.approx(0.5) and cell[
        "seconds_to_success"
    ] == pytest.approx(1.0)
    assert cell["curves"]["5deg_0.05"] == pytest.approx([0.0, 0.5, 0.5])
    md = markdown(spec, summary, "xfeat")
    assert (
        "| interval | method | metric | n | ours | paper | Δ (ours − paper) | paper source |" in md
    )
    assert paper_mod.NOT_FOUND in md and "50.0%" in md
    # a known paper value gets a delta
    monkeypatch.setitem(
        paper_mod.PAPER_NUMBERS,
        ("synthetic", "time_table", "r10-20", "icomma", "success_rate"),
        paper_mod.PaperValue(0.8, "Tab. X (test)"),
    )
    rows = table_rows(spec, summary, "xfeat")
    r = next(r for r in rows if r["method"] == "icomma" and r["metric"] == "success_rate")
    assert (
        r["paper"] == 0.8 and r["delta"] == pytest.approx(-0.3) and r["source"] == "Tab. X (test)"
    )
    assert "-30.0%" in markdown(spec, summary, "xfeat")
    from icomma_plugin.benchmark import save_plots

    files = save_plots(spec, summary, tmp_path)
    assert files and all((tmp_path / f).stat().st_size > 0 for f in files)


def test_results_md_says_once_per_table_that_the_paper_has_no_cell(tmp_path):
    """results.md: a row without a paper value shows "–", and one line under the table says why.

    Issue 16, bug 5: before, every such row repeated NOT_FOUND in the paper column and a
    sentence ("no cell for ...") in the source column.
    """
    from icomma_plugin.benchmark import ResultsWriter

    spec = ProtocolSpec(name="time_table", kind="time", methods=["icomma", "robust"],
                        max_iterations=2, intervals=[Interval("r10-20", (10, 20), (0, 0.2))])
    records = _fake_records(spec)
    w = ResultsWriter(tmp_path, spec, config={}, scene={"kind": "synthetic",
                      "translation_unit": "world", "translation_scale": 1.0, "queries": []},
                      matcher="sift", localizer_config={}, seed=0, plots=False)
    for rec in records:
        w.add(rec)
    w.write(final=True)
    md = (tmp_path / "results.md").read_text()
    rows = table_rows(spec, summarize(spec, records), "sift")
    missing = [r for r in rows if r["paper"] is None]
    assert len(missing) > 1 and len(missing) < len(rows)  # both kinds of row, several without
    assert md.count(paper_mod.NOT_FOUND) == 1 and "no cell for" not in md
    assert f"({len(missing)} of {len(rows)} rows)" in md
    table = [ln for ln in md.splitlines() if ln.startswith("| r10-20 |")]
    assert len(table) == len(rows)
    for line in table:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[1] == "robust":  # the paper has no row for our default method
            assert cells[5:] == ["–", "–", "–"], line
    known = [ln for ln in table if "| icomma | success_rate |" in ln]
    assert len(known) == 1 and "Table 1" in known[0] and "%" in known[0].split("|")[6]


def _paper_tables():
    """The markdown tables of ../shared/docs/paper_results.md as lists of rows (cells split)."""
    doc = REPO.parent / "shared" / "docs" / "paper_results.md"
    if not doc.is_file():
        pytest.skip(f"paper transcription not found at {doc}")
    tables, cur = [], []
    for line in doc.read_text().splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(set(c) <= set("-: ") for c in cells):
                cur.append(cells)
        elif cur:
            tables.append(cur)
            cur = []
    if cur:
        tables.append(cur)
    return tables


def test_paper_numbers_are_the_transcription():
    """Every number of paper.py is in the transcribed tables, at its place (nothing invented)."""
    t1, t2, t3, t4 = _paper_tables()[:4]
    pv = paper_mod.paper_value
    # Table 1: rows success (%) and time (s); columns iNeRF, iComMa, iComMa_c for each interval
    succ = [float(x) for x in t1[1][1:]]
    secs = [float(x) for x in t1[2][1:]]
    for j, (iv, m) in enumerate(
        [(iv, m) for iv in ("r10-20", "r20-40") for m in ("inerf", "icomma", "compare_only")]
    ):
        assert pv("time_table", iv, m, "success_rate").value == pytest.approx(succ[j] / 100)
        assert pv("time_table", iv, m, "seconds_to_success").value == pytest.approx(secs[j])
    # Tables 2 / 3: per method "a / b / c" per bin
    names = {
        "MatchFormer": "matchformer",
        "LightGlue": "essential_lightglue",
        "LoFTR": "essential_loftr",
        "iComMa": "icomma",
    }
    for table, ds in ((t2, "synthetic"), (t3, "360")):
        for row in table[1:]:
            for iv, cell in zip(("r0-20", "r20-40", "r40-60"), row[1:]):
                for k, x in zip(("auc5", "auc10", "auc20"), cell.split("/")):
                    assert pv("relative_pose", iv, names[row[0]], k, ds).value == pytest.approx(
                        float(x) / 100
                    )
    # Table 4
    variants = {"iComMa": "icomma", "w/o comparing": "match_only", "w/o matching": "compare_only"}
    for row in t4[1:]:
        m = variants[row[0]]
        for ds, vals in (("synthetic", row[1:4]), ("360", row[4:7])):
            for k, x in zip(("failure_rate", "mean_rot_deg", "mean_trans"), vals):
                assert pv("ablation", "r30-50", m, k, ds).value == pytest.approx(float(x))
    assert pv("time_table", "r60-180", "robust", "success_rate").note == paper_mod.NOT_FOUND


# ------------------------------------------------------------------------------ end to end


def test_run_protocol_in_process_with_essential_baseline():
    scene = synthetic_scene(num_gaussians=120, width=48, height=48, num_queries=1)
    spec = ProtocolSpec.from_dict(
        {
            "name": "relative_pose",
            "kind": "relative_pose",
            "methods": ["compare_only", "essential"],
            "num_queries": 1,
            "poses_per_query": 1,
            "max_iterations": 3,
            "intervals": [{"label": "r0-20", "rot_deg": [5, 10], "trans": [0, 0]}],
        }
    )
    from icomma_plugin.matchers import make_matcher

    seen = []
    recs = run_protocol(scene, spec, LocalizerConfig(), make_matcher("sift"), on_record=seen.append)
    assert len(recs) == 2 and len(seen) == 2
    co = recs[0]
    assert co["method"] == "compare_only" and len(co["curve_rot_deg"]) == co["iterations"] + 1
    assert 5 <= co["init_rot_err_deg"] <= 10
    assert recs[1]["method"] == "essential" and "num_matches" in recs[1]
    s = summarize(spec, recs)
    assert {c["method"] for c in s["cells"]} == {"compare_only", "essential"}
    # resuming reuses finished runs; the progress bar counts them by verdict as well
    from tools.benchmark import count_run

    events = []
    again = run_protocol(
        scene,
        spec,
        LocalizerConfig(),
        make_matcher("sift"),
        done={r["key"]: r for r in recs},
        on_record=lambda r: pytest.fail("recomputed a finished run"),
        progress=events.append,
    )
    assert [r["key"] for r in again] == [r["key"] for r in recs]
    counts = {"ok": 0, "uncertain": 0, "failed": 0, "error": 0}
    for ev in events:
        if ev["event"] == "run_end":
            count_run(counts, ev["record"])
    assert sum(counts.values()) >= 1, counts  # the essential baseline gives no verdict
    assert counts == {k: sum(r.get("status") == k for r in recs) for k in counts}, counts


def test_tool_smoke_run_on_synthetic_scene(tmp_path):
    out = tmp_path / "run"
    cmd = [
        sys.executable,
        str(REPO / "tools" / "benchmark.py"),
        "scene.kind=synthetic",
        "scene.synthetic.num_gaussians=100",
        "scene.synthetic.width=40",
        "scene.synthetic.height=40",
        "benchmark_protocol=ablation",
        "benchmark_protocol.methods=[icomma,compare_only]",
        "quick=true",
        "benchmark_protocol.quick.num_queries=1",
        "benchmark_protocol.quick.poses_per_query=1",
        "benchmark_protocol.quick.max_iterations=2",
        "matcher=sift",
        "output.progress=false",
        f"hydra.run.dir={out}",
    ]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run(cmd, cwd=str(tmp_path), env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    doc = json.loads((out / "results.json").read_text())
    assert doc["status"] == "complete" and doc["quick"] is True and doc["size"] == "quick"
    assert doc["num_runs_done"] == 2 and doc["seed"] == 0
    assert doc["scene"]["translation_unit"] == "world" and doc["scene"]["translation_scale"] == 1.0
    assert doc["records"][0]["seed"] == [0, 0, 0, 0]
    from icomma_plugin.localization.types import ROW_FIELDS

    for rec in doc["records"]:  # the one row schema, plus the benchmark's own fields
        assert set(ROW_FIELDS) | {"key", "protocol", "interval", "query_index", "pose_index",
                                  "seed", "init", "time_to_success"} <= set(rec), rec.keys()
        assert rec["method"] in ("icomma", "compare_only") and rec["status"] is not None
    md = (out / "results.md").read_text()
    assert "paper" in md and "failure_rate" in md
    assert (out / "failure_rate_ablation.png").is_file()


# ---------------------------------------------------------------------- shared data (optional)


def test_lego_scene_radius_and_origin_pivot(lego_root):
    from icomma_plugin.io.datasets import read_dataset

    sd = read_dataset(lego_root, white_background=True)
    r = sd.scene_radius()
    assert 3.0 < r < 6.0  # lego cameras sit ~4 world units from the origin
    gt = sd.test[0].c2w
    p = sample_initial_pose(gt, (20, 40), (0, 0.2), pose_seed(0, 0, 0, 0), translation_scale=r)
    # rotating about the origin keeps the distance to the origin before the offset
    d0 = np.linalg.norm(gt[:3, 3])
    assert np.linalg.norm(p.c2w[:3, 3] - p.offset_world) == pytest.approx(d0, rel=1e-9)


def test_results_writer_writes_after_each_run(tmp_path):
    from icomma_plugin.benchmark import ResultsWriter, load_done

    spec = ProtocolSpec.from_dict(
        {
            "name": "ablation",
            "kind": "ablation",
            "methods": ["icomma", "compare_only"],
            "max_iterations": 2,
            "intervals": [{"label": "r30-50", "rot_deg": [30, 50], "trans": [0, 0.6]}],
        }
    )
    w = ResultsWriter(
        tmp_path,
        spec,
        config={"a": 1},
        scene={
            "kind": "synthetic",
            "translation_unit": "world",
            "translation_scale": 1.0,
            "queries": [],
        },
        matcher="sift",
        localizer_config={},
        seed=3,
        plots=False,
    )
    rec = _fake_records(spec)[0]
    w.add(rec)
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["status"] == "running" and doc["num_runs_done"] == 1 and doc["seed"] == 3
    assert "partial: 1 of" in (tmp_path / "results.md").read_text()
    assert set(load_done(tmp_path / "results.json")) == {rec["key"]}
    w.write(final=True)
    assert json.loads((tmp_path / "results.json").read_text())["status"] == "complete"


def test_training_scale_from_cfg_args():
    from icomma_plugin.benchmark.scene import select_indices, training_scale

    assert training_scale({"resolution": 2}, [], 400) == 0.5
    assert training_scale({"resolution": 200}, [], 400) == 0.5
    assert training_scale({"resolution": -1}, [], 400) == 1.0
    assert training_scale({}, [], 3200) == 0.5
    assert select_indices(200, 5) == [0, 50, 100, 149, 199]
    with pytest.raises(ValueError, match="out of range"):
        select_indices(10, 2, [3, 12])


def test_a_run_that_raises_is_recorded_and_the_benchmark_goes_on(monkeypatch):
    """One failing run is kept with its error (type, message), counted as a failure.

    The protocol finishes the others.
    """
    from icomma_plugin.localization.localizer import Localizer

    scene = synthetic_scene(num_gaussians=120, width=48, height=48, num_queries=1)
    spec = ProtocolSpec.from_dict(
        {
            "name": "time_table",
            "kind": "time",
            "methods": ["compare_only"],
            "num_queries": 1,
            "poses_per_query": 3,
            "max_iterations": 2,
            "intervals": [{"label": "r10-20", "rot_deg": [10, 20], "trans": [0, 0.1]}],
        }
    )
    real = Localizer.localize
    calls = []

    def flaky(self, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("image0 must hold values in [0, 1] (a test double)")
        return real(self, *a, **k)

    monkeypatch.setattr(Localizer, "localize", flaky)
    recs = run_protocol(scene, spec, LocalizerConfig(), None)
    assert len(recs) == 3 and len(calls) == 3
    bad = [r for r in recs if r.get("error")]
    assert (
        len(bad) == 1
        and bad[0]["error"]["type"] == "ValueError"
        and "values in [0, 1]" in bad[0]["error"]["message"]
    )
    cell = summarize(spec, recs)["cells"][0]
    assert cell["num_errors"] == 1 and cell["n"] == 3
    assert cell["success_rate"] <= 2 / 3


def test_no_start_interval_runs_only_the_default_method():
    scene = synthetic_scene(num_gaussians=200, width=64, height=64, num_queries=1)
    spec = ProtocolSpec.from_dict(
        {
            "name": "time_table",
            "kind": "time",
            "methods": ["robust", "icomma"],
            "num_queries": 1,
            "poses_per_query": 1,
            "max_iterations": 2,
            "intervals": [{"label": "no_start", "init": "none"}],
        }
    )
    from icomma_plugin.matchers import make_matcher

    recs = run_protocol(scene, spec, LocalizerConfig(), make_matcher("xfeat"))
    assert [r["method"] for r in recs] == ["robust"] and recs[0]["init"] is None
    r = recs[0]
    assert r["init_c2w"] is None and r["init_rot_err_deg"] is None and r["error"] is None
    # without a start, the candidate views find the pose (this scene: 0.0003 deg, measured)
    assert r["hypotheses"] >= 1 and r["status"] == "ok", r["reason"]
    assert r["rot_err_deg"] < 0.5 and r["trans_err_rel"] < 0.005, r
    assert r["time_to_success"]["5deg_0.05"] is not None


def test_the_report_puts_the_records_own_precision_beside_the_errors():
    """Rows of the records' precision only where the queries have one (COLMAP tracks)."""
    spec = ProtocolSpec.from_dict({"name": "real_capture", "kind": "time", "methods": ["robust"],
                                   "intervals": [{"label": "r20-40", "rot_deg": [20, 40],
                                                  "trans": [0.0, 0.05]}],
                                   "num_queries": 2, "poses_per_query": 2})
    base = {"interval": "r20-40", "method": "robust", "seconds": 1.0, "iterations": 3,
            "status": "ok", "trans_err_rel": 0.001}
    recs = [dict(base, rot_err_deg=e, record_rot_std_deg=s, record_sigmas=m)
            for e, s, m in ((0.05, 0.08, 1.0), (0.15, 0.08, 2.0), (0.3, 0.1, 5.0),
                            (0.1, 0.06, 3.0))]
    cell = summarize(spec, recs)["cells"][0]
    assert cell["median_record_rot_std_deg"] == pytest.approx(0.08)
    assert cell["within_record"] == pytest.approx(0.75)  # 5 sigmas: outside its record's
    md = markdown(spec, summarize(spec, recs), "xfeat")
    assert "| r20-40 | robust | median_record_rot_std_deg | 4 | 0.08 |" in md
    assert "| r20-40 | robust | within_record | 4 | 75.0% |" in md
    assert "a perfect method would land about 0.9x this from them" in md
    plain = [{k: v for k, v in r.items() if not k.startswith("record")} for r in recs]
    assert "record" not in markdown(spec, summarize(spec, plain), "xfeat")


def test_the_bird_capture_records_precision_from_its_tracks(shared_data):
    """Every photo of the shared COLMAP capture gets its record's precision from its tracks."""
    from icomma_plugin.io.datasets.colmap_tracks import record_precision

    bird = shared_data / "bird"
    if not (bird / "sparse" / "0").is_dir():
        pytest.skip("../shared/data/bird not found")
    table = record_precision(bird)
    assert len(table) == 184  # every photo: SIMPLE_PINHOLE, one camera each, 200-400 points
    stds = np.array([v["rot_std_deg"] for v in table.values()])
    assert 0.1 < np.median(stds) < 0.3 and all(v["focal_free"] for v in table.values())
    assert all(v["points_free"] for v in table.values())  # the bundle: 184 x 7 parameters
    assert 0.5 < np.median([v["rms_px"] for v in table.values()]) < 2.0
    cov = np.array(next(iter(table.values()))["rot_cov"])
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_records_covariance_that_says_nothing_gives_no_sigmas():
    from icomma_plugin.benchmark.runner import _record_sigmas
    from icomma_plugin.benchmark.scene import BenchQuery

    gt = _gt()
    q = BenchQuery(None, gt, 0, {"rot_std_deg": 0.1, "rot_cov": np.zeros((3, 3)).tolist()})
    assert _record_sigmas(gt, q) is None
    q.record["rot_cov"] = (np.eye(3) * np.radians(0.1) ** 2).tolist()
    turned = gt.copy()
    turned[:3, :3] = gt[:3, :3] @ rotation_matrix(np.array([0.0, 0.0, 1.0]), 0.2)
    assert _record_sigmas(turned, q) == pytest.approx(2.0, rel=1e-6)
