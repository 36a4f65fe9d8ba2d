"""tools/bench_localize.py on a small demo scene.

It runs both methods through the scene's Localizer, writes its JSON and markdown, records the same
pose as a one-off ``localize()`` call from the same start, records a run that raises, and bad input
is one line.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch


def test_both_methods(small_demo, tmp_path, capsys):
    from tools.bench_localize import STAGES, main

    out = tmp_path / "bench"
    rc = main(
        [
            "--scenes",
            "demo",
            "--demo-path",
            str(small_demo),
            "--demo-size",
            "64",
            "--methods",
            "robust,icomma",
            "--starts",
            "2",
            "--paper-starts",
            "1",
            "--paper-max-iterations",
            "3",
            "--render-repeats",
            "1",
            "--threads",
            "1",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    runs = {(r["method"], r["start"]) for r in res["records"]}
    assert runs == {(m, k) for m, n in (("robust", 2), ("icomma", 1)) for k in range(n)}
    for r in res["records"]:
        assert set(r["stage_seconds"]) == set(STAGES) == set(r["stage_cpu_seconds"])
        assert r["wall_s"] > 0 and r["rot_err_deg"] is not None and r["trans_err"] is not None
        assert r["status"] in ("ok", "uncertain", "failed") and r["error"] is None
        c2w = np.asarray(r["c2w"])
        assert c2w.shape == (4, 4) and np.allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3))
        assert "render_path" not in r
    icomma = [r for r in res["records"] if r["method"] == "icomma"]
    assert all(r["iterations"] <= 3 for r in icomma)
    by_what = {q["what"]: q for q in res["ratios"]}
    assert set(by_what) == {"paper / default"} and by_what["paper / default"]["paired_n"] == 1
    assert set(res["render_timings"]["demo"]) >= {
        "prepared/fwd",
        "kernel/fwd",
        "prepared/fwd+bwd",
        "kernel/fwd+bwd",
    }
    assert res["machine"]["torch_threads"] == 1 and len(res["load_before"]) == 3
    md = (out / "results.md").read_text()
    assert "Breakdown by stage (CPU seconds" in md and "paper / default" in md
    assert md in capsys.readouterr().out


def test_a_record_is_the_pose_localize_gives_from_the_same_start(small_demo, tmp_path):
    """bench_localize localizes as the library's one-off ``localize()`` does (no monkeypatching).

    The same start, seed, cameras, background and training side give the same pose, bit for bit.
    """
    from icomma_plugin.localize import RobustConfig, localize
    from icomma_plugin.matchers import make_matcher
    from tools.bench_localize import build_parser, load_scene, main, sample_starts

    out = tmp_path / "bench"
    argv = ["--scenes", "demo", "--demo-path", str(small_demo), "--demo-size", "64",
            "--methods", "robust", "--starts", "1", "--threads", "1", "--out", str(out)]
    assert main(argv) == 0
    rec = json.loads((out / "results.json").read_text())["records"][0]
    args = build_parser().parse_args(argv)
    scene = load_scene("demo", args)
    st = sample_starts(scene, 1, args.seed, args.rot, args.trans)[0]
    assert rec["seed"] == list(st.seed) and rec["init_rot_err_deg"] == pytest.approx(st.rot_deg)
    torch.manual_seed(int(np.random.SeedSequence(list(st.seed)).generate_state(1)[0]))
    threads_before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        res = localize(scene.model, st.query.query, matcher=make_matcher(args.matcher),
                       config=RobustConfig(), init_c2w=st.init_c2w, gt_c2w=st.query.gt_c2w,
                       cameras=scene.cameras_c2w, background=scene.bg,
                       model_side=scene.model_side, cache_dir=False)
    finally:
        torch.set_num_threads(threads_before)
    assert np.array_equal(np.asarray(rec["c2w"]), res.c2w)
    assert rec["status"] == res.verdict.status and rec["iterations"] == res.iterations


def test_bad_input_is_one_line(tmp_path, capsys):
    from tools.bench_localize import main

    assert main(["--scenes", "lego200", "--model", str(tmp_path / "missing"), "--quick"]) == 2
    assert "error: --model: model folder not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--scenes", "mars"])
    assert main(["--matcher-set", "max_keypoint=5", "--quick"]) == 2
    assert "error: --matcher-set:" in capsys.readouterr().err
    assert main(["--matcher-set", "max_keypoints", "--quick"]) == 2
    assert "expected key=value" in capsys.readouterr().err


def test_cpu_stages_add_up_and_a_raising_run_is_recorded(small_demo, tmp_path, monkeypatch):
    from icomma_plugin.localization.localizer import Localizer
    from tools.bench_localize import STAGES, main

    real = Localizer.localize

    def flaky(self, *a, **kw):  # the paper's method raises (as a matcher check can mid-run)
        if type(self.method).__name__ == "LocalizerConfig":
            raise ValueError("image0 must hold values in [0, 1]")
        return real(self, *a, **kw)

    monkeypatch.setattr(Localizer, "localize", flaky)
    out = tmp_path / "bench"
    rc = main(["--scenes", "demo", "--demo-path", str(small_demo), "--demo-size", "64",
               "--starts", "1", "--paper-starts", "1", "--threads", "1", "--out", str(out)])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    robust, paper = (next(r for r in res["records"] if r["method"] == m)
                     for m in ("robust", "icomma"))
    assert paper["error"] == "ValueError: image0 must hold values in [0, 1]"
    assert not paper["success"]
    assert robust["error"] is None
    cpu = robust["stage_cpu_seconds"]
    kinds = sum(cpu[k] for k in STAGES[:-2])
    assert cpu["render"] > 0 and cpu["matcher"] > 0
    assert kinds <= cpu["total"] * 1.001 + 1e-3  # nested blocks are not counted twice
    rows = {r["method"]: r for r in res["rows"]}
    assert rows["icomma"]["errors"] == 1 and rows["icomma"]["success"] == 0.0
    assert rows["icomma"]["wall_s"] is None and rows["robust"]["errors"] == 0


def test_markdown_rows_match_the_header():
    from tools.bench_localize import STAGES, markdown

    row = {"scene": "demo", "method": "robust", "n": 4, "errors": 1,
           "wall_s": 2.5, "cpu_s": 1.5, "rot_err_deg": 0.01, "trans_err": 0.001,
           "success": 0.75, "ok": 0.5, "iterations": 7.0,
           "stages": {k: 0.1 for k in STAGES}, "stages_cpu": {k: 0.2 for k in STAGES}}
    md = markdown({"machine": {"torch_threads": 1, "cores": 2, "cpu": "x", "torch": "t",
                               "commit": None},
                   "args": {"rot": [20, 40], "trans": [0, 0.2], "seed": 1}, "load_before": None,
                   "load_after": None, "rows": [row], "blocks": {}, "ratios": [],
                   "render_timings": {}})
    lines = md.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("| scene | method"))
    header = [c.strip() for c in lines[i].strip("|").split("|")]
    cells = [c.strip() for c in lines[i + 2].strip("|").split("|")]
    assert len(header) == len(cells)
    got = dict(zip(header, cells))
    assert (got["n"], got["errors"], got["wall s"], got["CPU s"]) == ("4", "1", "2.50", "1.50")
    assert (got["success"], got["verdict ok"], got["iterations"]) == ("75 %", "50 %", "7")
    assert (got["final rot deg"], got["final trans"]) == ("0.010", "0.0010")
    assert "OMP_WAIT_POLICY" not in lines[0]
    # the thread environment the timings depend on is in the header line
    md = markdown({"machine": {"torch_threads": 2, "cores": 2, "cpu": "x", "torch": "t",
                               "commit": None, "thread_env": {"OMP_WAIT_POLICY": "PASSIVE"}},
                   "args": {"rot": [20, 40], "trans": [0, 0.2], "seed": 1}, "load_before": None,
                   "load_after": None, "rows": [row], "blocks": {}, "ratios": [],
                   "render_timings": {}})
    assert ", OMP_WAIT_POLICY=PASSIVE;" in md.splitlines()[0]


def test_the_reference_run_gets_every_option_that_shapes_the_runs(tmp_path):
    """--compare-with runs the other checkout on the same scenes, starts and method settings."""
    from pathlib import Path

    from tools.bench_localize import _NOT_FORWARDED, build_parser, reference_command

    assert set(_NOT_FORWARDED) == {"help", "out", "compare_with", "quick", "render_repeats",
                                   "set", "matcher_set", "profile"}  # its profile: not asked
    parser = build_parser()
    argv = ["--scenes", "lego400", "--methods", "robust", "--starts", "4", "--paper-starts", "2",
            "--rot", "40,60", "--trans", "0,0.1", "--seed", "7", "--queries", "3",
            "--model", "/m", "--dataset", "/d", "--demo-path", "/p", "--demo-size", "64",
            "--matcher", "sift", "--backend", "torch", "--paper-max-iterations", "9",
            "--threads", "1", "--lod", "off", "--work-side", "800", "--query-scale", "2",
            "--render-repeats", "3", "--compare-with", "/ref", "--out", "/o",
            "--set", "refine.hessian_reduced=false", "--matcher-set", "max_keypoints=256"]
    args = parser.parse_args(argv)
    cmd = reference_command(args, Path("/ref/tools/bench_localize.py"), tmp_path)
    assert cmd[2:4] == ["--out", str(tmp_path)]
    ref = parser.parse_args(cmd[4:])
    for name, value in vars(args).items():
        if name not in _NOT_FORWARDED:
            assert getattr(ref, name) == value, name
    assert ref.compare_with is None and ref.render_repeats == 0
    assert ref.set is None and ref.matcher_set is None  # the reference runs its own defaults
    # options left at their defaults are not passed (an older checkout may not know them)
    plain = reference_command(parser.parse_args(["--starts", "2"]), Path("s"), tmp_path)
    for option in ("--lod", "--work-side", "--query-scale", "--dataset", "--demo-size"):
        assert option not in plain
    assert "--starts" in plain and "--rot" in plain


def test_set_overrides_the_default_method_and_names_a_bad_key():
    from tools.bench_localize import build_parser, method_config

    parser = build_parser()
    args = parser.parse_args(["--work-side", "400", "--set", "refine.hessian_scale=0.5",
                              "--set", "refine.iterations=[2]", "--set", "refine_reduced=true"])
    cfg = method_config("robust", args)
    assert cfg.work_side == 400 and cfg.refine.hessian_scale == 0.5
    assert cfg.refine.iterations == (2,) and cfg.refine_reduced is True
    for bad, words in (("refine.nope=1", "no key 'refine.nope'"), ("refine", "expected key=value"),
                       ("refine.scales=[2, 9]", "scales")):
        with pytest.raises(ValueError, match=words):
            method_config("robust", parser.parse_args(["--set", bad]))


def test_profile_writes_the_operator_table_and_is_not_timed(small_demo, tmp_path):
    from tools.bench_localize import main

    out = tmp_path / "bench"
    assert main(["--scenes", "demo", "--demo-path", str(small_demo), "--demo-size", "64",
                 "--methods", "robust", "--starts", "1", "--threads", "1", "--profile",
                 "--out", str(out)]) == 0
    assert len(json.loads((out / "results.json").read_text())["records"]) == 1
    text = (out / "profile_demo_robust.txt").read_text()
    calls = int(text.split("aten operator calls: ")[1].split()[0])
    assert calls > 100 and "grp::rasterize_forward" in text and "by self CPU time" in text
