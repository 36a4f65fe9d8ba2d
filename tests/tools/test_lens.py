"""One camera's lens distortion from many photos: the pooled estimate, and a batch that adopts it.

The pooling rule and a photo's estimate (``app/lens.py``), a batch whose fake lens is distorted
(adopted, every photo undistorted and localized again from its pose, kept through a resume), the
cases that keep the photos as they are, and fox's phone photos given their pinhole intrinsics
alone through the tool.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from icomma_plugin.app.batch import BatchPlan, PhotoTask, WorkerSetup, run_batch
from icomma_plugin.app.batch import worker as batch_worker
from icomma_plugin.app.inputs import LensDistortion
from icomma_plugin.app.lens import (LensConfig, PhotoDistortion, centre_evidence,
                                    photo_centre, photo_distortion, pooled_distortion)
from icomma_plugin.app.ledger import PosesLedger
from icomma_plugin.camera import Intrinsics
from tests.helpers.tools import compose, localize_tool

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

FOX_LENS = (0.0578421, -0.0805099, -0.000980296, 0.00015575)  # fox's transforms.json


def _photos(rng, centre, spread, n=20, reach=0.7, focal=340.0):
    return [PhotoDistortion(tuple(np.asarray(centre) + spread * rng.standard_normal(4)), reach,
                            focal) for _ in range(n)]


def test_pooled_distortion_needs_photos_that_agree():
    rng = np.random.default_rng(0)
    lens = _photos(rng, FOX_LENS, [0.005, 0.01, 0.0002, 0.0002])
    got = pooled_distortion(lens)
    assert got == pytest.approx(np.median([p.coefficients for p in lens], axis=0))
    assert got[0] == pytest.approx(FOX_LENS[0], abs=0.005)
    # relative to the coefficients used now: nothing left to adopt
    assert pooled_distortion(lens, current=got) is None
    # photos without distortion, scattered as bird's soft ones (k1 +-0.05): not adopted
    assert pooled_distortion(_photos(rng, (0, 0, 0, 0), [0.05, 0.08, 0.001, 0.001], 60)) is None
    # a median that moves pixels by less than min_shift_px: not adopted
    small = _photos(rng, (0.004, 0, 0, 0), [0.0005, 0, 0, 0])
    assert pooled_distortion(small, min_shift_px=0.5) is None
    assert pooled_distortion(small, min_shift_px=0.2) is not None
    # a median off but photos both ways: not adopted
    split = _photos(rng, FOX_LENS, 0.0, 6) + _photos(rng, np.negative(FOX_LENS), 0.0, 4)
    assert pooled_distortion(split, agree=0.8) is None
    assert pooled_distortion(split, agree=0.6) is not None
    assert pooled_distortion([]) is None


def test_a_photos_distortion_adds_the_one_it_was_undistorted_with():
    sig = {"coefficients": [0.01, -0.02, 0.0001, 0.0], "reach": 0.6, "focal_px": 300.0}
    row = {"status": "ok", "c2w": np.eye(4).tolist(), "signals": {"distortion": sig}}
    assert photo_distortion(row).coefficients == pytest.approx((0.01, -0.02, 0.0001, 0.0))
    used = {**row, "camera_distortion": [0.05, -0.06, -0.001, 0.0002]}
    assert photo_distortion(used).coefficients == pytest.approx((0.06, -0.08, -0.0009, 0.0002))
    assert photo_distortion(used).reach == 0.6 and photo_distortion(used).focal_px == 300.0
    assert photo_distortion({**row, "status": "failed"}) is None
    assert photo_distortion({**row, "signals": {}}) is None
    assert photo_distortion({**row, "signals": {"distortion": {"coefficients": [1.0]}}}) is None


def test_batch_lens_config_names_bad_settings():
    with pytest.raises(ValueError, match="batch.lens.min_views"):
        LensConfig(min_views=1)
    with pytest.raises(ValueError, match="batch.lens.min_shift_px"):
        LensConfig(min_shift_px=0.0)
    with pytest.raises(ValueError, match="batch.lens.agree"):
        LensConfig(agree=0.2)
    with pytest.raises(ValueError, match="batch.lens.estimate"):
        LensConfig(estimate="yes")
    with pytest.raises(ValueError, match="batch.lens.rounds"):
        LensConfig(rounds=0)
    with pytest.raises(ValueError, match="batch.lens.min_centre_move"):
        LensConfig(min_centre_move=-0.1)


# ------------------------------------------------------------------ a batch through a fake lens


class _DistortedWorker:
    """Every photo `ok` where it starts.

    Its matches see the lens ``LENS`` less what it was undistorted with; a photo given no
    principal point sees k1, k2 alone and the principal point ``CENTRE`` less the one it was
    given (as the verdict's refit with the centre free).
    """

    LENS = FOX_LENS
    CENTRE = (0.0, 0.0)  # the principal point's move from the image centre [focal lengths]
    calls: list = []  # (name, distortion or None, start x, (cx, cy) or None) of every photo

    def __init__(self, setup, model_folder=None, matcher=None):
        pass

    def run(self, task: PhotoTask):
        used = np.zeros(4) if task.distortion is None else np.asarray(task.distortion)
        intr = task.intrinsics
        type(self).calls.append((task.name, task.distortion,
                                 None if task.init_c2w is None else float(task.init_c2w[0, 3]),
                                 None if intr.cx is None else (intr.cx, intr.cy)))
        c2w = np.eye(4)
        c2w[0, 3] = 1.0 + task.index
        left = (np.asarray(self.LENS) - used).tolist()
        sig = {"coefficients": left, "reach": 0.7, "focal_px": 340.0}
        if intr.cx is None:
            sig["coefficients"][2:] = [0.0, 0.0]
            sig["centre"] = list(self.CENTRE)
        row = {"name": task.name, "index": task.index, "status": "ok", "c2w": c2w.tolist(),
               "signals": {"distortion": sig, "focal": {"scale": 1.0}},
               "intrinsics": task.intrinsics.to_json(), "camera_focal_scale": task.focal_scale}
        return batch_worker._camera_of(row, task)  # the camera it was localized with


CAMERA = Intrinsics(8, 8, 8.0, 8.0, 3.6, 3.4)  # its principal point given


def _plan(n=6, view=None, camera=CAMERA):
    tasks = [PhotoTask(i, f"p{i}.png", f"p{i}.png", view, camera) for i in range(n)]
    return BatchPlan(tasks, "model", None, False, None, "none")


def _run(tmp_path, monkeypatch, plan=None, lens=LensConfig(), distortion=None):
    monkeypatch.setattr(batch_worker, "BatchWorker", _DistortedWorker)
    monkeypatch.setattr(_DistortedWorker, "calls", [])
    plan = plan or _plan()
    ledger = PosesLedger(tmp_path / "out", {"kind": "batch"}, len(plan.tasks), 0, 1)
    setup = WorkerSetup(model_path="model", method=None, matcher=None,
                        out_dir=str(tmp_path / "out"), distortion=distortion)
    from icomma_plugin.app.focal import BatchFocalConfig

    summ = run_batch(plan, setup, ledger, focal=BatchFocalConfig(), lens=lens)
    return summ, ledger, list(_DistortedWorker.calls)


def test_a_batch_adopts_the_lens_its_photos_agree_on(tmp_path, monkeypatch):
    summ, ledger, calls = _run(tmp_path, monkeypatch)
    # six photos read as they are agree on fox's lens: adopted, all six undistorted with it and
    # localized again, each from the pose it was found at; then nothing is left to adopt
    assert [c[:2] for c in calls[:6]] == [(f"p{i}.png", None) for i in range(6)]
    assert [c[0] for c in calls[6:]] == [f"p{i}.png" for i in range(6)]
    assert all(c[1] == pytest.approx(FOX_LENS) for c in calls[6:])
    assert [c[2] for c in calls[6:]] == [1.0 + i for i in range(6)]
    assert summ.distortion == pytest.approx(FOX_LENS) and summ.distortion_adoptions == 1
    assert summ.focal_scale == 1.0 and summ.redone == 6 and summ.done_now == 6
    rows = ledger.all_rows()
    assert all(r["camera_distortion"] == pytest.approx(FOX_LENS) for r in rows)
    state = json.loads((tmp_path / "out" / "poses.focal.json").read_text())
    assert state["distortion"] == pytest.approx(FOX_LENS) and state["distortion_adoptions"] == 1
    # run again in the same folder: nothing to do, the lens kept
    summ2, _, calls2 = _run(tmp_path, monkeypatch)
    assert calls2 == [] and summ2.distortion == pytest.approx(FOX_LENS)
    assert summ2.distortion_adoptions == 0


def test_a_batch_given_no_principal_point_adopts_the_one_its_photos_agree_on(tmp_path,
                                                                            monkeypatch):
    monkeypatch.setattr(_DistortedWorker, "CENTRE", (0.05, -0.03))
    plan = _plan(camera=Intrinsics(8, 8, 8.0, 8.0))  # the image centre (3.5, 3.5) taken
    summ, ledger, calls = _run(tmp_path, monkeypatch, plan=plan)
    # the first pass measures the principal point with k1, k2: both adopted at once, then every
    # photo localized again from its pose, at 3.5 + 0.05 x 8 and 3.5 - 0.03 x 8
    assert [c[3] for c in calls[:6]] == [None] * 6
    assert [c[0] for c in calls[6:]] == [f"p{i}.png" for i in range(6)]
    assert all(c[3] == pytest.approx((3.9, 3.26)) for c in calls[6:])
    assert all(c[1] == pytest.approx(FOX_LENS[:2] + (0.0, 0.0)) for c in calls[6:])
    assert [c[2] for c in calls[6:]] == [1.0 + i for i in range(6)]
    assert summ.principal_point == pytest.approx([3.9, 3.26]) and summ.distortion_adoptions == 1
    assert summ.centre_evidence["agree"] == 1.0 and summ.centre_evidence["views"] == 6
    assert all(r["camera_principal_point"] == pytest.approx([3.9, 3.26])
               for r in ledger.all_rows())
    state = json.loads((tmp_path / "out" / "poses.focal.json").read_text())
    assert state["centre"] == pytest.approx([0.05, -0.03])
    line = localize_tool()._lens_line({"principal_point": summ.principal_point,
                                       "distortion": summ.distortion}, "photos")
    assert "data.intrinsics.cx=3.90 data.intrinsics.cy=3.26" in line
    assert "data.intrinsics.distortion=[0.05784,-0.08051,0.00000,0.00000]" in line
    # run again in the same folder: nothing to do, the camera kept
    summ2, _, calls2 = _run(tmp_path, monkeypatch, plan=plan)
    assert calls2 == [] and summ2.principal_point == pytest.approx([3.9, 3.26])


def test_a_photos_principal_point_and_the_photos_together():
    row = {"status": "ok", "c2w": np.eye(4).tolist(),
           "signals": {"distortion": {"centre": [0.01, -0.002], "focal_px": 300.0}}}
    assert photo_centre(row) == pytest.approx((0.01, -0.002, 300.0))
    assert photo_centre({**row, "status": "failed"}) is None
    assert photo_centre({**row, "signals": {"distortion": {"focal_px": 300.0}}}) is None
    rng = np.random.default_rng(1)
    rows = [{**row, "signals": {"distortion": {"centre": list(c), "focal_px": 300.0}}}
            for c in (0.01, -0.002) + 0.002 * rng.standard_normal((20, 2))]
    ev = centre_evidence(rows)
    assert ev["shift_px"] == pytest.approx(300.0 * np.hypot(0.01, 0.002), rel=0.2)
    assert ev["agree"] >= 0.9 and ev["views"] == 20
    assert LensConfig().adopt_centre(rows) == pytest.approx(tuple(ev["offset"]))
    assert LensConfig(estimate=False).adopt_centre(rows) is None
    assert LensConfig(min_views=21).adopt_centre(rows) is None
    # a move shorter than min_centre_move (0.008 focal lengths): what a tangential distortion makes
    near = [{**row, "signals": {"distortion": {"centre": list(c), "focal_px": 300.0}}}
            for c in (0.004, 0.0) + 0.0005 * rng.standard_normal((20, 2))]
    assert centre_evidence(near)["agree"] == 1.0 and centre_evidence(near)["shift_px"] > 1.0
    assert LensConfig().adopt_centre(near) is None
    assert LensConfig(min_centre_move=0.002).adopt_centre(near) is not None
    # the image centre right: the refits scatter about it both ways (goldcape's 60 photos:
    # 0.42 px, 52 % the same way), not adopted
    null = [{**row, "signals": {"distortion": {"centre": list(c), "focal_px": 300.0}}}
            for c in 0.003 * rng.standard_normal((60, 2))]
    assert centre_evidence(null)["agree"] < 0.8 and LensConfig().adopt_centre(null) is None
    assert centre_evidence([]) is None


@pytest.mark.parametrize("case", ["off", "too_few", "dataset_views", "given", "pinhole",
                                  "centred"])
def test_a_batch_keeps_its_photos_as_they_are(tmp_path, monkeypatch, case):
    plan, lens, distortion = _plan(), LensConfig(), None
    if case == "off":
        lens = LensConfig(estimate=False)
    elif case == "too_few":
        plan = _plan(4)
    elif case == "dataset_views":  # a dataset folder's views are undistorted already
        plan = _plan(view=object())
    elif case == "given":  # the user's coefficients are the photos' lens
        distortion = LensDistortion(FOX_LENS)
    else:  # a pinhole lens, given its principal point or at the image centre
        monkeypatch.setattr(_DistortedWorker, "LENS", (0.0, 0.0, 0.0, 0.0))
        if case == "centred":
            plan = _plan(camera=Intrinsics(8, 8, 8.0, 8.0))
    summ, ledger, calls = _run(tmp_path, monkeypatch, plan=plan, lens=lens,
                               distortion=distortion)
    assert len(calls) == len(plan.tasks) and {c[1] for c in calls} == {None}
    assert summ.distortion is None and summ.distortion_adoptions == 0
    assert not (tmp_path / "out" / "poses.focal.json").exists()
    assert all("camera_distortion" not in r and "camera_principal_point" not in r
               for r in ledger.all_rows())
    assert summ.principal_point is None
    line = localize_tool()._lens_line({"centre_evidence": summ.centre_evidence}, "photos")
    # the one case that measured the principal point (none given) says it kept the centre
    assert ("the image centre is kept" in line) == (case == "centred"), line


# ---------------------------------------------------------- a sequence through a fake lens


def _lens_frames(tmp_path, n):
    from PIL import Image

    folder = tmp_path / "frames"
    folder.mkdir(exist_ok=True)
    for i in range(n):
        Image.new("RGB", (8, 8)).save(folder / f"g{i}.png")
    return folder


def _fake_lens_worker(focal_ask=1.0, centre=(0.0, 0.0)):
    """The tracking tests' fake worker whose frames see fox's lens until undistorted.

    A frame given no principal point sees k1, k2 alone and the principal point ``centre`` (its
    move from the image centre in focal lengths) until it is given one.
    """
    from tests.tools.test_tracking import _FakeWorker

    class _Worker(_FakeWorker):
        def result(self, query, init_c2w, fast):
            res = super().result(query, init_c2w, fast)
            undistorted = query.valid is not None  # (a remapped 8x8 frame loses its corners)
            left = [0.0] * 4 if undistorted else list(FOX_LENS)
            sig = {"coefficients": left, "reach": 0.7, "focal_px": 340.0}  # (a phone's, in px)
            if query.intrinsics.cx is None:
                sig["coefficients"][2:] = [0.0, 0.0]
                sig["centre"] = list(centre)
            res.verdict.signals["distortion"] = sig
            res.verdict.signals["focal"] = {"scale": focal_ask, "rms_px": 0.5,
                                            "rms_px_given": 0.6}
            self.calls[-1] += (undistorted, round(query.intrinsics.fx, 6), query.intrinsics.cx)
            return res

    return _Worker({f"g{i}.png": np.eye(4) for i in range(8)})


def test_a_sequence_adopts_the_lens_of_its_first_frames_and_keeps_it(tmp_path):
    from icomma_plugin.app.lens import TrackingLensConfig
    from icomma_plugin.app.tracking import FrameSource, TrackingConfig, track

    folder = _lens_frames(tmp_path, 6)
    cfg = TrackingConfig(lens=TrackingLensConfig(min_views=3), focal_window=3)
    w = _fake_lens_worker(focal_ask=1.1)  # the distorted frames also ask for 10 % more focal
    summ = track(w, FrameSource.open(str(folder), limit=4),
                 PosesLedger(tmp_path / "out", {"kind": "sequence"}, 6),
                 lambda s: CAMERA, init_c2w=np.eye(4), cfg=cfg)
    # three frames read as they are agree on the lens: adopted; those three localized again
    # undistorted, with the focal length adopted from them undone (it made up for the lens)
    assert [(c[0], c[3], c[4]) for c in w.calls] == [
        ("g0.png", False, 8.0), ("g1.png", False, 8.0), ("g2.png", False, 8.0),
        ("g0.png", True, 8.0), ("g1.png", True, 8.0), ("g2.png", True, 8.0), ("g3.png", True, 8.0)]
    assert summ.distortion == pytest.approx(FOX_LENS) and summ.distortion_adoptions == 1
    assert summ.redone == 3
    rows = PosesLedger(tmp_path / "out", {"kind": "sequence"}, 6).all_rows()
    assert all(r["camera_distortion"] == pytest.approx(FOX_LENS) for r in rows)
    assert all(r["camera_focal_scale"] == 1.0 for r in rows)
    # a resumed run goes on undistorting with it, deciding nothing again
    w2 = _fake_lens_worker()
    summ2 = track(w2, FrameSource.open(str(folder)),
                  PosesLedger(tmp_path / "out", {"kind": "sequence"}, 6),
                  lambda s: CAMERA, init_c2w=np.eye(4), cfg=cfg)
    assert [(c[0], c[3]) for c in w2.calls] == [("g4.png", True), ("g5.png", True)]
    assert summ2.distortion == pytest.approx(FOX_LENS) and summ2.distortion_adoptions == 0
    # off: the frames as they are
    w3 = _fake_lens_worker()
    summ3 = track(w3, FrameSource.open(str(folder)),
                  PosesLedger(tmp_path / "out_off", {"kind": "sequence"}, 6),
                  lambda s: CAMERA, init_c2w=np.eye(4),
                  cfg=TrackingConfig(lens=TrackingLensConfig(estimate=False, min_views=3)))
    assert {c[3] for c in w3.calls} == {False} and len(w3.calls) == 6
    assert summ3.distortion is None and summ3.principal_point is None


def test_a_sequence_given_no_principal_point_adopts_one_with_its_lens(tmp_path):
    from icomma_plugin.app.lens import TrackingLensConfig
    from icomma_plugin.app.tracking import FrameSource, TrackingConfig, track

    folder = _lens_frames(tmp_path, 5)
    cfg = TrackingConfig(lens=TrackingLensConfig(min_views=3))
    centred = Intrinsics(8, 8, 8.0, 8.0)  # the image centre (3.5, 3.5) taken
    w = _fake_lens_worker(centre=(0.05, -0.03))
    summ = track(w, FrameSource.open(str(folder), limit=4),
                 PosesLedger(tmp_path / "out", {"kind": "sequence"}, 5),
                 lambda s: centred, init_c2w=np.eye(4), cfg=cfg)
    # the first three frames' refits agree on the principal point and on k1, k2: both adopted,
    # those three localized again with them, and the next frame with them too
    assert [(c[0], c[3], c[5]) for c in w.calls] == [
        ("g0.png", False, None), ("g1.png", False, None), ("g2.png", False, None),
        ("g0.png", True, pytest.approx(3.9)), ("g1.png", True, pytest.approx(3.9)),
        ("g2.png", True, pytest.approx(3.9)), ("g3.png", True, pytest.approx(3.9))]
    assert summ.principal_point == pytest.approx([3.9, 3.26])
    assert summ.centre_evidence["views"] == 3 and summ.centre_evidence["agree"] == 1.0
    assert summ.distortion == pytest.approx(FOX_LENS[:2] + (0.0, 0.0))
    rows = PosesLedger(tmp_path / "out", {"kind": "sequence"}, 5).all_rows()
    assert all(r["camera_principal_point"] == pytest.approx([3.9, 3.26]) for r in rows)
    # a resumed run goes on with them
    w2 = _fake_lens_worker(centre=(0.05, -0.03))
    summ2 = track(w2, FrameSource.open(str(folder)),
                  PosesLedger(tmp_path / "out", {"kind": "sequence"}, 5),
                  lambda s: centred, init_c2w=np.eye(4), cfg=cfg)
    assert [(c[0], c[3], c[5]) for c in w2.calls] == [("g4.png", True, pytest.approx(3.9))]
    assert summ2.principal_point == pytest.approx([3.9, 3.26])


def test_tracking_lens_config_names_its_group():
    from icomma_plugin.app.lens import TrackingLensConfig
    from icomma_plugin.app.tracking import TrackingConfig
    from icomma_plugin.checks import config_from_dict

    with pytest.raises(ValueError, match="tracking.lens.min_views"):
        TrackingLensConfig(min_views=1)
    cfg = config_from_dict(TrackingConfig, {"lens": {"min_views": 7}}, "tracking")
    assert isinstance(cfg.lens, TrackingLensConfig) and cfg.lens.min_views == 7
    with pytest.raises(ValueError, match="tracking.lens"):
        config_from_dict(TrackingConfig, {"lens": {"min_photos": 7}}, "tracking")


# ------------------------------------------------------------- the demo scene, through the tool

DEMO_LENS = (0.12, -0.05, 0.002, -0.001)


def _lens_photos(root, shift=(0.0, 0.0)):
    """A 200x200 demo model and 6 photos of it through the lens ``DEMO_LENS``, their true poses.

    ``shift``: the photos' principal point's move from the image centre [px].
    """
    import dataclasses

    import cv2
    from PIL import Image

    from tests.helpers.demo import demo_model, orbit_c2w, photo

    s, model = demo_model(root / "model", 200)
    i = s.intrinsics
    i = dataclasses.replace(i, cx=i.cx_px + shift[0], cy=i.cy_px + shift[1])
    K = np.array([[i.fx, 0.0, i.cx_px], [0.0, i.fy, i.cy_px], [0.0, 0.0, 1.0]])
    # the distorted photo's pixel shows the pinhole render at its undistorted position
    uv = np.stack(np.meshgrid(np.arange(200.0), np.arange(200.0)), -1).reshape(-1, 1, 2)
    src = cv2.undistortPoints(uv, K, np.array(DEMO_LENS), P=K).reshape(200, 200, 2)
    src = src.astype(np.float32)
    folder, gt = root / "photos", {}
    folder.mkdir()
    for n in range(6):
        c2w = orbit_c2w(0.3 + 0.9 * n, 1.6 + 0.2 * (n % 3))
        img = cv2.remap(photo(model, i, c2w), src[..., 0], src[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        Image.fromarray(img).save(folder / f"p{n}.png")
        gt[f"p{n}.png"] = c2w.tolist()
    (root / "gt.json").write_text(json.dumps(gt))
    return {"model": s.path, "photos": folder, "gt": root / "gt.json", "intrinsics": i}


@pytest.fixture(scope="module")
def distorted_photos(tmp_path_factory):
    return _lens_photos(tmp_path_factory.mktemp("lens_batch"))


def _lens_runs(ps, tmp_path, camera):
    """The tool's batch of ``ps``'s photos given ``camera`` (its overrides).

    ``{estimate: poses.json}``, without and with the lens estimated.
    """
    doc = {}
    for on in (False, True):
        out = tmp_path / f"out_{on}"
        doc[on] = localize_tool().run(compose([
            "data=model_folder", f"data.model_path={ps['model']}", f"data.queries={ps['photos']}",
            *camera, f"data.gt.poses_file={ps['gt']}", "data.init=none",
            f"batch.lens.estimate={str(on).lower()}", f"output.dir={out}",
            "output.progress=false", "output.contact_sheet=false", "threads=1"]), out)
    return doc


def test_a_batch_of_distorted_photos_finds_their_lens(distorted_photos, tmp_path):
    """Photos through a lens, given their pinhole intrinsics alone.

    The batch estimates the lens from them, undistorts them and localizes them again, nearer the
    truth.
    """
    ps, i = distorted_photos, distorted_photos["intrinsics"]
    doc = _lens_runs(ps, tmp_path, [f"data.intrinsics.fx={i.fx}", f"data.intrinsics.fy={i.fy}",
                                    f"data.intrinsics.cx={i.cx_px}",
                                    f"data.intrinsics.cy={i.cy_px}"])
    assert doc[False]["summary"]["distortion"] is None
    found = doc[True]["summary"]["distortion"]
    assert found is not None and doc[True]["summary"]["distortion_adoptions"] >= 1
    from icomma_plugin.localization.geometry import distortion_field

    # the lens it found moves the photos' pixels as the true one does, within a few tenths of a px
    true_field = distortion_field(DEMO_LENS, 0.55, i.fx)
    assert np.abs(distortion_field(found, 0.55, i.fx) - true_field).max() < 0.35 * np.abs(
        true_field).max()
    rows = {r["name"]: r for r in doc[True]["photos"]}
    assert all(r["camera_distortion"] == pytest.approx(found) for r in rows.values())
    errs = {on: np.array([r["rot_err_deg"] for r in doc[on]["photos"]]) for on in doc}
    assert np.median(errs[True]) < 0.6 * np.median(errs[False])
    assert errs[True].max() < 0.1
    assert "lens" in localize_tool().many_summary(doc[True])


def test_distorted_photos_given_no_principal_point_find_it(tmp_path_factory, tmp_path):
    """Photos through a lens whose principal point is 5 and -3 px off the image centre.

    Given their focal length alone, the batch finds the principal point with the lens.
    """
    ps = _lens_photos(tmp_path_factory.mktemp("lens_centre"), (5.0, -3.0))
    i = ps["intrinsics"]
    doc = _lens_runs(ps, tmp_path, [f"data.intrinsics.fx={i.fx}", f"data.intrinsics.fy={i.fy}"])
    summ = doc[True]["summary"]
    assert doc[False]["summary"]["principal_point"] is None
    assert summ["principal_point"] == pytest.approx([i.cx, i.cy], abs=1.5)
    assert summ["centre_evidence"]["agree"] >= 0.8 and summ["distortion"] is not None
    errs = {on: np.array([r["rot_err_deg"] for r in doc[on]["photos"]]) for on in doc}
    assert np.median(errs[True]) < 0.6 * np.median(errs[False])
    assert "data.intrinsics.cx=" in localize_tool().many_summary(doc[True])


# ------------------------------------------------------------- fox's phone photos, through the tool

#: Fox's fit: where `make scenes` writes it, else where tools/fit_scene.py runs here put it.
_FITS = [Path.home() / ".cache" / "icomma" / d for d in ("scenes/fox_270", "fits/fox")]
FOX_FIT = next((p for p in _FITS if (p / "cfg_args").is_file()), _FITS[0])


@pytest.mark.shared_data
@pytest.mark.skipif(not (FOX_FIT / "cfg_args").is_file(), reason=f"no fox fit at {FOX_FIT}")
def test_fox_photos_given_no_distortion_find_their_lens(fox_root, tmp_path):
    """Ten of fox's phone photos as files, given their pinhole intrinsics alone.

    The batch finds the lens its calibration gives, and the poses come nearer the truth.
    """
    doc = {}
    for on in (False, True):
        out = tmp_path / f"out_{on}"
        doc[on] = localize_tool().run(compose([
            "data=model_folder", f"data.model_path={FOX_FIT}",
            f"data.queries={fox_root / 'images'}",
            "data.every=5", "data.intrinsics.fx=1375.52", "data.intrinsics.fy=1374.49",
            "data.intrinsics.cx=554.058", "data.intrinsics.cy=964.768",
            "data.intrinsics.width=1080", "data.intrinsics.height=1920", "data.resize=480",
            "data.init=none", f"data.gt.cameras_json={FOX_FIT / 'cameras.json'}",
            f"batch.lens.estimate={str(on).lower()}", f"output.dir={out}",
            "output.progress=false", "output.contact_sheet=false", "threads=2"]), out)
    found = doc[True]["summary"]["distortion"]
    assert doc[False]["summary"]["distortion"] is None
    assert found[0] == pytest.approx(FOX_LENS[0], abs=0.01)
    assert found[1] == pytest.approx(FOX_LENS[1], abs=0.02)
    assert found[2] == pytest.approx(FOX_LENS[2], abs=0.0005)

    def median_err(d):
        return float(np.median([r["rot_err_deg"] for r in d["photos"]]))

    assert median_err(doc[True]) < 0.5 * median_err(doc[False])
    assert median_err(doc[True]) < 0.05


@pytest.mark.shared_data
@pytest.mark.skipif(not (FOX_FIT / "cfg_args").is_file(), reason=f"no fox fit at {FOX_FIT}")
def test_fox_photos_given_a_focal_length_alone_find_their_principal_point(fox_root, tmp_path):
    """Ten of fox's phone photos given fx, fy alone (as a cameras.json entry gives them).

    The image centre is 14.6 and 4.8 px from their principal point (0.48 deg of turn, median,
    over the 50); the batch finds it with k1, k2 and the poses come nearer the truth.
    """
    out = tmp_path / "out"
    doc = localize_tool().run(compose([
        "data=model_folder", f"data.model_path={FOX_FIT}", f"data.queries={fox_root / 'images'}",
        "data.every=5", "data.intrinsics.fx=1375.52", "data.intrinsics.fy=1374.49",
        "data.intrinsics.width=1080", "data.intrinsics.height=1920", "data.resize=480",
        "data.init=none", f"data.gt.cameras_json={FOX_FIT / 'cameras.json'}",
        f"output.dir={out}", "output.progress=false", "output.contact_sheet=false",
        "threads=2"]), out)
    summ = doc["summary"]
    # its calibration's (554.06, 964.77); the refits' estimate carries fox's p1 (3-4 px in cy)
    assert summ["principal_point"] == pytest.approx([554.06, 964.77], abs=6.0)
    assert summ["distortion"][0] == pytest.approx(FOX_LENS[0], abs=0.01)
    assert summ["distortion"][2:] == [0.0, 0.0]
    errs = [r["rot_err_deg"] for r in doc["photos"]]
    assert float(np.median(errs)) < 0.25 and max(errs) < 0.3
