"""One row schema for result.json, a batch's poses.json rows and the benchmark's records.

They name the same things the same way (docs/CONTRACTS.md, "Result rows").
"""
from __future__ import annotations

import numpy as np
import pytest

from icomma_plugin.app.batch.planning import PhotoTask
from icomma_plugin.app.batch.records import failure_row, result_row
from icomma_plugin.app.ledger import CSV_COLUMNS
from icomma_plugin.app.output import result_document
from icomma_plugin.app.problem import Problem
from icomma_plugin.benchmark.protocols import ProtocolSpec
from icomma_plugin.benchmark.runner import _error_record, _localizer_record
from icomma_plugin.camera import Intrinsics
from icomma_plugin.localization.candidates import CandidateConfig
from icomma_plugin.localization.localizer import Localizer
from icomma_plugin.localization.robust import RobustConfig
from icomma_plugin.localization.types import ROW_FIELDS, Query, blank_row
from icomma_plugin.matchers import make_matcher
from icomma_plugin.pose.convert import perturb_pose


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    from icomma_plugin.app.demo_scene import build_demo_scene

    scene = build_demo_scene(tmp_path_factory.mktemp("demo") / "scene", seed=0, width=64,
                             height=64)
    loc = Localizer(scene.load_model(), make_matcher("xfeat"),
                    RobustConfig(candidates=CandidateConfig(num_sampled=0)), cache_dir=False)
    q = Query(scene.load_query(), scene.intrinsics, name="query")
    init = perturb_pose(scene.gt_c2w, 10.0, 0.05, 0, pivot=scene.scene_centre)
    return scene, q, loc.localize(q, init, scene.gt_c2w)


def test_every_row_has_the_fields_with_the_same_values(result):
    scene, q, res = result
    problem = Problem(model=None, query=q, init_c2w=res.init_c2w, gt_c2w=scene.gt_c2w,
                      bg=None, scene_scale=2.0)
    doc = result_document(problem, res, backend="cpu", config={}, seconds_total=1.0)
    task = PhotoTask(0, "query", "query.png", intrinsics=q.intrinsics, init_c2w=res.init_c2w,
                     gt_c2w=scene.gt_c2w)
    row = result_row(task, res, 2.0, 1.5)
    spec = ProtocolSpec.from_dict({"name": "t", "kind": "time", "intervals": [
        {"label": "r", "rot_deg": [1, 2], "trans": [0, 0]}], "methods": ["robust"],
        "thresholds": [[5.0, 0.05]]})
    record = _localizer_record(res, 2.0, spec)
    for r in (doc, row, record):
        assert set(ROW_FIELDS) <= set(r), set(ROW_FIELDS) - set(r)
        assert r["status"] == res.verdict.status and r["rot_err_deg"] == res.rot_err_deg
        assert np.allclose(r["c2w"], res.c2w) and r["trans_err_rel"] == res.trans_err / 2.0
        assert r["inliers"] == res.inliers and r["intrinsics"] == q.intrinsics.to_json()
    assert row["seconds"] == 1.5 and row["localize_seconds"] == res.seconds
    # rows without a localization still have every field
    for r in (failure_row(task, "bad input", "bad"), blank_row(), _error_record(ValueError("x"))):
        assert set(ROW_FIELDS) <= set(r)
    assert set(CSV_COLUMNS) - {"index", "relocalized", "camera_focal_scale"} <= set(ROW_FIELDS)


def test_an_estimated_focal_length_is_what_result_json_records(result):
    """With ``refine.focal`` the camera entry holds the estimated focal lengths, not the given."""
    import dataclasses

    scene, q, res = result
    problem = Problem(model=None, query=q, init_c2w=res.init_c2w, gt_c2w=scene.gt_c2w,
                      bg=None, scene_scale=2.0)
    i = q.intrinsics
    est = dataclasses.replace(res, intrinsics=dataclasses.replace(i, fx=i.fx * 1.03,
                                                                 fy=i.fy * 1.03))
    doc = result_document(problem, est, backend="cpu", config={}, seconds_total=1.0)
    assert doc["camera_entry"]["fx"] == pytest.approx(i.fx * 1.03)
    assert doc["intrinsics"]["fx"] == pytest.approx(i.fx * 1.03)


def test_a_batch_row_holds_the_estimated_focal_length_at_the_photos_size(result):
    """A batch row's intrinsics are at the photo file's size, with the focal length estimated.

    Exports (COLMAP, nerfstudio) read them: the pose holds with the estimated focal length.
    """
    import dataclasses

    scene, q, res = result
    photo = q.intrinsics.scaled(2.0)  # the file was resized to the query's size
    task = PhotoTask(0, "query", "query.png", intrinsics=photo)
    assert result_row(task, res, 2.0, 1.0)["intrinsics"] == photo.to_json()
    est = dataclasses.replace(res, details={**res.details, "focal_scale": 1.03})
    row = result_row(task, est, 2.0, 1.0)
    assert row["intrinsics"] == photo.with_focal_scale(1.03).to_json()
    assert row["intrinsics"]["width"] == photo.width


def test_intrinsics_have_one_encoding():
    intr = Intrinsics(64, 48, 50.0, 51.0)
    j = intr.to_json()
    assert j == {"width": 64, "height": 48, "fx": 50.0, "fy": 51.0, "cx": 31.5, "cy": 23.5}
    back = Intrinsics.from_json(j)
    assert (back.cx_px, back.cy_px, back.fx) == (31.5, 23.5, 50.0)
    longer = intr.with_focal_scale(1.1)  # the focal lengths only: the same image's pixels
    assert (longer.fx, longer.fy) == pytest.approx((55.0, 56.1))
    assert (longer.cx_px, longer.cy_px, longer.width, longer.height) == (31.5, 23.5, 64, 48)
    assert intr.with_focal_scale(1.0) is intr
    with pytest.raises(ValueError, match="lacks"):
        Intrinsics.from_json({"width": 1})
