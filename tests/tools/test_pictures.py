"""Pictures where a person looks.

The optimisation as MP4, the contact sheet of a batch (framed by verdict colour), the
trajectory plot, and the benchmark curves beside the paper's numbers.
"""

from __future__ import annotations


import numpy as np
import pytest
from PIL import Image

from icomma_plugin import pictures as viz
from icomma_plugin.io.video import video_info
from tests.helpers.tools import compose, localize_tool

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def test_optimisation_as_mp4(tmp_path):
    from icomma_plugin.app.demo_scene import build_demo_scene

    scene = build_demo_scene(tmp_path / "demo", seed=0, width=64, height=64)
    cfg = compose(
        [
            f"data.path={scene.path}",
            "data.width=64",
            "data.height=64",
            "optimizer=icomma",
            "optimizer.max_iterations=4",
            "output.progress=false",
            "output.mp4=true",
            "output.gif_every=1",
            "output.overlays=false",
            "output.match_lines=false",
            "output.convergence_plot=false",
        ]
    )
    res = localize_tool().run(cfg, tmp_path / "out")
    assert "optimisation.mp4" in res["files"] and "optimisation.gif" not in res["files"]
    w, h, n, _ = video_info(tmp_path / "out" / "optimisation.mp4")
    assert n == res["iterations"] == 4 and h == 64 and w >= 4 * 64


def _rows(tmp_path):
    rows = []
    for i, st in enumerate(["ok", "uncertain", "failed", "ok", "failed"]):
        r = {
            "index": i,
            "name": f"IMG_{i}.jpg",
            "status": st,
            "rot_err_deg": 0.1 * i if st != "failed" else None,
            "trans_err_rel": 0.001 if st != "failed" else None,
        }
        if i < 3:
            (tmp_path / "thumbs").mkdir(exist_ok=True)
            Image.fromarray(np.full((30, 40, 3), 200, np.uint8)).save(
                tmp_path / "thumbs" / f"{i}.png"
            )
            r["thumb"] = f"thumbs/{i}.png"
        rows.append(r)
    return rows


def test_contact_sheet_frames_each_photo_in_its_verdict_colour(tmp_path):
    rows = _rows(tmp_path)
    p = viz.contact_sheet(tmp_path / "sheet.png", rows, tmp_path, columns=3, cell=64, border=4)
    a = np.asarray(Image.open(p).convert("RGB"))
    pitch, header = 64 + 8, 24
    assert a.shape == (header + 2 * pitch, 3 * pitch, 3)
    for i, r in enumerate(rows):
        y0, x0 = header + (i // 3) * pitch, (i % 3) * pitch
        assert tuple(a[y0 + 1, x0 + pitch // 2]) == viz.VERDICT_COLOURS[r["status"]]  # the frame
    # a thumbnail fills its cell (scaled up to the cell), a photo without one is grey
    assert tuple(a[header + 4 + 32, 4 + 32]) == (200, 200, 200)
    assert tuple(a[header + pitch + 4 + 32, 4 + 32]) == (70, 70, 70)
    with pytest.raises(ValueError, match="rows is empty"):
        viz.contact_sheet(tmp_path / "x.png", [], tmp_path)


def test_trajectory_plot(tmp_path):
    from icomma_plugin.pose.convert import look_at_c2w

    cams = [
        look_at_c2w(np.array([4 * np.cos(a), 4 * np.sin(a), 2.0]), np.zeros(3))
        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ]
    est = [
        look_at_c2w(np.array([3 * np.cos(a), 3 * np.sin(a), 1.5]), np.zeros(3))
        for a in np.linspace(0, 1, 5)
    ]
    p = viz.plot_trajectory(
        tmp_path / "t.png",
        est[:2] + [None] + est[3:],
        cams,
        est,
        ["ok", "uncertain", "failed", "ok", "ok"],
        title="t",
    )
    with Image.open(p) as im:
        assert im.size[0] > 600 and im.size[1] > 300


def test_curves_beside_the_paper(tmp_path):
    from icomma_plugin.benchmark.paper import PaperValue

    summary = {
        "protocol": "curves_rotation",
        "cells": [
            {
                "interval": "r0-20",
                "method": "icomma",
                "curves": {"1deg_0.01": [0, 0.5, 0.8], "5deg_0.05": [0, 0.9, 1]},
            },
            {"interval": "r20-40", "method": "icomma", "curves": {"1deg_0.01": [0, 0.2, 0.4]}},
            {"interval": "r20-40", "method": "essential", "auc5": 0.3},  # no curves: skipped
        ],
    }
    paper = {
        ("r0-20", "icomma", "success_1deg_0.01"): PaperValue(0.85, "Fig. 4"),
        ("curves_rotation", "r20-40", "icomma", "success_1deg_0.01"): 0.6,
        ("r0-20", "icomma", "success_5deg_0.05"): PaperValue(None, "Fig. 4", "n/a"),
    }
    assert viz.plots._paper_number(paper, "r0-20", "icomma", "success_1deg_0.01") == 0.85
    assert (
        viz.plots._paper_number(paper, "r20-40", "icomma", "success_1deg_0.01") == 0.6
    )  # protocol-keyed
    assert viz.plots._paper_number(paper, "r0-20", "icomma", "success_5deg_0.05") is None
    assert viz.plots._paper_number(lambda iv, m, k: PaperValue(0.5, "x"), "a", "b", "c") == 0.5
    p = viz.plot_curves_vs_paper(tmp_path / "c.png", summary, paper)
    with Image.open(p) as im:
        assert im.size[0] > 500
    p = viz.plot_curves_vs_paper(tmp_path / "c2.png", summary)  # no paper numbers at all
    assert p.is_file()
    with pytest.raises(ValueError, match="no cells with 'curves'"):
        viz.plot_curves_vs_paper(tmp_path / "x.png", {"cells": [{"interval": "a", "method": "b"}]})
