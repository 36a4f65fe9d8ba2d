"""Batches (data.queries), end to end through the tool.

Inputs (photo lists, poses files), poses.json / poses.csv content, per-photo failures that do not
stop the batch, one-line errors, exports read back, resume after a kill, worker processes, and
shards through submitit's local executor (the SLURM code path).

Photos are rendered from a 100x100 demo scene at known poses, so the truth is known.
"""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from icomma_plugin.app.inputs import ProblemError, list_photos
from icomma_plugin.app.ledger import CSV_COLUMNS, LedgerError, PosesLedger
from icomma_plugin.io.poses_file import PosesFileError, read_poses_file
from tests.helpers.demo import demo_model, photo
from tests.helpers.paths import REPO
from tests.helpers.tools import LOCALIZE_TOOL, compose, localize_tool

SIZE = 100

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 100x100 demo model folder, 6 photos rendered around it, their true poses (JSON)."""
    from icomma_plugin.pose.convert import look_at_c2w

    root = tmp_path_factory.mktemp("batch")
    s, model = demo_model(root / "model", SIZE)
    photos = root / "photos"
    photos.mkdir()
    gt = {}
    for i in range(6):
        az = 0.3 + 0.9 * i
        c2w = look_at_c2w(
            np.array([3.8 * math.cos(az), 3.8 * math.sin(az), 2.0]), np.array([0.0, 0.0, 0.4])
        )
        Image.fromarray(photo(model, s.intrinsics, c2w)).save(photos / f"p{i}.png")
        gt[f"p{i}.png"] = c2w.tolist()
    (root / "gt.json").write_text(json.dumps(gt))
    return {
        "root": root,
        "model": s.path,
        "photos": photos,
        "gt": root / "gt.json",
        "gt_poses": gt,
        "scale": s.scene_scale,
    }


def _base(scene, out: Path, *extra):
    return [
        "data=model_folder",
        f"data.model_path={scene['model']}",
        f"data.queries={scene['photos']}",
        "data.intrinsics.camera=ring_000",
        f"data.gt.poses_file={scene['gt']}",
        f"output.dir={out}",
        "output.progress=false",
        "threads=1",
        *extra,
    ]


def _cli(args, timeout=600, **kw):
    env = dict(os.environ, PYTHONWARNINGS="ignore", HYDRA_FULL_ERROR="0", OMP_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, str(LOCALIZE_TOOL), *args],
        cwd=str(REPO),
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        **kw,
    )


# ------------------------------------------------------------------------------------ inputs


def test_list_photos_folder_glob_and_list_file(scene, tmp_path):
    folder = list_photos(str(scene["photos"]))
    assert folder.names == [f"p{i}.png" for i in range(6)]
    glob = list_photos(str(scene["photos"] / "p[13].png"))
    assert glob.names == ["p1.png", "p3.png"]
    lst = tmp_path / "list.txt"
    lst.write_text(
        f"# two photos\n{scene['photos'] / 'p4.png'}\n\n"
        f"{os.path.relpath(scene['photos'] / 'p0.png', tmp_path)}\n"
    )
    assert list_photos(str(lst)).names == ["p4.png", "p0.png"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ProblemError, match="data.queries: no image files"):
        list_photos(str(tmp_path / "empty"))
    with pytest.raises(ProblemError, match="data.queries: no image files match"):
        list_photos(str(tmp_path / "*.jpg"))
    lst.write_text("nope.png\n")
    with pytest.raises(ProblemError, match="line 1 of the list file"):
        list_photos(str(lst))


def test_poses_files_json_text_cameras_json_and_poses_json(scene, tmp_path):
    gt = scene["gt_poses"]
    table = read_poses_file(scene["gt"], "data.init.poses_file")
    assert len(table) == 6 and np.allclose(table.get("p2.png"), gt["p2.png"])
    assert (
        np.allclose(table.get("p2"), gt["p2.png"]) and table.get("sub/p2.png") is not None
    )  # stem, basename
    assert table.get("p9.png") is None
    txt = tmp_path / "poses.txt"
    txt.write_text(
        "# name and 16 numbers\n"
        + "\n".join(
            f"{k} " + " ".join(repr(float(v)) for v in np.asarray(m).ravel()) for k, m in gt.items()
        )
        + "\n"
    )
    t2 = read_poses_file(txt, "data.init.poses_file")
    assert all(np.array_equal(t2.get(k), np.asarray(v)) for k, v in gt.items())
    from icomma_plugin.io.cameras_json import read_cameras_json

    cams = read_cameras_json(Path(scene["model"]) / "cameras.json")
    t3 = read_poses_file(Path(scene["model"]) / "cameras.json", "data.init.cameras_json")
    assert np.allclose(t3.get(cams[3].img_name), cams[3].c2w)
    bad = tmp_path / "bad.txt"
    bad.write_text("p0.png 1 2 3\n")
    with pytest.raises(PosesFileError,
                       match=r"data.init.poses_file: line 1 .*16 \(or 12\) numbers"):
        read_poses_file(bad, "data.init.poses_file")
    bad.write_text("{not json")
    with pytest.raises(PosesFileError, match="data.gt.poses_file: .* not valid JSON"):
        read_poses_file(bad, "data.gt.poses_file")
    (tmp_path / "skew.json").write_text(json.dumps({"a": (2 * np.eye(4)).tolist()}))
    with pytest.raises(PosesFileError, match="entry 'a' must be a rigid 4x4"):
        read_poses_file(tmp_path / "skew.json", "data.init.poses_file")


def test_ledger_refuses_another_runs_folder(tmp_path):
    led = PosesLedger(tmp_path, {"kind": "batch", "model_path": "/a", "queries": "/q"}, total=1)
    led.record({"index": 0, "name": "x.png", "status": "ok"})
    assert json.loads((tmp_path / "poses.json").read_text())["status"] == "complete"
    with pytest.raises(LedgerError, match="belongs to another run .*model_path"):
        PosesLedger(tmp_path, {"kind": "batch", "model_path": "/b", "queries": "/q"}, total=1)
    (tmp_path / "poses.json").write_text("{trunc")
    with pytest.raises(LedgerError, match="cannot read"):
        PosesLedger(tmp_path, {"kind": "batch", "model_path": "/a", "queries": "/q"}, total=1)


# ------------------------------------------------------------------------------------ one batch


def test_batch_poses_json_csv_exports_and_bad_photos(scene, tmp_path):
    """No start pose; a photo of another size and an unreadable one fail alone.

    The others localize.
    """
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in (0, 1):
        (photos / f"p{i}.png").write_bytes((scene["photos"] / f"p{i}.png").read_bytes())
    Image.new("RGB", (80, SIZE)).save(photos / "small.png")
    (photos / "broken.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    cfg = compose(
        [
            "data=model_folder",
            f"data.model_path={scene['model']}",
            f"data.queries={photos}",
            "data.intrinsics.camera=ring_000",
            f"data.gt.poses_file={scene['gt']}",
            "data.init=none",
            "output.progress=false",
            "output.export=[cameras_json,colmap,nerfstudio]",
            "output.photo_folders=true",
            "output.match_lines=false",
            "output.convergence_plot=false",
        ]
    )
    doc = localize_tool().run(cfg, out)
    assert doc == json.loads((out / "poses.json").read_text()) | {"summary": doc["summary"]}
    rows = {r["name"]: r for r in doc["photos"]}
    assert set(rows) == {"broken.png", "p0.png", "p1.png", "small.png"}
    assert doc["status"] == "complete" and doc["total"] == 4 and doc["done"] == 4
    assert sum(doc["counts"].values()) == 4 and doc["counts"]["failed"] >= 2
    assert (
        rows["small.png"]["status"] == "failed"
        and "80x100" in rows["small.png"]["error"]
        and "data.intrinsics.camera" in rows["small.png"]["error"]
    )
    assert rows["broken.png"]["status"] == "failed" and "broken.png" in rows["broken.png"]["error"]
    for n in ("p0.png", "p1.png"):
        r = rows[n]
        assert r["status"] == "ok", r["reason"]
        assert r["init_c2w"] is None and r["error"] is None
        assert r["rot_err_deg"] < 0.1 and r["trans_err_rel"] < 1e-3
        assert np.allclose(r["gt_c2w"], scene["gt_poses"][n])
        assert (out / r["folder"] / "result.json").is_file() and (
            out / r["folder"] / "overlay_final.png"
        ).is_file()
        assert (out / r["thumb"]).is_file()
    assert (out / "contact_sheet.png").is_file()
    # one CSV row per photo, the same numbers as poses.json
    with open(out / "poses.csv") as fh:
        table = list(csv.DictReader(fh))
    assert tuple(table[0].keys()) == CSV_COLUMNS and len(table) == 4
    for t in table:
        r = rows[t["name"]]
        assert t["status"] == r["status"]
        assert (t["rot_err_deg"] == "") == (r["rot_err_deg"] is None)
        if r["rot_err_deg"] is not None:
            assert (
                float(t["rot_err_deg"]) == r["rot_err_deg"] and float(t["seconds"]) == r["seconds"]
            )
    # exports hold the estimated poses (only ok / uncertain), read back with our readers
    from icomma_plugin.io.cameras_json import read_cameras_json
    from icomma_plugin.io.datasets import read_colmap

    cams = {e.img_name: e for e in read_cameras_json(out / "exports" / "cameras.json")}
    good = {n for n, r in rows.items() if r["status"] != "failed"}
    assert set(cams) == good
    for n in good:
        assert np.allclose(cams[n].c2w, rows[n]["c2w"], atol=1e-9)
    img_dir = out / "exports" / "colmap" / "images"  # sparse/0 beside images/: a COLMAP dataset
    img_dir.mkdir()
    for n in good:
        (img_dir / n).write_bytes((photos / n).read_bytes())
    views = {v.name: v for v in read_colmap(out / "exports" / "colmap", eval=False).train}
    assert set(views) == good
    for n in good:
        assert np.allclose(views[n].c2w, rows[n]["c2w"], atol=1e-9)
    ns = json.loads((out / "exports" / "transforms.json").read_text())
    assert {f["file_path"] for f in ns["frames"]} == good


def test_per_photo_start_poses_and_missing(scene, tmp_path):
    """data.init.poses_file: a photo the file lacks fails (missing=fail) with a reason."""
    starts = {k: v for k, v in scene["gt_poses"].items() if k != "p1.png"}
    pf = tmp_path / "starts.json"
    pf.write_text(json.dumps(starts))
    out = tmp_path / "out"
    cfg = compose(
        _base(
            scene, out, "data.limit=2", f"data.init.poses_file={pf}", "output.contact_sheet=false"
        )
    )
    doc = localize_tool().run(cfg, out)
    rows = {r["name"]: r for r in doc["photos"]}
    assert rows["p0.png"]["status"] != "failed" and np.allclose(
        rows["p0.png"]["init_c2w"], starts["p0.png"]
    )
    assert rows["p0.png"]["init_rot_err_deg"] < 1e-6
    assert (
        rows["p1.png"]["status"] == "failed"
        and "no start pose for 'p1.png'" in rows["p1.png"]["error"]
    )
    assert "data.init.missing=none" in rows["p1.png"]["error"]


def test_cli_one_line_errors(scene, tmp_path):
    (tmp_path / "empty").mkdir()
    p = _cli(_base(scene, tmp_path / "o1", f"data.queries={tmp_path / 'empty'}", "data.init=none"))
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr[-2000:]
    err = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "data.queries" in err[0] and "no image files" in err[0]
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2")
    p = _cli(_base(scene, tmp_path / "o2", f"data.init.poses_file={bad}"))
    err = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    assert p.returncode == 2 and len(err) == 1 and "data.init.poses_file" in err[0], p.stderr[
        -2000:
    ]
    p = _cli([a for a in _base(scene, tmp_path / "o3", "data.init=none") if "intrinsics" not in a])
    err = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    assert p.returncode == 2 and len(err) == 1 and "data.intrinsics.fx" in err[0], p.stderr[-2000:]


# ------------------------------------------------------------------------------------ resume


def test_resume_after_kill_redoes_no_finished_photo(scene, tmp_path):
    out = tmp_path / "out"
    args = _base(scene, out, "data.init=none", "output.contact_sheet=false")
    env = dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS="1")
    proc = subprocess.Popen(
        [sys.executable, str(LOCALIZE_TOOL), *args],
        cwd=str(REPO),
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    first = None
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            if (out / "poses.json").is_file():
                doc = json.loads((out / "poses.json").read_text())  # never half-written
                if doc["done"] >= 2:
                    os.killpg(proc.pid, signal.SIGKILL)
                    first = doc
                    break
            time.sleep(0.05)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert first is not None, "the batch finished or stalled before it could be killed"
    killed = json.loads((out / "poses.json").read_text())
    assert killed["status"] == "running" and 2 <= killed["done"] < 6
    p = _cli(args)
    assert p.returncode == 0, p.stderr[-2000:]
    final = json.loads((out / "poses.json").read_text())
    assert final["status"] == "complete" and final["done"] == 6
    assert [r["name"] for r in final["photos"]] == [f"p{i}.png" for i in range(6)]
    before = {r["name"]: r for r in killed["photos"]}
    after = {r["name"]: r for r in final["photos"]}
    for n, r in before.items():  # the same rows, from the same (killed) process: not redone
        assert after[n] == r
    assert {after[n]["worker"] for n in after if n not in before} != {
        r["worker"] for r in before.values()
    }
    assert f"{len(before)} skipped" in p.stdout


# ------------------------------------------------------------------------------------ parallel


def test_two_worker_processes(scene, tmp_path):
    out = tmp_path / "out"
    cfg = compose(
        _base(
            scene, out, "data.limit=4", "data.init=none", "workers=2", "output.contact_sheet=false"
        )
    )
    doc = localize_tool().run(cfg, out)
    assert doc["done"] == 4 and [r["index"] for r in doc["photos"]] == [0, 1, 2, 3]
    pids = {r["worker"] for r in doc["photos"]}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2
    assert all(r["status"] != "failed" for r in doc["photos"]), [r["reason"] for r in doc["photos"]]


def test_submitit_local_shards_merge_into_one_poses_json(scene, tmp_path):
    sweep = tmp_path / "sweep"
    args = [
        "-m",
        "hydra/launcher=submitit_local",
        "hydra.launcher.timeout_min=10",
        f"hydra.sweep.dir={sweep}",
        "data=model_folder",
        f"data.model_path={scene['model']}",
        f"data.queries={scene['photos']}",
        "data.limit=4",
        "data.intrinsics.camera=ring_000",
        f"data.gt.poses_file={scene['gt']}",
        f"data.init.poses_file={scene['gt']}",
        "output.progress=false",
        "threads=1",
        "data.shard=0,1",
        "data.num_shards=2",
    ]
    p = _cli(args)
    assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-3000:])
    assert (sweep / ".submitit").is_dir()  # it went through submitit's executor
    doc = json.loads((sweep / "poses.json").read_text())
    assert doc["status"] == "complete" and doc["done"] == 4
    assert [(r["index"], r["shard"]) for r in doc["photos"]] == [(0, 0), (1, 1), (2, 0), (3, 1)]
    parts = sorted(p.name for p in (sweep / "parts").iterdir())
    assert parts == [f"shard-00{i}-of-002.{e}" for i in (0, 1) for e in ("json", "jsonl")]
    assert all(r["status"] != "failed" for r in doc["photos"])
    with open(sweep / "poses.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 4


def test_journal_keeps_every_row_between_rewrites(tmp_path):
    """Past rewrite_rows, poses.json is rewritten only now and then; a kill loses no row.

    The journal has every row, a line cut short by a kill is ignored, and the next run reads it all.
    """
    run = {"kind": "batch", "model_path": "/m", "queries": "/q"}
    led = PosesLedger(tmp_path, run, total=5, rewrite_rows=1, rewrite_seconds=3600)
    for i in range(4):
        led.record({"index": i, "name": f"p{i}.png", "status": "ok", "c2w": np.eye(4).tolist()})
    assert json.loads((tmp_path / "poses.json").read_text())["done"] == 1  # rewritten once
    with open(tmp_path / "poses.jsonl", "a") as fh:
        fh.write('{"index": 4, "name": "p4.png", "sta')  # killed mid-line
    again = PosesLedger(tmp_path, run, total=5)
    assert sorted(again.finished()) == [f"p{i}.png" for i in range(4)]
    again.record({"index": 4, "name": "p4.png", "status": "failed"})
    doc = json.loads((tmp_path / "poses.json").read_text())
    assert doc["status"] == "complete" and [r["name"] for r in doc["photos"]] == [
        f"p{i}.png" for i in range(5)
    ]
    with pytest.raises(LedgerError, match="belongs to another run"):
        (tmp_path / "poses.json").unlink()
        PosesLedger(tmp_path, dict(run, model_path="/other"), total=5)


def test_the_verdict_counts_follow_every_row_without_a_recount(tmp_path, monkeypatch):
    """The verdict counts, asked after every photo by the progress line, follow ``record``.

    A photo recorded again moves its count, earlier runs' rows count, and between rewrites
    nothing merges or sorts every row again (a recount each photo made a batch quadratic).
    """
    import icomma_plugin.app.ledger as ledger_mod

    run = {"kind": "batch", "model_path": "/m", "queries": "/q"}
    led = PosesLedger(tmp_path, run, total=6, rewrite_rows=1, rewrite_seconds=3600)
    led.record({"index": 0, "name": "p0.png", "status": "failed"})
    again = PosesLedger(tmp_path, run, total=6, rewrite_rows=1, rewrite_seconds=3600)
    assert again.counts() == {"ok": 0, "uncertain": 0, "failed": 1}
    recounts = []
    real = ledger_mod.counts_of
    monkeypatch.setattr(ledger_mod, "counts_of", lambda rows: recounts.append(1) or real(rows))
    monkeypatch.setattr(again, "all_rows", lambda: pytest.fail("every row merged and sorted"))
    again._last_write = float("inf")  # no rewrite due: the journal takes the rows
    statuses = ["ok", "uncertain", "ok", "failed", "ok"]
    for i, status in enumerate(statuses, start=1):
        again.record({"index": i, "name": f"p{i}.png", "status": status})
        assert again.counts() == real([{"status": "failed"}] + [{"status": x}
                                                                 for x in statuses[:i]])
    again.record({"index": 0, "name": "p0.png", "status": "ok"})  # the failed photo, redone
    again.record({"index": 2, "name": "p2.png", "status": "ok"})  # a photo localized again
    assert again.counts() == {"ok": 5, "uncertain": 0, "failed": 1}
    assert recounts == []
    monkeypatch.undo()
    assert again.counts() == real(again.all_rows())


@pytest.mark.parametrize("least, share, every", [(0, 0.1, 20), (0, 0.5, 4), (0, 1.0, 2),
                                                  (0.4, 1.0, 2), (3, 1.0, 6)])
def test_rewrites_take_a_bounded_share_of_the_run(tmp_path, monkeypatch, least, share, every):
    """poses.json is rewritten once the time since the last rewrite is 1/share times its cost.

    And at least ``min_rewrite_seconds`` since. A fake clock: every rewrite takes 1 s, every
    photo 0.5 s; the journal still has every row.
    """
    import icomma_plugin.app.ledger as ledger_mod

    clock = [0.0]
    monkeypatch.setattr(ledger_mod.time, "monotonic", lambda: clock[0])
    led = PosesLedger(tmp_path, {"kind": "batch", "model_path": "/m", "queries": "/q"},
                      total=41, min_rewrite_seconds=least, max_rewrite_share=share)
    writes = []
    real = led._write_merged

    def timed_write():
        writes.append(len(led.rows))
        real()
        clock[0] += 1.0

    monkeypatch.setattr(led, "_write_merged", timed_write)
    for i in range(41):
        clock[0] += 0.5
        led.record({"index": i, "name": f"p{i}.png", "status": "ok"})
    assert writes == list(range(1, 42, every))
    assert len((tmp_path / "poses.jsonl").read_text().splitlines()) == 42  # run line + 41 rows
    led.close()
    assert json.loads((tmp_path / "poses.json").read_text())["done"] == 41
    with pytest.raises(ValueError, match=r"max_rewrite_share must be a finite number in \(0, 1\]"):
        PosesLedger(tmp_path / "x", {"kind": "batch"}, total=1, max_rewrite_share=0)
    with pytest.raises(ValueError, match="min_rewrite_seconds must be a finite number >= 0"):
        PosesLedger(tmp_path / "x", {"kind": "batch"}, total=1, min_rewrite_seconds=-1)


# ------------------------------------------------------------- the candidate index (issue 16)

FOCAL_FACTORS = (0.95, 1.0, 1.05)  # per-image focal lengths ~10 % apart, as COLMAP gives


@pytest.fixture(scope="module")
def colmap_photos(scene, tmp_path_factory):
    """A COLMAP dataset folder of 3 photos of the batch model, each with its own camera.

    Focal lengths 0.95 / 1.0 / 1.05 x the model's (per-image intrinsics, as ../shared/data/bird
    has), photos rendered with them at the model's 100x100, poses around the scene.
    """
    from icomma_plugin.camera import Intrinsics
    from icomma_plugin.io.cameras_json import read_cameras_json
    from icomma_plugin.io.model_folder import load_model_folder
    from icomma_plugin.pose.convert import look_at_c2w
    from tests.helpers.colmap import write_colmap_dataset

    model = load_model_folder(scene["model"]).model
    f0 = read_cameras_json(Path(scene["model"]) / "cameras.json")[0].fx
    photos = []
    for i, k in enumerate(FOCAL_FACTORS):
        az = 0.3 + 0.9 * i
        c2w = look_at_c2w(
            np.array([3.8 * math.cos(az), 3.8 * math.sin(az), 2.0]), np.array([0.0, 0.0, 0.4])
        )
        rgb = photo(model, Intrinsics(SIZE, SIZE, f0 * k, f0 * k), c2w)
        photos.append((f"c{i}.png", rgb, c2w, f0 * k, f0 * k))
    root = tmp_path_factory.mktemp("colmap") / "dataset"
    write_colmap_dataset(root, photos)
    return {"root": root, "f0": f0, "c2w": {p[0]: p[2] for p in photos}}


def _colmap_plan(scene, colmap_photos):
    from icomma_plugin.app.batch import plan_batch

    plan, mf = plan_batch({"kind": "model_folder", "model_path": str(scene["model"]),
                           "queries": str(colmap_photos["root"]), "init": "none"})
    fxs = sorted(t.intrinsics.fx for t in plan.tasks)
    assert [t.name for t in plan.tasks] == ["c0.png", "c1.png", "c2.png"]
    assert fxs == pytest.approx([colmap_photos["f0"] * k for k in FOCAL_FACTORS])
    assert all(t.init_c2w is None and t.error is None for t in plan.tasks)
    return plan, mf


def test_a_colmap_batch_builds_the_candidate_index_once(scene, colmap_photos, tmp_path):
    """Photos whose focal lengths differ by 10 % share one candidate index (issue 16, bug 2).

    Before: the worker kept one candidate set per photo intrinsics, so every photo of a COLMAP
    dataset (one camera per image) rendered every candidate view again.
    """
    from icomma_plugin.app.batch import BatchWorker, WorkerSetup
    from icomma_plugin.localize import RobustConfig
    from icomma_plugin.matchers import make_matcher

    plan, mf = _colmap_plan(scene, colmap_photos)
    cache = tmp_path / "cache"
    setup = WorkerSetup(model_path=plan.model_path, method=RobustConfig(), matcher=None,
                        out_dir=str(tmp_path / "out"), thumbs=False, cache_dir=str(cache))
    worker = BatchWorker(setup, mf, make_matcher("xfeat"))
    rows = [worker.run(t) for t in plan.tasks]
    for r in rows:
        assert r["status"] == "ok", (r["name"], r["reason"])
        assert r["rot_err_deg"] < 0.1 and r["trans_err_rel"] < 1e-3, r
        assert np.allclose(r["gt_c2w"], colmap_photos["c2w"][r["name"]], atol=1e-9)
    assert worker.localizer.candidate_builds == 1
    assert len(list(cache.rglob("*.pt"))) == 1


def test_a_second_call_without_a_start_loads_the_candidate_index(scene, colmap_photos, tmp_path):
    """A second single-photo call without a start pose reads the index from disk (bug 2).

    Before: every call rendered and described every candidate view again.
    """
    from icomma_plugin.localize import Localizer, Query
    from icomma_plugin.matchers import make_matcher

    plan, mf = _colmap_plan(scene, colmap_photos)
    task = plan.tasks[0]
    query = Query.from_view(task.view, torch.zeros(3))
    matcher = make_matcher("xfeat")
    results, builds = [], []
    for _ in range(2):  # two Localizers, as two runs of the tool
        loc = Localizer.from_model_folder(mf, matcher, cache_dir=tmp_path / "cache")
        results.append(loc.localize(query, gt_c2w=task.gt_c2w))
        builds.append(loc.candidate_builds)
    first, second = results
    assert builds == [1, 0]
    # the ranking is charged to "candidates" in both; the renders only in the first (measured
    # 4.25 s vs 0.66 s here; the baseline's two calls 5.59 s and 5.57 s)
    assert second.stage_seconds["candidates"] < 0.5 * first.stage_seconds["candidates"]
    assert first.verdict.status == second.verdict.status == "ok"
    assert first.rot_err_deg < 0.1 and np.array_equal(first.c2w, second.c2w)


def test_a_distortion_for_dataset_views_is_refused(scene, colmap_photos):
    """data.intrinsics.distortion is for photo files: a dataset's views are undistorted already."""
    from icomma_plugin.app.batch import plan_batch
    from icomma_plugin.app.inputs import ProblemError

    data = {"kind": "model_folder", "model_path": str(scene["model"]),
            "queries": str(colmap_photos["root"]), "init": "none",
            "intrinsics": {"distortion": [0.1, 0.0, 0.0, 0.0]}}
    with pytest.raises(ProblemError, match="data.intrinsics.distortion is for photo files"):
        plan_batch(data)
    data["intrinsics"]["distortion"] = [0.0, 0.0, 0.0, 0.0]  # none at all: planned as before
    assert len(plan_batch(data)[0].tasks) == 3
