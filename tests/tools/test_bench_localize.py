"""tools/bench_localize.py on a small demo scene.

It runs both methods and both render paths, writes its JSON and markdown, the two render paths
end on the same poses, bad input is one line.
"""

from __future__ import annotations

import json

import pytest


def test_both_methods_and_render_paths(small_demo, tmp_path, capsys):
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
            "--render-path",
            "both",
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
    runs = {(r["method"], r["render_path"], r["start"]) for r in res["records"]}
    assert runs == {
        (m, p, k)
        for m, n in (("robust", 2), ("icomma", 1))
        for p in ("plain", "prepared")
        for k in range(n)
    }
    for r in res["records"]:
        assert set(r["stage_seconds"]) == set(STAGES) == set(r["stage_cpu_seconds"])
        assert r["wall_s"] > 0 and r["final_rot_deg"] is not None
    icomma = [r for r in res["records"] if r["method"] == "icomma"]
    assert all(r["iterations"] <= 3 for r in icomma)
    # The prepared render path renders the same bits: every localization ends on the same pose.
    by_path = {q["what"]: q for q in res["ratios"]}
    for method in ("robust", "icomma"):
        assert by_path[f"plain / prepared ({method})"]["max_pose_diff"] == 0.0
    assert "paper / default (prepared)" in by_path
    assert set(res["render_timings"]["demo"]) >= {
        "plain/fwd",
        "prepared/fwd",
        "plain/fwd+bwd",
        "prepared/fwd+bwd",
    }
    assert res["machine"]["torch_threads"] == 1 and len(res["load_before"]) == 3
    md = (out / "results.md").read_text()
    assert "Breakdown by stage (CPU seconds" in md and "plain / prepared (robust)" in md
    assert md in capsys.readouterr().out


def test_bad_input_is_one_line(tmp_path, capsys):
    from tools.bench_localize import main

    assert main(["--scenes", "lego200", "--model", str(tmp_path / "missing"), "--quick"]) == 2
    assert "error: --model: model folder not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--scenes", "mars"])


def test_cpu_stages_add_up_and_a_raising_run_is_recorded(small_demo, tmp_path, monkeypatch):
    import icomma_plugin.localize as loc
    from tools.bench_localize import STAGES, main

    real = loc.localize

    def flaky(*a, **kw):  # the paper's method raises (as a matcher check can mid-run)
        if type(a[5]).__name__ == "LocalizerConfig":
            raise ValueError("image0 must hold values in [0, 1]")
        return real(*a, **kw)

    monkeypatch.setattr(loc, "localize", flaky)
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

    row = {"scene": "demo", "method": "robust", "render_path": "prepared", "n": 4, "errors": 1,
           "wall_s": 2.5, "cpu_s": 1.5, "final_rot_deg": 0.01, "final_trans": 0.001,
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
