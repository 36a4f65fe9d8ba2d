"""One camera's focal length from many photos: the pooled estimate, and a batch that adopts it.

The pooling rule and a photo's estimate (``app/focal.py``, shared with tracking), a batch whose
fake lens prefers another focal length (adopted, every photo localized again from its pose, kept
through a resume and a kill in the second pass), and the demo scene's photos given a focal length
8 % short through the tool.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from icomma_plugin.app.batch import BatchPlan, PhotoTask, WorkerSetup, run_batch
from icomma_plugin.app.batch import worker as batch_worker
from icomma_plugin.app.focal import BatchFocalConfig, photo_focal_scale, pooled_focal_scale
from icomma_plugin.app.ledger import PosesLedger
from icomma_plugin.camera import Intrinsics
from tests.helpers.demo import demo_model, orbit_c2w, save_photos
from tests.helpers.focal import check_focal_found
from tests.helpers.tools import compose, localize_tool

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def test_pooled_focal_scale_needs_photos_that_agree():
    rng = np.random.default_rng(0)
    right = 1.0 + 0.006 * rng.standard_normal(10)  # the lego path's scatter, given the right one
    assert pooled_focal_scale(right) is None
    off = 1.04 + 0.006 * rng.standard_normal(10)
    assert pooled_focal_scale(off) == pytest.approx(float(np.median(off)))
    # relative to the focal length used now
    assert pooled_focal_scale(off, current=1.04) is None
    assert pooled_focal_scale(off, current=1.02) == pytest.approx(float(np.median(off)))
    # a median off but photos on both sides: not adopted
    split = np.array([1.05, 1.05, 1.05, 1.05, 1.05, 1.05, 0.97, 0.97, 0.97, 0.97])
    assert pooled_focal_scale(split, agree=0.8) is None
    assert pooled_focal_scale(split, agree=0.6) == pytest.approx(1.05)
    # within min_change: not adopted; photos without the signal are left out
    assert pooled_focal_scale([1.008] * 10, min_change=0.01) is None
    assert pooled_focal_scale([None, float("nan"), 1.03, 1.03, 1.03]) == pytest.approx(1.03)
    assert pooled_focal_scale([None, None]) is None


def test_a_photos_focal_scale_is_of_the_given_focal_length():
    row = {"status": "ok", "c2w": np.eye(4).tolist(), "signals": {"focal": {"scale": 1.01}},
           "details": {"focal_scale": 1.05}, "camera_focal_scale": 0.98}
    assert photo_focal_scale(row) == pytest.approx(0.98 * 1.05 * 1.01)
    assert photo_focal_scale({**row, "details": {}, "camera_focal_scale": None}) == \
        pytest.approx(1.01)
    assert photo_focal_scale({**row, "status": "failed"}) is None
    assert photo_focal_scale({**row, "signals": {"focal": None}}) is None


def test_batch_focal_config_names_bad_settings():
    with pytest.raises(ValueError, match="batch.focal_min_photos"):
        BatchFocalConfig(focal_min_photos=1)
    with pytest.raises(ValueError, match="batch.focal_agree"):
        BatchFocalConfig(focal_agree=0.3)
    with pytest.raises(ValueError, match="batch.focal_settle"):
        BatchFocalConfig(focal_settle=0.05, focal_min_change=0.01)
    with pytest.raises(ValueError, match="batch.focal_from_photos"):
        BatchFocalConfig(focal_from_photos="yes")


# ------------------------------------------------------------------ a batch through a fake lens


class _LensWorker:
    """Every photo `ok` where it starts; its matches prefer the lens's focal length ``F_TRUE``."""

    F_TRUE = 8.8
    calls: list = []  # (name, fx, start x) of every photo localized, in order
    stop_after = None  # raise KeyboardInterrupt after this many calls (a kill)

    def __init__(self, setup, model_folder=None, matcher=None):
        pass

    def run(self, task: PhotoTask):
        calls = type(self).calls
        if self.stop_after is not None and len(calls) >= self.stop_after:
            raise KeyboardInterrupt
        fx = task.intrinsics.fx
        start = None if task.init_c2w is None else float(task.init_c2w[0, 3])
        calls.append((task.name, round(fx, 6), start))
        c2w = np.eye(4)
        c2w[0, 3] = 1.0 + task.index  # where the photo was found (a pose the redo starts from)
        return {"name": task.name, "index": task.index, "status": "ok", "c2w": c2w.tolist(),
                "signals": {"focal": {"scale": self.F_TRUE / fx}},
                "intrinsics": task.intrinsics.to_json(),
                "camera_focal_scale": task.focal_scale}


def _plan(n=6, view=None):
    tasks = [PhotoTask(i, f"p{i}.png", f"p{i}.png", view, Intrinsics(8, 8, 8.0, 8.0))
             for i in range(n)]
    return BatchPlan(tasks, "model", None, False, None, "none")


def _run(tmp_path, monkeypatch, plan=None, focal=BatchFocalConfig(), stop_after=None, out="out",
         shard=(0, 1), lens=None):
    monkeypatch.setattr(batch_worker, "BatchWorker", lens or _LensWorker)
    monkeypatch.setattr(_LensWorker, "calls", [])
    monkeypatch.setattr(_LensWorker, "stop_after", stop_after)
    plan = plan or _plan()
    ledger = PosesLedger(tmp_path / out, {"kind": "batch"}, len(plan.tasks), *shard)
    setup = WorkerSetup(model_path="model", method=None, matcher=None, out_dir=str(tmp_path / out))
    summ = run_batch(plan, setup, ledger, focal=focal)
    return summ, ledger, list(_LensWorker.calls)


def test_a_batch_adopts_the_focal_length_its_photos_agree_on(tmp_path, monkeypatch):
    summ, ledger, calls = _run(tmp_path, monkeypatch)
    # six photos at the given 8.0 agree on 8.8: adopted, and all six localized again with it,
    # each from the pose it was found at
    assert [c[:2] for c in calls] == [(f"p{i}.png", 8.0) for i in range(6)] + \
        [(f"p{i}.png", 8.8) for i in range(6)]
    assert [c[2] for c in calls[6:]] == [1.0 + i for i in range(6)]
    assert summ.focal_scale == pytest.approx(1.1) and summ.focal_adoptions == 1
    assert summ.redone == 6 and summ.done_now == 6 and len(summ.rows) == 6
    rows = ledger.all_rows()
    assert [r["camera_focal_scale"] for r in rows] == pytest.approx([1.1] * 6)
    assert [r["intrinsics"]["fx"] for r in rows] == pytest.approx([8.8] * 6)
    state = json.loads((tmp_path / "out" / "poses.focal.json").read_text())
    assert state["scale"] == pytest.approx(1.1) and state["adoptions"] == 1
    # the record of the passes: at the given focal length every photo asked for 1.1, then 1.0
    assert [p["used"] for p in state["passes"]] == pytest.approx([1.0, 1.1])
    assert list(state["passes"][0]["estimates"].values()) == pytest.approx([1.1] * 6)
    assert list(state["passes"][1]["estimates"].values()) == pytest.approx([1.1] * 6)
    assert summ.focal_passes == state["passes"]
    # run again in the same folder: nothing to do, the focal length kept
    summ2, _, calls2 = _run(tmp_path, monkeypatch)
    assert calls2 == [] and summ2.focal_scale == pytest.approx(1.1)


def test_a_batch_killed_while_localizing_again_resumes_with_the_adopted_focal_length(
        tmp_path, monkeypatch):
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path, monkeypatch, stop_after=8)  # 6 photos, then 2 of the second pass
    summ, ledger, calls = _run(tmp_path, monkeypatch)
    # the four photos still at the given focal length are localized again; no new adoption
    assert [c[:2] for c in calls] == [(f"p{i}.png", 8.8) for i in range(2, 6)]
    assert summ.focal_adoptions == 0 and summ.focal_scale == pytest.approx(1.1)
    assert [r["camera_focal_scale"] for r in ledger.all_rows()] == pytest.approx([1.1] * 6)


def test_a_shard_decides_on_its_own_photos(tmp_path, monkeypatch):
    summ, ledger, calls = _run(tmp_path, monkeypatch, plan=_plan(8), shard=(1, 2),
                               focal=BatchFocalConfig(focal_min_photos=4))
    assert [c[:2] for c in calls] == [(f"p{i}.png", 8.0) for i in (1, 3, 5, 7)] + \
        [(f"p{i}.png", 8.8) for i in (1, 3, 5, 7)]
    state = tmp_path / "out" / "parts" / "shard-001-of-002.focal.json"
    assert json.loads(state.read_text())["scale"] == pytest.approx(1.1)
    assert not (tmp_path / "out" / "poses.focal.json").exists()


@pytest.mark.parametrize("case", ["off", "too_few", "dataset_views", "right_focal"])
def test_a_batch_keeps_the_given_focal_length(tmp_path, monkeypatch, case):
    plan, focal = _plan(), BatchFocalConfig()
    if case == "off":
        focal = BatchFocalConfig(focal_from_photos=False)
    elif case == "too_few":
        plan = _plan(4)
    elif case == "dataset_views":  # a dataset folder's views hold their own cameras
        plan = _plan(view=object())
    else:
        monkeypatch.setattr(_LensWorker, "F_TRUE", 8.0 * 1.005)  # within focal_min_change
    summ, ledger, calls = _run(tmp_path, monkeypatch, plan=plan, focal=focal)
    assert len(calls) == len(plan.tasks) and {c[1] for c in calls} == {8.0}
    assert summ.focal_adoptions == 0 and summ.focal_scale == 1.0
    assert not (tmp_path / "out" / "poses.focal.json").exists()


# ------------------------------------------------------------- the demo scene, through the tool


@pytest.fixture(scope="module")
def photos_scene(tmp_path_factory):
    """A 100x100 demo model and 6 photos of it rendered around it, with their true poses."""
    root = tmp_path_factory.mktemp("focal_batch")
    s, model = demo_model(root / "model", 100)
    folder = root / "photos"
    save_photos(model, s.intrinsics,
                {f"p{i}.png": orbit_c2w(0.3 + 0.9 * i, 1.6 + 0.2 * (i % 3)) for i in range(6)},
                folder, root / "gt.json")
    return {"model": s.path, "photos": folder, "gt": root / "gt.json", "fx": s.intrinsics.fx}


def test_a_batch_given_a_wrong_focal_length_finds_it_from_its_photos(photos_scene, tmp_path):
    """Given 8 % too short a focal length and no per-photo retry, the photos agree on it.

    Without the estimate every photo is localized with the distance off; with it, the batch adopts
    the focal length its photos' checks prefer and localizes them again.
    """
    ps = photos_scene
    fx = ps["fx"] * 0.92
    docs = {}
    for on in (False, True):
        out = tmp_path / f"out_{on}"
        docs[on] = localize_tool().run(compose([
            "data=model_folder", f"data.model_path={ps['model']}", f"data.queries={ps['photos']}",
            f"data.intrinsics.fx={fx}", f"data.intrinsics.fy={fx}", "data.intrinsics.cx=49.5",
            "data.intrinsics.cy=49.5", f"data.gt.poses_file={ps['gt']}", "data.init=none",
            "optimizer.focal_retry=false", f"batch.focal_from_photos={str(on).lower()}",
            f"output.dir={out}", "output.progress=false", "output.contact_sheet=false",
            "threads=1"]), out)
    check_focal_found(docs, ps["fx"], 0.92, "photos")
    assert (tmp_path / "out_True" / "focal.png").is_file()
    assert not (tmp_path / "out_False" / "focal.png").exists()


def test_an_unreadable_focal_state_is_named(tmp_path, monkeypatch):
    from icomma_plugin.app.inputs import ProblemError

    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "poses.focal.json").write_text("{not json")
    with pytest.raises(ProblemError, match="poses.focal.json"):
        _run(tmp_path, monkeypatch)


class _RunawayLens(_LensWorker):
    """Every refit asks for 10 % more than the focal length it was given: never satisfied."""

    def run(self, task: PhotoTask):
        row = super().run(task)
        row["signals"]["focal"]["scale"] = 1.1
        return row


def test_the_adoptions_are_capped_across_resumed_runs(tmp_path, monkeypatch):
    focal = BatchFocalConfig(focal_rounds=2)
    summ, _, calls = _run(tmp_path, monkeypatch, focal=focal, lens=_RunawayLens)
    assert summ.focal_adoptions == 2 and len(calls) == 18
    assert summ.focal_scale == pytest.approx(1.21)
    summ2, _, calls2 = _run(tmp_path, monkeypatch, focal=focal, lens=_RunawayLens)
    assert calls2 == [] and summ2.focal_adoptions == 0 and summ2.focal_scale == pytest.approx(1.21)
