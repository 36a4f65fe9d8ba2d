"""Benchmark scenes: which views are queries and which cameras may be candidate views."""
from __future__ import annotations

import pytest

from icomma_plugin.benchmark import load_model_folder_scene


def test_val_split_queries_and_candidates_from_the_fitted_cameras(lego_root, tmp_path):
    """Lego's val views as queries (held out from the benchmark's test views).

    The candidate views are the train cameras only, never a camera of a held-out split.
    """
    from icomma_plugin.app.demo_scene import blob_model
    from icomma_plugin.io.cameras_json import CameraEntry
    from icomma_plugin.io.datasets import read_dataset
    from icomma_plugin.io.model_folder import write_model_folder

    sd = read_dataset(lego_root, white_background=True, test_split="val")
    views = sd.train + sd.test + read_dataset(lego_root, white_background=True).test
    cams = [CameraEntry(id=i, img_name=v.name, width=v.width, height=v.height, c2w=v.c2w,
                        fx=v.intrinsics.fx, fy=v.intrinsics.fy) for i, v in enumerate(views)]
    folder = tmp_path / "model"
    write_model_folder(folder, blob_model(50), {"source_path": str(lego_root), "resolution": 8,
                                                "white_background": True}, cams, 7000)
    scene = load_model_folder_scene(folder, num_queries=3, split="val")
    assert scene.info["split"] == "val" and len(scene.queries) == 3
    assert len(scene.cameras_c2w) == len(sd.train) == 100
    # the Localizer gets the cameras as a user's would: with their names and intrinsics
    assert [c.img_name for c in scene.cameras] == [v.name for v in sd.train]
    assert all((c.c2w == T).all() for c, T in zip(scene.cameras, scene.cameras_c2w))
    from icomma_plugin.localize import LocalizerConfig
    loc = scene.localizer(None, LocalizerConfig())
    assert loc.camera_names == [v.name for v in sd.train]
    assert all(i is not None and i.width == 400 for i in loc.camera_intrinsics)
    test_scene = load_model_folder_scene(folder, num_queries=3, split="test")
    assert len(test_scene.cameras_c2w) == 100 and test_scene.model_side == 50
    with pytest.raises(ValueError, match="split must be"):
        load_model_folder_scene(folder, num_queries=3, split="holdout")


def test_resume_reuses_finished_runs_and_retries_the_ones_that_raised(tmp_path):
    import json

    from icomma_plugin.benchmark.results import SCHEMA, load_done

    p = tmp_path / "results.json"
    records = [
        {"key": "a", "rot_err_deg": 0.1},
        {"key": "b", "error": {"type": "ValueError", "message": "x"}},
    ]
    p.write_text(json.dumps({"schema": SCHEMA, "records": records}))
    assert set(load_done(p)) == {"a"}
    assert set(load_done(p, retry_errors=False)) == {"a", "b"}
