"""Sequences (data.sequence): prediction, videos, relocalization, tracking through the tool.

Constant-velocity prediction, video files written and read back (MP4, GIF fallback),
relocalization of a failed frame, and tracking a synthetic path on a 100x100 demo scene from a
folder of frames and from an MP4 through the tool.
"""

from __future__ import annotations

import json
import threading
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from icomma_plugin.io import video
from icomma_plugin.app.ledger import PosesLedger
from icomma_plugin.app.tracking import FrameSource, TrackingConfig, predict_c2w, track
from icomma_plugin.localization.types import LocalizationResult, Verdict
from icomma_plugin.pose.se3 import se3_exp
from tests.helpers.demo import demo_model, orbit_c2w, photo
from tests.helpers.focal import check_focal_found
from tests.helpers.tools import compose, localize_tool

SIZE = 100
N_FRAMES = 6

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


# ------------------------------------------------------------------------------------ prediction


def test_constant_velocity_prediction_is_exact_on_a_constant_twist_path():
    xi = torch.tensor([0.05, -0.02, 0.03, 0.02, -0.01, 0.04], dtype=torch.float64)
    C0 = se3_exp(torch.tensor([0.3, 0.1, -2.0, 0.2, 0.5, -0.1], dtype=torch.float64)).numpy()

    def C(k):  # camera-to-world moving by the same camera-frame twist every frame
        return C0 @ se3_exp(xi * k).numpy()

    assert predict_c2w([], 3) is None
    assert np.allclose(predict_c2w([(0, C(0))], 1), C(0))  # one pose: stay there
    assert np.allclose(predict_c2w([(0, C(0)), (1, C(1))], 2), C(2), atol=1e-9)
    assert np.allclose(
        predict_c2w([(0, C(0)), (2, C(2))], 5), C(5), atol=1e-9
    )  # gaps (every N, failures)
    assert np.allclose(predict_c2w([(0, C(0)), (1, C(1))], 2, velocity=False), C(1))
    assert not np.allclose(C(2), C(1), atol=1e-3)  # the path moves: staying put is not exact


# ------------------------------------------------------------------------------------ video files


def _frames(n=5, h=48, w=64):
    out = []
    for i in range(n):
        f = np.zeros((h, w, 3), np.uint8)
        f[:, 8 * i : 8 * i + 16] = (255, 128, 0)
        f[h // 2 :, :, 2] = 40 * i
        out.append(f)
    return out


def test_video_written_and_read_back(tmp_path):
    frames = _frames()
    p = video.write_video(tmp_path / "v.mp4", frames, fps=5)
    assert p == tmp_path / "v.mp4" and p.is_file()
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".")]  # no temporary left
    w, h, n, fps = video.video_info(p)
    assert (w, h, n) == (64, 48, 5) and abs(fps - 5) < 1e-6
    back = list(video.read_video_frames(p))
    assert [i for i, _ in back] == [0, 1, 2, 3, 4]
    for (_, b), f in zip(back, frames):
        assert b.shape == f.shape and np.abs(b.astype(int) - f).mean() < 12  # lossy codec
    assert [i for i, _ in video.read_video_frames(p, every=2)] == [0, 2, 4]
    assert [i for i, _ in video.read_video_frames(p, every=2, limit=2)] == [0, 2]
    with pytest.raises(video.VideoError, match="not found"):
        video.video_info(tmp_path / "none.mp4")
    (tmp_path / "bad.mp4").write_bytes(b"nope")
    with pytest.raises(video.VideoError, match="cannot open"):
        video.video_info(tmp_path / "bad.mp4")
    with pytest.raises(video.VideoError, match="differ in size"):
        video.write_video(tmp_path / "x.mp4", [frames[0], frames[0][:10]])


def test_video_falls_back_to_gif_when_no_encoder_works(tmp_path, monkeypatch):
    monkeypatch.setattr(video, "_write_imageio", lambda *a: False)
    monkeypatch.setattr(video, "_write_cv2", lambda *a: False)
    p = video.write_video(tmp_path / "v.mp4", _frames(3))
    assert p == tmp_path / "v.gif" and not (tmp_path / "v.mp4").exists()
    with Image.open(p) as im:
        assert im.n_frames == 3 and im.size == (64, 48)


# ---------------------------------------------------------------------------- relocalization


class _FakeLocalizer:
    """The worker's localizer: the default method, called by the tracking mode's cheap try."""

    def __init__(self, worker):
        from icomma_plugin.localize import RobustConfig

        self.worker, self.method, self.model_side = worker, RobustConfig(), None
        self.matcher = None

    def localize(self, query, init_c2w=None, gt_c2w=None, progress=None, method=None):
        assert method is not None  # the tracking mode's own config; the full one is the worker's
        return self.worker.result(query, init_c2w, fast=True)


class _FakeWorker:
    """Fails from a start pose on f2.png and succeeds without one (the candidate views)."""

    def __init__(self, truth):
        self.truth, self.calls = truth, []
        self.setup = SimpleNamespace(resize=None, distortion=None)
        self.scene_scale = 1.0
        self.localizer = _FakeLocalizer(self)

    def problem(self, task, query):
        return SimpleNamespace(
            name=task.name, query=query, init_c2w=task.init_c2w, gt_c2w=None, scene_scale=1.0
        )

    def result(self, query, init_c2w, fast):
        self.calls.append((query.name, init_c2w is None, fast))
        ok = init_c2w is None or query.name != "f2.png"
        status = "ok" if ok else "failed"
        c2w = self.truth[query.name] if ok else np.eye(4)
        return LocalizationResult(
            name=query.name, c2w=c2w, verdict=Verdict(status, status), method="fake",
            matcher=None, iterations=1, stop_reason="converged", seconds=0.0,
            intrinsics=query.intrinsics, init_c2w=init_c2w,
        )

    def localize(self, problem, init_c2w):
        return self.result(problem.query, init_c2w, fast=False)

    def write_pictures(self, problem, result, seconds):
        return None, None


def test_a_failed_frame_is_relocalized_from_candidates(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    truth = {}
    for i in range(4):
        Image.new("RGB", (8, 8)).save(folder / f"f{i}.png")
        c2w = np.eye(4)
        c2w[0, 3] = 0.1 * i
        truth[f"f{i}.png"] = c2w
    w = _FakeWorker(truth)
    from icomma_plugin.camera import Intrinsics

    ledger = PosesLedger(tmp_path / "out", {"kind": "sequence"}, 4)
    summ = track(
        w,
        FrameSource.open(str(folder)),
        ledger,
        lambda s: Intrinsics(8, 8, 8.0, 8.0),
        init_c2w=np.eye(4),
        cfg=TrackingConfig(),
    )
    rows = ledger.all_rows()
    assert [r["status"] for r in rows] == ["ok"] * 4 and summ.relocalized == 1
    assert [r["relocalized"] for r in rows] == [False, False, True, False]
    # the tracking mode's cheap try first; the full method from the start, then from the
    # candidate views (no start), only for the frame whose cheap try was not ok
    assert w.calls == [("f0.png", False, True), ("f1.png", False, True), ("f2.png", False, True),
                       ("f2.png", False, False), ("f2.png", True, False), ("f3.png", False, True)]
    assert summ.fast_ok == 3
    assert np.allclose(rows[3]["predicted_c2w"], truth["f3.png"])  # velocity from f1, f2
    w2 = _FakeWorker(truth)
    ledger2 = PosesLedger(tmp_path / "out2", {"kind": "sequence"}, 4)
    track(
        w2,
        FrameSource.open(str(folder)),
        ledger2,
        lambda s: Intrinsics(8, 8, 8.0, 8.0),
        init_c2w=np.eye(4),
        cfg=TrackingConfig(relocalize=False, fast=False),
    )
    assert [r["status"] for r in ledger2.all_rows()][2] == "failed"
    assert ("f2.png", True, False) not in w2.calls and not any(c[2] for c in w2.calls)


# ------------------------------------------------------------------------------------ real tracking


@pytest.fixture(scope="module")
def path_scene(tmp_path_factory):
    """A 100x100 demo model and N_FRAMES frames along an arc around it (PNG folder + MP4)."""
    root = tmp_path_factory.mktemp("track")
    s, model = demo_model(root / "model", SIZE)
    folder = root / "frames"
    folder.mkdir()
    gts, frames = {}, []
    for i in range(N_FRAMES):
        az = 0.4 + 0.05 * i
        c2w = orbit_c2w(az, 2.0 + 0.03 * i)
        a = photo(model, s.intrinsics, c2w)
        Image.fromarray(a).save(folder / f"frame{i}.png")
        frames.append(a)
        gts[f"frame{i}.png"] = c2w.tolist()
        gts[f"frame_{i:06d}"] = c2w.tolist()  # the names of a video's frames
    (root / "gt.json").write_text(json.dumps(gts))
    first = np.asarray(gts["frame0.png"])
    start = first.copy()
    start[:3, 3] += 0.05  # a start near the first frame
    np.savetxt(root / "start.txt", start)
    mp4 = video.write_video(root / "path.mp4", frames, fps=5)
    return {
        "model": s.path,
        "frames": folder,
        "gt": root / "gt.json",
        "start": root / "start.txt",
        "mp4": mp4,
        "scale": s.scene_scale,
        "gts": gts,
        "fx": s.intrinsics.fx,
    }


def _args(ps, out, *extra):
    return [
        "data=model_folder",
        f"data.model_path={ps['model']}",
        "data.intrinsics.camera=ring_000",
        f"data.gt.poses_file={ps['gt']}",
        f"data.init.c2w_file={ps['start']}",
        f"output.dir={out}",
        "output.progress=false",
        *extra,
    ]


def test_tracking_a_path_from_a_folder_of_frames(path_scene, tmp_path):
    out = tmp_path / "out"
    doc = localize_tool().run(
        compose(
            _args(path_scene, out, f"data.sequence={path_scene['frames']}", "output.video=false",
                  "tracking.fast_patch_search=2")
        ),
        out,
    )
    rows = doc["photos"]
    assert [r["name"] for r in rows] == [f"frame{i}.png" for i in range(N_FRAMES)]
    assert doc["status"] == "complete" and doc["summary"]["kind"] == "sequence"
    for r in rows:
        assert r["status"] != "failed", r["reason"]
        assert r["rot_err_deg"] < 0.2 and r["trans_err_rel"] < 2e-3, r
    # the constant-velocity prediction is close to the truth on this smooth path
    gts = path_scene["gts"]
    from icomma_plugin.pose.convert import rotation_error_deg

    for r in rows[2:]:
        pred, gt = np.asarray(r["predicted_c2w"]), np.asarray(gts[r["name"]])
        assert rotation_error_deg(pred, gt) < 0.5
    assert (out / "trajectory.png").is_file() and not (out / "tracking.mp4").exists()
    # the tracking mode (with the patch search asked for) matched the renders after the first
    # frame by the patch search, and the console summary says so
    assert sum(r["details"]["patch_search"]["matched"] for r in rows[1:]) >= N_FRAMES - 1
    text = localize_tool().many_summary(doc)
    assert "fast mode settled" in text and "patch search matched" in text, text


def test_look_ahead_extracts_each_frame_in_the_prefetch_thread(path_scene, tmp_path, monkeypatch):
    """With tracking.look_ahead the prefetch thread makes the query's features of every frame.

    The localization uses them (``Localizer.prepare``): the main thread extracts only
    renders. Without it, none there; the poses are the same either way.
    """
    from icomma_plugin.matchers.base import Matcher

    threads = []
    extract = Matcher.extract

    def recorded(self, image):
        threads.append(threading.current_thread().name)
        return extract(self, image)

    monkeypatch.setattr(Matcher, "extract", recorded)
    docs, main = {}, {}
    for look_ahead in (True, False):
        threads.clear()
        out = tmp_path / f"out_{look_ahead}"
        docs[look_ahead] = localize_tool().run(
            compose(_args(path_scene, out, f"data.sequence={path_scene['frames']}",
                          "output.video=false", "output.trajectory_plot=false",
                          f"tracking.look_ahead={str(look_ahead).lower()}")),
            out,
        )
        ahead = threads.count("frame-prefetch")
        assert ahead == (N_FRAMES if look_ahead else 0), threads
        main[look_ahead] = threads.count("MainThread")
        rows = docs[look_ahead]["photos"]
        assert all(r["status"] == "ok" for r in rows), [r["reason"] for r in rows]
        assert not any("patch_search" in r["details"] for r in rows)  # off by default
    # the main thread extracted the renders alone: the query's features came from the memo
    assert main[True] == main[False] - N_FRAMES
    a, b = docs[True]["photos"], docs[False]["photos"]
    assert [r["name"] for r in a] == [r["name"] for r in b]
    for ra, rb in zip(a, b):
        assert np.allclose(ra["c2w"], rb["c2w"], atol=1e-9), ra["name"]


def test_tracking_an_mp4_every_second_frame_with_its_video(path_scene, tmp_path):
    out = tmp_path / "out"
    doc = localize_tool().run(
        compose(
            _args(
                path_scene,
                out,
                f"data.sequence={path_scene['mp4']}",
                "data.every=2",
                "output.export=[nerfstudio]",
            )
        ),
        out,
    )
    rows = doc["photos"]
    assert [r["name"] for r in rows] == ["frame_000000", "frame_000002", "frame_000004"]
    assert [r["index"] for r in rows] == [0, 2, 4]
    for r in rows:  # compressed frames: looser than the PNGs
        assert r["status"] != "failed" and r["rot_err_deg"] < 1.0 and r["trans_err_rel"] < 0.01, r
    w, h, n, _ = video.video_info(out / "tracking.mp4")
    assert n == 3 and h == SIZE and w >= 4 * SIZE
    ns = json.loads((out / "exports" / "transforms.json").read_text())
    assert [f["file_path"] for f in ns["frames"]] == [
        r["name"] for r in rows if r["status"] != "failed"
    ]
    # run again on the same folder: nothing is redone
    again = localize_tool().run(
        compose(
            _args(
                path_scene,
                out,
                f"data.sequence={path_scene['mp4']}",
                "data.every=2",
                "output.video=false",
                "output.trajectory_plot=false",
            )
        ),
        out,
    )
    assert again["summary"]["done_now"] == 0 and again["summary"]["skipped"] == 3
    assert again["photos"] == rows


# ------------------------------------------------------------------- a portrait camera (issue 16)

PORTRAIT = (64, 96)  # W x H of the model's portrait camera (even sides: H.264 needs them)


@pytest.fixture(scope="module")
def portrait_scene(tmp_path_factory):
    """A demo model whose cameras.json also lists a portrait camera, and a video taken with it.

    The square demo cameras stay first (the model's training side is theirs); the portrait entry
    ``portrait`` comes last. Three frames along an arc, rendered at the portrait camera's size.
    """
    from icomma_plugin.camera import Intrinsics
    from icomma_plugin.io.cameras_json import CameraEntry, read_cameras_json, write_cameras_json

    root = tmp_path_factory.mktemp("portrait")
    s, model = demo_model(root / "model", SIZE)
    W, H = PORTRAIT
    fx = 80.0
    intr = Intrinsics(W, H, fx, fx)
    cams = read_cameras_json(s.path / "cameras.json")
    cams.append(CameraEntry(len(cams), "portrait", W, H, orbit_c2w(0.4, 2.0), fx, fx))
    write_cameras_json(s.path / "cameras.json", cams)
    gts, frames = {}, []
    for i in range(3):
        az = 0.4 + 0.05 * i
        c2w = orbit_c2w(az, 2.0)
        frames.append(photo(model, intr, c2w))
        gts[f"frame_{i:06d}"] = c2w.tolist()
    (root / "gt.json").write_text(json.dumps(gts))
    start = np.asarray(gts["frame_000000"])
    start[:3, 3] += 0.05
    np.savetxt(root / "start.txt", start)
    mp4 = video.write_video(root / "portrait.mp4", frames, fps=5)
    return {"model": s.path, "gt": root / "gt.json", "start": root / "start.txt", "mp4": mp4,
            "fx": fx}


def test_a_video_of_a_portrait_camera_is_tracked(portrait_scene, tmp_path):
    """data.intrinsics.camera=<portrait camera> with a video of its size tracks (issue 16, bug 1).

    Before: the sequence path checked the camera against a dummy 1000x1000 photo and stopped at
    once ("the photo is 1000x1000 but data.intrinsics.camera=... is 64x96 (another aspect
    ratio)").
    """
    ps = portrait_scene
    w, h, n, _ = video.video_info(ps["mp4"])
    assert (w, h, n) == (*PORTRAIT, 3)
    out = tmp_path / "out"
    cfg = compose([
        "data=model_folder", f"data.model_path={ps['model']}",
        "data.intrinsics.camera=portrait", f"data.sequence={ps['mp4']}",
        f"data.gt.poses_file={ps['gt']}", f"data.init.c2w_file={ps['start']}",
        f"output.dir={out}", "output.progress=false", "output.video=false",
        "output.trajectory_plot=false", "threads=1",
    ])
    doc = localize_tool().run(cfg, out)
    rows = doc["photos"]
    assert [r["name"] for r in rows] == [f"frame_{i:06d}" for i in range(3)]
    for r in rows:
        assert r["status"] != "failed", r["reason"]
        assert r["rot_err_deg"] < 1.0 and r["trans_err_rel"] < 0.01, r
        intr = r["intrinsics"]
        assert (intr["width"], intr["height"]) == PORTRAIT
        assert intr["fx"] == pytest.approx(ps["fx"]) and intr["fy"] == pytest.approx(ps["fx"])


# ----------------------------------------------------------- the focal length from the frames


class _LensWorker(_FakeWorker):
    """Every frame `ok`; its matches prefer the lens's focal length (``f_true``) to the query's."""

    f_true = 8.8

    def result(self, query, init_c2w, fast):
        res = super().result(query, init_c2w, fast)
        res.verdict.signals["focal"] = {"scale": self.f_true / query.intrinsics.fx,
                                        "rms_px": 0.5, "rms_px_given": 0.6}
        self.calls[-1] += (round(query.intrinsics.fx, 6),)
        return res


def test_an_adopted_focal_length_relocalizes_the_window_and_survives_a_resume(tmp_path):
    from icomma_plugin.camera import Intrinsics

    folder = tmp_path / "frames"
    folder.mkdir()
    truth = {}
    for i in range(6):
        Image.new("RGB", (8, 8)).save(folder / f"g{i}.png")
        truth[f"g{i}.png"] = np.eye(4)
    cfg = TrackingConfig(focal_window=3)
    w = _LensWorker(truth)
    ledger = PosesLedger(tmp_path / "out", {"kind": "sequence"}, 6)
    summ = track(w, FrameSource.open(str(folder), limit=4), ledger,
                 lambda s: Intrinsics(8, 8, 8.0, 8.0), init_c2w=np.eye(4), cfg=cfg)
    # three frames at the given 8.0 agree on 8.8: adopted, and those three localized again
    assert [(c[0], c[3]) for c in w.calls] == [
        ("g0.png", 8.0), ("g1.png", 8.0), ("g2.png", 8.0),
        ("g0.png", 8.8), ("g1.png", 8.8), ("g2.png", 8.8), ("g3.png", 8.8)]
    assert summ.focal_scale == pytest.approx(1.1) and summ.focal_adoptions == 1
    assert summ.redone == 3 and summ.done_now == 4 and summ.fast_ok == 4
    rows = ledger.all_rows()
    assert [r["camera_focal_scale"] for r in rows] == pytest.approx([1.1] * 4)
    assert [r["intrinsics"]["fx"] for r in rows] == pytest.approx([8.8] * 4)
    # a resumed run goes on with the focal length adopted
    w2 = _LensWorker(truth)
    summ2 = track(w2, FrameSource.open(str(folder)),
                  PosesLedger(tmp_path / "out", {"kind": "sequence"}, 6),
                  lambda s: Intrinsics(8, 8, 8.0, 8.0), init_c2w=np.eye(4), cfg=cfg)
    assert [(c[0], c[3]) for c in w2.calls] == [("g4.png", 8.8), ("g5.png", 8.8)]
    assert summ2.focal_scale == pytest.approx(1.1) and summ2.focal_adoptions == 0
    # off: the given focal length throughout
    w3 = _LensWorker(truth)
    track(w3, FrameSource.open(str(folder)), PosesLedger(tmp_path / "out3", {"kind": "sequence"},
          6), lambda s: Intrinsics(8, 8, 8.0, 8.0), init_c2w=np.eye(4),
          cfg=TrackingConfig(focal_window=3, focal_from_frames=False))
    assert {c[3] for c in w3.calls} == {8.0} and len(w3.calls) == 6


class _DriftingLensWorker(_LensWorker):
    """The refits of the frames after the 10th prefer 0.6 % more: a bias along the path."""

    def result(self, query, init_c2w, fast):
        self.f_true = 8.8 * (1.006 if int(query.name[1:].split(".")[0]) >= 10 else 1.0)
        return super().result(query, init_c2w, fast)


@pytest.mark.parametrize("history, adoptions", [(100, 1), (3, 2)])
def test_the_frames_since_the_last_adoption_decide_the_next(tmp_path, history, adoptions):
    """A bias in a stretch of the path does not move the estimate.

    The frames since the last adoption decide; the last few alone would follow the bias.
    """
    from icomma_plugin.camera import Intrinsics

    folder = tmp_path / "frames"
    folder.mkdir()
    truth = {}
    for i in range(16):
        Image.new("RGB", (8, 8)).save(folder / f"g{i}.png")
        truth[f"g{i}.png"] = np.eye(4)
    summ = track(_DriftingLensWorker(truth), FrameSource.open(str(folder)),
                 PosesLedger(tmp_path / "out", {"kind": "sequence"}, 16),
                 lambda s: Intrinsics(8, 8, 8.0, 8.0), init_c2w=np.eye(4),
                 cfg=TrackingConfig(focal_window=3, focal_history=history))
    assert summ.focal_adoptions == adoptions
    assert summ.focal_scale == pytest.approx(1.1 if adoptions == 1 else 1.1 * 1.006)


def test_tracking_config_names_bad_focal_settings():
    with pytest.raises(ValueError, match="tracking.focal_window"):
        TrackingConfig(focal_window=1)
    with pytest.raises(ValueError, match="tracking.focal_agree"):
        TrackingConfig(focal_agree=0.3)
    with pytest.raises(ValueError, match="tracking.focal_settle"):
        TrackingConfig(focal_settle=0.05, focal_min_change=0.01)
    with pytest.raises(ValueError, match="tracking.focal_history"):
        TrackingConfig(focal_window=10, focal_history=5)


def test_a_sequence_given_a_wrong_focal_length_finds_it_from_its_frames(path_scene, tmp_path):
    """Given 8 % too short a focal length, the frames agree on it and the sequence adopts it.

    One frame's check alone does not ask (the tracking mode's frames are judged on their geometric
    render), so without the estimate every frame is `ok` with the distance off; with it the
    frames are localized again with the focal length found.
    """
    fx = path_scene["fx"] * 0.92
    docs = {}
    for on in (False, True):
        out = tmp_path / f"out_{on}"
        docs[on] = localize_tool().run(compose(_args(
            path_scene, out, f"data.sequence={path_scene['frames']}", "output.video=false",
            "output.trajectory_plot=false", "data.intrinsics.camera=null",
            f"data.intrinsics.fx={fx}", f"data.intrinsics.fy={fx}",
            f"tracking.focal_from_frames={str(on).lower()}", "tracking.focal_window=3")), out)
    check_focal_found(docs, path_scene["fx"], 0.92, "frames")
    assert (tmp_path / "out_True" / "focal.png").is_file()
    assert not (tmp_path / "out_False" / "focal.png").exists()
