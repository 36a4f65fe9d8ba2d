"""The Localizer: what it builds once and shares, the candidate index on disk, own cameras."""
from __future__ import annotations

import dataclasses
import multiprocessing
import time

import numpy as np
import pytest
import torch

from icomma_plugin.localization.candidate_cache import CandidateCache, model_fingerprint
from icomma_plugin.localization.candidates import CandidateConfig, CandidateIndex
from icomma_plugin.localization.localizer import Localizer
from icomma_plugin.localization.robust import RobustConfig
from icomma_plugin.localization.types import Query
from icomma_plugin.pose.convert import perturb_pose

#: A small candidate search: the demo's ring cameras and 4 sampled views.
SMALL = RobustConfig(candidates=CandidateConfig(num_sampled=4))


def _query(scene):
    return Query(scene.load_query(), scene.intrinsics, name="query")


def test_the_index_is_built_once_and_shared_by_queries_and_cameras(demo, xfeat, tmp_path):
    scene, model, cams = demo
    loc = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    a = loc.localize(_query(scene), gt_c2w=scene.gt_c2w)
    # another photo of the same size whose focal length differs by 5 % (a per-image camera)
    intr = dataclasses.replace(scene.intrinsics, fx=scene.intrinsics.fx * 1.05,
                               fy=scene.intrinsics.fy * 1.05)
    b = loc.localize(Query(scene.load_query(), intr, name="zoomed"))
    assert loc.candidate_builds == 1
    assert a.verdict.status == "ok" and a.rot_err_deg < 0.1, a.verdict.reason
    assert b.stage_seconds["candidates"] < a.stage_seconds["candidates"]
    assert len(list((tmp_path / "candidates").glob("*.pt"))) == 1


def test_a_second_localizer_loads_the_index_from_disk(demo, xfeat, tmp_path):
    scene, model, cams = demo
    first = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    built = first.candidate_index(scene.intrinsics, SMALL.candidates)
    second = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    loaded = second.candidate_index(scene.intrinsics, SMALL.candidates)
    assert (first.candidate_builds, second.candidate_builds) == (1, 0)
    assert loaded.source == built.source and loaded.num_cameras == built.num_cameras
    assert all(np.array_equal(x, y) for x, y in zip(loaded.c2w, built.c2w))
    for f, g in zip(built.features, loaded.features):
        assert (f is None) == (g is None)
        if f is not None:
            assert torch.equal(f.kpts, g.kpts) and torch.equal(f.desc, g.desc)
    res = second.localize(_query(scene))
    assert res.verdict.status == "ok" and second.candidate_builds == 0


def test_the_index_is_rebuilt_when_a_key_changes(demo, xfeat, tmp_path):
    scene, model, cams = demo
    Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path).candidate_index(
        scene.intrinsics, SMALL.candidates)
    more = CandidateConfig(num_sampled=6)
    moved = model.to(dtype=torch.float32)
    moved.means = moved.means.clone()
    moved.means[0, 0] += 1e-3  # one Gaussian moved by a hair: another model
    assert model_fingerprint(moved) != model_fingerprint(model)
    cases = [
        (model, cams, more),  # another candidate search
        (moved, cams, SMALL.candidates),  # another model
        (model, cams[:-1], SMALL.candidates),  # other cameras
    ]
    for m, c, cfg in cases:
        loc = Localizer(m, xfeat, SMALL, cameras=c, cache_dir=tmp_path)
        loc.candidate_index(scene.intrinsics, cfg)
        assert loc.candidate_builds == 1
    assert len(list((tmp_path / "candidates").glob("*.pt"))) == 4


def test_the_cache_goes_where_it_is_told_never_into_the_model_folder(demo, xfeat, tmp_path,
                                                                    monkeypatch):
    scene, model, cams = demo
    monkeypatch.setenv("ICOMMA_CACHE_DIR", str(tmp_path / "env"))
    before = sorted(p.name for p in scene.path.rglob("*"))
    Localizer(model, xfeat, SMALL, cameras=cams).candidate_index(scene.intrinsics,
                                                                 SMALL.candidates)
    assert len(list((tmp_path / "env" / "candidates").glob("*.pt"))) == 1
    assert sorted(p.name for p in scene.path.rglob("*")) == before
    none = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=False)
    none.candidate_index(scene.intrinsics, SMALL.candidates)
    assert none.cache is None and len(list((tmp_path / "env" / "candidates").glob("*.pt"))) == 1


def test_a_damaged_cache_file_is_rebuilt(demo, xfeat, tmp_path, caplog):
    scene, model, cams = demo
    loc = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    loc.candidate_index(scene.intrinsics, SMALL.candidates)
    (f,) = (tmp_path / "candidates").glob("*.pt")
    f.write_bytes(b"not a torch file")
    again = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    again.candidate_index(scene.intrinsics, SMALL.candidates)
    assert again.candidate_builds == 1 and "unreadable" in caplog.text
    assert CandidateCache(tmp_path / "candidates").load(f.stem) is not None


def _slow_build(directory, marker_dir, fields):
    """A process asking the cache for an index whose build takes a while (and leaves a mark)."""
    import os
    from pathlib import Path

    def build():
        Path(marker_dir, f"built-{os.getpid()}").touch()
        time.sleep(1.0)
        return CandidateIndex([np.eye(4)], ["camera_0"], scene_intrinsics(), [None], 1)

    index, _ = CandidateCache(directory).get_or_build(fields, build)
    return index.source


def scene_intrinsics():
    from icomma_plugin.camera import Intrinsics

    return Intrinsics(32, 24, 30.0, 30.0)


def test_two_processes_building_one_index_build_it_once(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    fields = {"format": 1, "model": "test", "n": 1}
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        out = pool.starmap(_slow_build, [(tmp_path / "cache", marks, fields)] * 2)
    assert out == [["camera_0"], ["camera_0"]]
    assert len(list(marks.iterdir())) == 1  # the second process waited and loaded
    assert len(list((tmp_path / "cache").glob("*.pt"))) == 1


def test_a_query_at_a_model_camera_does_not_find_that_camera(demo, xfeat, tmp_path):
    """The own-camera rule: a camera at the query's true pose is never a candidate."""
    scene, model, cams = demo
    own = cams[3]
    loc = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    from icomma_plugin.render import render

    with torch.no_grad():
        photo = render(model, scene.intrinsics, torch.as_tensor(np.linalg.inv(own.c2w)).float(),
                       torch.zeros(3)).color.clamp(0, 1)
    query = Query(photo, scene.intrinsics, name=own.img_name)
    assert loc.own_cameras(own.c2w) == [own.img_name]
    assert loc.own_cameras(perturb_pose(own.c2w, 0.01, 0.0, 0, pivot="camera")) == []
    res = loc.localize(query, gt_c2w=own.c2w)
    starts = [h["start"] for h in res.details["hypotheses"]]
    assert own.img_name not in starts and res.verdict.status == "ok", (starts, res.verdict)
    assert res.rot_err_deg < 1.0  # found from the other views (a 96 px ring view: ~0.4 deg)


def test_preconditions_are_checked_once_when_built(demo, xfeat):
    from icomma_plugin.localization.icomma import LocalizerConfig

    scene, model, cams = demo
    with pytest.raises(ValueError, match="needs a matcher"):
        Localizer(model, None)
    with pytest.raises(ValueError, match="backend must be one of"):
        Localizer(model, xfeat, backend="gpu")
    with pytest.raises(ValueError, match="model must be a GaussianModel"):
        Localizer("model.ply", xfeat)
    with pytest.raises(ValueError, match=r"cameras\[0\]"):
        Localizer(model, xfeat, cameras=[np.eye(3)])
    paper = Localizer(model, None, LocalizerConfig(use_matching=False))
    with pytest.raises(ValueError, match="needs a start pose"):
        paper.localize(_query(scene))


def test_a_stored_calibration_of_the_model_is_its_verdict(demo, xfeat, tmp_path):
    """The Localizer uses the model's calibration when its cache folder has one (verdict=auto)."""
    from icomma_plugin.localization.calibration import Calibration, save_calibration
    from icomma_plugin.localization.verify import VerdictConfig

    scene, model, cams = demo
    strict = VerdictConfig(ok_inliers=500, ok_mean_px=0.2)
    save_calibration(Calibration(strict, VerdictConfig()), model, cache_dir=tmp_path)
    loc = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path)
    assert loc.method.verdict == strict
    res = loc.localize(_query(scene), gt_c2w=scene.gt_c2w)
    assert res.rot_err_deg < 0.1 and res.verdict.status == "uncertain"  # right, not ok here
    assert "(< 500)" in res.verdict.reason
    plain = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path, verdict=None)
    assert plain.method.verdict == VerdictConfig()
    assert Localizer(model, xfeat, SMALL, cache_dir=False).method.verdict == VerdictConfig()
    other = Localizer(model, xfeat, SMALL, verdict=tmp_path / "calibration" /
                      next((tmp_path / "calibration").iterdir()).name, cache_dir=False)
    assert other.method.verdict == strict


def test_prepared_features_are_used_and_a_fresh_query_has_none(demo, xfeat, monkeypatch):
    """``prepare`` extracts the query's features once; localizing that query extracts renders.

    A ``fresh()`` copy extracts the query again, and the pose is the same.
    """
    scene, model, cams = demo
    loc = Localizer(model, xfeat, SMALL, cameras=cams)
    start = perturb_pose(scene.gt_c2w, 5.0, 0.02, np.random.default_rng(0))
    calls = []
    extract = type(xfeat).extract

    def counted(self, image):
        calls.append(tuple(image.shape))
        return extract(self, image)

    monkeypatch.setattr(type(xfeat), "extract", counted)
    q = _query(scene)
    assert loc.prepare(q) is q and len(calls) == 1 and len(q.memo) == 1
    a = loc.localize(q, start)
    in_localize = len(calls) - 1
    b = loc.localize(q.fresh(), start)
    assert len(calls) - 1 - in_localize == in_localize + 1  # the fresh copy extracts the query
    assert a.verdict.status == b.verdict.status == "ok"
    assert np.allclose(a.c2w, b.c2w, atol=1e-9)
    with pytest.raises(ValueError, match="query must be a Query"):
        loc.prepare("photo.png")
