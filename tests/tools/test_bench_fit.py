"""tools/bench_fit.py on a tiny fitted capture: two checkouts (this one twice), interleaved."""

from __future__ import annotations

import json

import pytest


def test_steps_timed_in_two_workers(tmp_path, capsys):
    from tests.helpers.paths import REPO
    from tests.icomma_plugin.fit.test_recipe import fit_tiny_capture
    from tools.bench_fit import PARTS
    from tools.bench_fit import main as bench

    model = fit_tiny_capture(tmp_path, 10)
    capsys.readouterr()
    out = tmp_path / "fit_steps.json"
    assert bench(["-m", str(model), "--checkouts", f"{REPO},{REPO}", "--at", "3", "--steps", "2",
                  "--rounds", "2", "--warmup", "1", "--threads", "1", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    (result,) = data["results"]
    assert result["at"] == 3 and len(result["rows"]) == 2
    for row, rounds in zip(result["rows"], result["rounds"]):
        assert len(rounds) == 2 and [r["step"] for r in rounds] == [6, 8]  # warm-up 1, 2 a round
        assert row["ms"] > 0 and row["cpu_ms"] > 0 and row["gaussians"] > 0
        assert row["render"] > 0 and row["backward"] > 0 and set(PARTS) <= set(row)
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")]
    assert len(table) == 4 and table[2].endswith("| 1 | 1 |")  # header, rule, two checkouts
    with pytest.raises(SystemExit, match="--at: 100000 is past the recipe"):
        bench(["-m", str(model), "--at", "100000", "--steps", "1", "--rounds", "1",
               "--threads", "1"])
    with pytest.raises(SystemExit):
        bench(["-m", str(tmp_path / "nowhere")])
    for bad in (",", "x", "-5"):
        with pytest.raises(SystemExit):
            bench(["-m", str(model), "--at", bad])
