"""A model's principal point convention: upstream 3DGS fits every view with the image centre.

A capture whose files give a principal point off the centre (a COLMAP PINHOLE camera after
undistortion, fox's transforms.json) is fitted by upstream 3DGS as if it were centred: its
cameras are field-of-view angles alone. The model explains each photo at its recorded pose
through a centred camera, so the localizer must localize that capture's views through the same
camera to come back to their records (``ModelFolder.principal_point``, ``data.principal_point``).

The photos here are rendered from the demo model through centred cameras (what such a model
gives back at the records), and the COLMAP files say the principal point is 3 px off.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.demo import demo_model, photo

SIZE = 100
SHIFT_PX = (3.0, -2.0)  # the files' principal point from the image centre (COLMAP pixels)

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The demo model folder (upstream's: no metrics.json) and a COLMAP capture of 3 photos."""
    from icomma_plugin.camera import Intrinsics
    from icomma_plugin.pose.convert import look_at_c2w
    from tests.helpers.colmap import write_colmap_dataset

    root = tmp_path_factory.mktemp("pp")
    s, model = demo_model(root / "model", SIZE)
    f0 = float(s.intrinsics.fx)
    photos = []
    for i in range(3):
        az = 0.4 + 1.1 * i
        c2w = look_at_c2w(np.array([3.8 * math.cos(az), 3.8 * math.sin(az), 2.0]),
                          np.array([0.0, 0.0, 0.4]))
        rgb = photo(model, Intrinsics(SIZE, SIZE, f0, f0), c2w)
        photos.append((f"v{i}.png", rgb, c2w, f0, f0,
                       SIZE / 2 + SHIFT_PX[0], SIZE / 2 + SHIFT_PX[1]))
    write_colmap_dataset(root / "dataset", photos)
    return {"model": s.path, "dataset": root / "dataset", "c2w": {p[0]: p[2] for p in photos},
            "f0": f0}


def _plan(capture, principal_point):
    from icomma_plugin.app.batch import plan_batch

    data = {"kind": "model_folder", "model_path": str(capture["model"]),
            "queries": str(capture["dataset"]), "init": {"rot_deg": 5.0, "seed": 1}}
    if principal_point is not None:
        data["principal_point"] = principal_point
    return plan_batch(data)


def test_an_upstream_model_folder_takes_its_views_principal_point_at_the_centre(capture):
    from icomma_plugin.app.problem import open_model_folder

    mf, _ = open_model_folder({"model_path": str(capture["model"])})
    assert mf.principal_point == "centre"  # no metrics.json, no cfg_args key: upstream's
    plan, _ = _plan(capture, None)
    assert all(t.intrinsics.cx is None and t.intrinsics.cy is None for t in plan.tasks)
    plan, _ = _plan(capture, "dataset")
    np.testing.assert_allclose([(t.intrinsics.cx_px, t.intrinsics.cy_px) for t in plan.tasks],
                               [(SIZE / 2 + SHIFT_PX[0] - 0.5, SIZE / 2 + SHIFT_PX[1] - 0.5)] * 3)


def test_a_bad_principal_point_setting_names_the_key(capture):
    from icomma_plugin.app.inputs import ProblemError
    from icomma_plugin.app.problem import open_model_folder

    with pytest.raises(ProblemError, match="data.principal_point.*auto, dataset or centre"):
        open_model_folder({"model_path": str(capture["model"]), "principal_point": "middle"})


def test_views_localized_through_the_models_convention_come_back_to_their_records(capture,
                                                                                 tmp_path):
    """Through the centre (the model's): at the records; through the files' point: turned."""
    from icomma_plugin.app.batch import BatchWorker, WorkerSetup
    from icomma_plugin.localize import RobustConfig
    from icomma_plugin.matchers import make_matcher

    matcher = make_matcher("xfeat")
    errs = {}
    for pp in ("auto", "dataset"):
        plan, mf = _plan(capture, pp)
        setup = WorkerSetup(model_path=plan.model_path, method=RobustConfig(), matcher=None,
                            out_dir=str(tmp_path / pp), thumbs=False, cache_dir=False,
                            principal_point=pp)
        worker = BatchWorker(setup, mf, matcher)
        rows = [worker.run(t) for t in plan.tasks]
        assert all(np.allclose(r["gt_c2w"], capture["c2w"][r["name"]]) for r in rows)
        errs[pp] = np.array([r["rot_err_deg"] for r in rows])
    # 3.6 px at a focal length of ~100 px turns the camera by ~2 deg
    turn = math.degrees(math.atan(math.hypot(*SHIFT_PX) / capture["f0"]))
    assert errs["auto"].max() < 0.1, errs
    assert np.all(errs["dataset"] > 0.5 * turn), (errs, turn)


def test_photos_given_a_principal_point_are_told_when_the_model_took_the_centre(capture, caplog):
    from icomma_plugin.app import problem

    mf, _ = problem.open_model_folder({"model_path": str(capture["model"])})
    given = {"intrinsics": {"fx": 100.0, "fy": 100.0, "cx": 52.0, "cy": 48.0}}
    problem._centred_model_note.cache_clear()
    with caplog.at_level("WARNING", logger="icomma_plugin.app.problem"):
        problem.photo_camera(given, mf.with_principal_point("dataset"), False)
        assert "fitted with the image centre" not in caplog.text
        problem.photo_camera({"intrinsics": {"fx": 100.0}}, mf, False)  # no cx, cy: nothing
        assert "fitted with the image centre" not in caplog.text
        problem.photo_camera(given, mf, False)
    assert "fitted with the image centre" in caplog.text and "leave cx, cy out" in caplog.text


def test_photos_given_a_focal_length_hear_of_the_source_camera_that_has_more(capture):
    """A source camera of the photos' shape and focal length with a principal point is named."""
    from icomma_plugin.app import problem
    from icomma_plugin.camera import Intrinsics
    from tests.helpers.tools import localize_tool

    mf, _ = problem.open_model_folder({"model_path": str(capture["model"])})
    f0 = capture["f0"]
    # the photos at twice the dataset's size: the camera is compared at theirs
    given = Intrinsics(2 * SIZE, 2 * SIZE, 2 * f0, 2 * f0)

    def like(folder, it=None, at=given):
        data = {"intrinsics": it or {"fx": at.fx, "fy": at.fy},
                "query": {"dataset": str(capture["dataset"])}}
        return problem.source_camera_like(data, folder, False, at)

    found = like(mf.with_principal_point("dataset"))
    assert found["camera"] in ("v0", "v1", "v2") and found["distortion"] is None
    np.testing.assert_allclose(found["principal_point"],
                               [2 * (SIZE / 2 + s) - 0.5 for s in SHIFT_PX])
    line = localize_tool()._source_camera_line(found)
    assert f"data.intrinsics.camera={found['camera']} " in line and "a principal point" in line
    assert like(mf) is None  # fitted with the centre: the dataset's camera has nothing more
    assert like(mf.with_principal_point("dataset"),
                at=Intrinsics(2 * SIZE, 2 * SIZE, 2.1 * f0, 2.1 * f0)) is None  # 5 % off
    assert like(mf.with_principal_point("dataset"),
                {"fx": 2 * f0, "fy": 2 * f0, "cx": 99.5, "cy": 99.5}) is None  # given one


@pytest.mark.parametrize("pp", ["auto", "dataset"])
def test_every_reader_of_the_models_dataset_takes_its_principal_point(capture, pp):
    """The benchmark's queries, the source photos and a single dataset view alike."""
    import dataclasses

    from icomma_plugin.app import problem
    from icomma_plugin.benchmark.scene import load_model_folder_scene
    from icomma_plugin.localization.localizer import source_photos

    centred = pp == "auto"  # the demo folder is upstream's: the image centre
    mf, _ = problem.open_model_folder({"model_path": str(capture["model"]),
                                       "principal_point": pp})
    with_source = dataclasses.replace(mf, cfg={**mf.cfg, "source_path": str(capture["dataset"])})
    photos = source_photos(with_source, False)
    view = problem._query_view({"dataset": str(capture["dataset"]), "index": 0, "split": "train"},
                               mf, False, None)
    bench = load_model_folder_scene(capture["model"], capture["dataset"], num_queries=1,
                                    split="train", image_scale=1.0, principal_point=pp)
    found = [p.intrinsics for p in photos] + [view.intrinsics] + [
        q.query.intrinsics for q in bench.queries] + [p.intrinsics for p in bench.photos or []]
    assert len(found) >= 3
    assert all((i.cx is None) == centred for i in found), found


def test_the_benchmark_takes_the_principal_point_of_its_scene_group(capture):
    from icomma_plugin.benchmark import ProtocolSpec
    from tests.helpers.tools import compose
    from tools import _common as common
    from tools.benchmark import load_scene

    def scene(pp):
        cfg = compose([f"scene.model_path={capture['model']}",
                       f"scene.query.dataset={capture['dataset']}", "scene.query.split=train",
                       "scene.query.image_scale=1.0", f"scene.principal_point={pp}"],
                      name="benchmark")
        spec = ProtocolSpec.from_dict(common.container(cfg.benchmark_protocol), quick=True)
        return load_scene(cfg, spec, "cpu")

    auto, given = scene("auto"), scene("dataset")
    assert auto.queries[0].query.intrinsics.cx is None  # upstream's folder: the centre
    assert given.queries[0].query.intrinsics.cx is not None
    assert (auto.info["principal_point"], given.info["principal_point"]) == ("centre", "dataset")
    with pytest.raises(common.UserError, match="scene.principal_point must be auto, dataset or "
                                               "centre, got 'middle'"):
        scene("middle")


def test_a_model_trained_elsewhere_finds_its_photos_in_the_dataset_given(capture, tmp_path,
                                                                         caplog):
    """cfg_args' source_path is the training machine's: ``data.query.dataset`` stands for it."""
    import dataclasses

    from icomma_plugin.app import problem
    from icomma_plugin.app.batch import BatchWorker, WorkerSetup
    from icomma_plugin.localize import RobustConfig

    mf, _ = problem.open_model_folder({"model_path": str(capture["model"])})
    assert problem.photos_of({}, mf, False) is None  # the demo folder names no dataset
    elsewhere = dataclasses.replace(mf, cfg={**mf.cfg, "source_path": "/home/someone/garden"})
    with caplog.at_level("INFO", logger="icomma_plugin.localization.localizer"):
        assert problem.photos_of({}, elsewhere, False) is None
    assert "/home/someone/garden are not a folder here" in caplog.text
    assert "data.query.dataset=<folder>" in caplog.text
    data = {"query": {"dataset": str(capture["dataset"])}}
    names = sorted(p.name for p in problem.photos_of(data, mf, False))
    assert len(names) >= 2 and set(names) <= {"v0.png", "v1.png", "v2.png"}
    setup = WorkerSetup(model_path=str(capture["model"]), method=RobustConfig(), matcher=None,
                        out_dir=str(tmp_path), thumbs=False, cache_dir=False,
                        dataset=str(capture["dataset"]))
    worker = BatchWorker(setup, mf, matcher=object())
    assert sorted(p.name for p in worker.localizer.photos.photos) == names


@pytest.fixture(scope="module")
def off_centre_capture(tmp_path_factory, capture):
    """A capture fitted with its own principal point: 6 photos and files saying it.

    Rendered through a camera whose principal point is 3, -2 px off the centre.
    """
    from icomma_plugin.camera import Intrinsics
    from icomma_plugin.io.model_folder import load_model_folder
    from icomma_plugin.pose.convert import look_at_c2w
    from tests.helpers.colmap import write_colmap_dataset

    model = load_model_folder(capture["model"]).model
    f0 = capture["f0"]
    cx, cy = SIZE / 2 + SHIFT_PX[0], SIZE / 2 + SHIFT_PX[1]  # COLMAP's pixels
    cam = Intrinsics(SIZE, SIZE, f0, f0, cx - 0.5, cy - 0.5)
    photos = []
    for i in range(6):
        az = 0.2 + 1.0 * i
        c2w = look_at_c2w(np.array([3.8 * math.cos(az), 3.8 * math.sin(az), 2.0]),
                          np.array([0.0, 0.0, 0.4]))
        photos.append((f"w{i}.png", photo(model, cam, c2w), c2w, f0, f0, cx, cy))
    root = tmp_path_factory.mktemp("off") / "dataset"
    write_colmap_dataset(root, photos)
    return root


def test_a_batch_of_views_read_at_the_wrong_principal_point_says_so(capture, off_centre_capture,
                                                                   tmp_path):
    """Views whose camera is off the centre, read at the centre: every pose turned, and said."""
    from tests.helpers.tools import compose, localize_tool

    doc = {}
    for pp in ("centre", "dataset"):
        out = tmp_path / pp
        doc[pp] = localize_tool().run(compose([
            "data=model_folder", f"data.model_path={capture['model']}",
            f"data.queries={off_centre_capture}", "data.init.rot_deg=5.0",
            f"data.principal_point={pp}", f"output.dir={out}", "output.progress=false",
            "output.contact_sheet=false", "threads=1"]), out)
    wrong, right = doc["centre"]["summary"], doc["dataset"]["summary"]
    ev = wrong["centre_evidence"]
    assert ev["views_centred"] and ev["off"] and ev["views"] == 6, ev
    assert ev["shift_px"] == pytest.approx(math.hypot(*SHIFT_PX), abs=1.0)
    assert "data.principal_point=dataset" in localize_tool().many_summary(doc["centre"])
    assert right["centre_evidence"] is None
    errs = {pp: np.median([r["rot_err_deg"] for r in doc[pp]["photos"]]) for pp in doc}
    assert errs["dataset"] < 0.1 < errs["centre"], errs
