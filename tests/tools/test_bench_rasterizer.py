"""tools/bench_rasterizer.py on tiny scenes.

Every mode is timed, the reference is skipped above its limits, the table and the JSON agree.
"""

from __future__ import annotations

import json


def test_tiny_table_and_json(tmp_path, capsys):
    from tools.bench_rasterizer import MODES, main

    out = tmp_path / "raster.json"
    rc = main(["--backends", "cpu,reference", "--sizes", "300", "--resolutions", "32",
               "--repeats", "1", "--threads", "1", "--reference-max-gaussians", "300",
               "--reference-max-pixels", str(32 * 32), "--json", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert data["threads"] == 1 and data["repeats"] == 1
    # the asked-for scene, and the reference's target size (--reference-max-gaussians at 200 px)
    small, target = data["results"]
    assert [(r["gaussians"], r["resolution"]) for r in (small, target)] == [(300, 32), (300, 200)]
    for mode in MODES:
        assert small["ms"][f"cpu/{mode}"] > 0 and small["ms"][f"reference/{mode}"] > 0
        assert target["ms"][f"cpu/{mode}"] > 0
        assert target["ms"][f"reference/{mode}"] is None  # 200x200 is above --reference-max-pixels
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")]
    assert len(table) == 4  # header, rule, two scenes
    assert "—" in table[3]
    assert len(table[0].split("|")) == len(table[2].split("|"))


def test_checkouts_compared_interleaved(tmp_path, capsys):
    """--checkouts with this checkout twice: both workers time every mode, same bits."""
    from tests.helpers.paths import REPO
    from tools.bench_rasterizer import main

    out = tmp_path / "cmp.json"
    rc = main(["--checkouts", f"{REPO},{REPO}", "--sizes", "300", "--resolutions", "32",
               "--repeats", "2", "--thread-counts", "1", "--modes", "fwd,fwd+pose-only",
               "--json", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert [(r["mode"], r["threads"]) for r in data["results"]] == [("fwd", 1),
                                                                   ("fwd+pose-only", 1)]
    for r in data["results"]:
        assert len(r["ms"]) == 2 and min(r["ms"]) > 0 and min(r["cpu_ms"]) > 0
        assert r["same_images"] == r["same_camera_grad"] == r["same_state"] == [True, True]
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("|")]
    assert len(table) == 4 and "yes / yes / yes" in table[2]
