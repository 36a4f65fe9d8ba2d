"""icomma_plugin.io.export: each format read back with our readers, conventions, bad input.

Read back, every format gives the same poses and intrinsics (1e-9); plus the files' conventions,
and bad input.
"""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from PIL import Image

from icomma_plugin.camera import Intrinsics
from icomma_plugin.io.cameras_json import CameraEntry, read_cameras_json
from icomma_plugin.io.datasets import read_colmap, read_dataset
from icomma_plugin.io.export import (
    FORMATS,
    NamedPose,
    as_named_poses,
    export_cameras_json,
    export_colmap,
    export_nerfstudio,
    export_poses,
)
from icomma_plugin.pose.convert import look_at_c2w
from icomma_plugin.pose.se3 import se3_exp

TOL = 1e-9


def _random_c2w(rng) -> np.ndarray:
    import torch

    xi = torch.from_numpy(rng.normal(size=6) * np.array([2.0, 2.0, 2.0, 1.5, 1.5, 1.5]))
    return se3_exp(xi.double()).numpy()


def _poses(n=4, mixed=False, seed=0):
    """n rigid poses named images/frame_<i>.png; `mixed`: two intrinsics, one off-centre."""
    rng = np.random.default_rng(seed)
    shared = Intrinsics(48, 32, 41.123456789012, 40.5)
    other = Intrinsics(40, 30, 35.25, 36.0, cx=21.3, cy=13.7)
    out = []
    for i in range(n):
        intr = other if (mixed and i % 2) else shared
        out.append(NamedPose(f"images/frame_{i:03d}.png", _random_c2w(rng), intr))
    # an exact rotation with large translation (a far camera), and an identity rotation
    out[0] = NamedPose(out[0].name, look_at_c2w([123.456, -7.0, 3.25], [0.0, 0.0, 0.0]),
                       out[0].intrinsics)
    c2w = np.eye(4)
    c2w[:3, 3] = (1e-3, -2.5, 1e4)
    out[1] = NamedPose(out[1].name, c2w, out[1].intrinsics)
    return out


def _write_images(root, poses):
    for p in poses:
        f = root / p.name
        f.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (p.intrinsics.width, p.intrinsics.height), (90, 120, 30)).save(f, "PNG")


def _same_intrinsics(a: Intrinsics, b: Intrinsics, where: str):
    assert (a.width, a.height) == (b.width, b.height), where
    for k in ("fx", "fy", "cx_px", "cy_px"):
        assert abs(getattr(a, k) - getattr(b, k)) < TOL, (where, k, getattr(a, k), getattr(b, k))


def _assert_same(poses, read_back, key=lambda name: name, tol=TOL):
    """read_back: {name: (c2w, Intrinsics)}; poses keyed by key(name)."""
    assert sorted(read_back) == sorted(key(p.name) for p in poses)
    for p in poses:
        c2w, intr = read_back[key(p.name)]
        err = np.abs(np.asarray(c2w) - p.c2w).max()
        assert err < tol * max(1.0, np.abs(p.c2w).max()), (p.name, err)
        _same_intrinsics(p.intrinsics, intr, p.name)


# ----------------------------------------------------------------------------- cameras.json

def test_cameras_json_round_trip(tmp_path):
    poses = _poses()
    out = export_cameras_json(tmp_path / "cameras.json", poses)
    entries = read_cameras_json(out)
    assert [e.id for e in entries] == list(range(len(poses)))
    _assert_same(poses, {e.img_name: (e.c2w, Intrinsics(e.width, e.height, e.fx, e.fy))
                         for e in entries})
    # upstream camera_to_JSON layout: key order, rotation = C2W rotation, position = centre
    raw = json.loads(out.read_text())
    assert list(raw[0]) == ["id", "img_name", "width", "height", "position", "rotation", "fy", "fx"]
    assert np.array_equal(raw[2]["rotation"], poses[2].c2w[:3, :3])
    assert np.array_equal(raw[2]["position"], poses[2].c2w[:3, 3])


def test_cameras_json_drops_an_off_centre_principal_point_with_a_warning(tmp_path, caplog):
    poses = _poses(mixed=True)
    with caplog.at_level(logging.WARNING, logger="icomma_plugin.io.export"):
        export_cameras_json(tmp_path, poses)  # a folder: cameras.json inside it
    assert "principal point" in caplog.text and "frame_001" in caplog.text
    e = read_cameras_json(tmp_path / "cameras.json")[1]
    assert (e.fx, e.fy, e.width, e.height) == (35.25, 36.0, 40, 30)


# ----------------------------------------------------------------------------- COLMAP

def test_colmap_round_trip_through_read_colmap(tmp_path):
    poses = _poses(n=5, mixed=True)
    scene = tmp_path / "scene"
    written = export_colmap(scene / "sparse" / "0", poses)
    assert [f.name for f in written] == ["cameras.txt", "images.txt", "points3D.txt"]
    _write_images(scene / "images", poses)  # COLMAP names are relative to the image folder
    data = read_colmap(scene, eval=False)
    assert data.test == [] and data.points.shape == (0, 3)
    _assert_same(poses, {v.name: (v.c2w, v.intrinsics) for v in data.train})
    assert read_dataset(scene, eval=False).source == "colmap"  # detected like 3DGS's Scene
    # two distinct intrinsics -> two PINHOLE cameras, with COLMAP's +0.5 principal point
    cams = [ln.split() for ln in written[0].read_text().splitlines() if not ln.startswith("#")]
    assert [c[:4] for c in cams] == [["1", "PINHOLE", "48", "32"], ["2", "PINHOLE", "40", "30"]]
    assert float(cams[0][6]) == 24.0 and float(cams[1][6]) == pytest.approx(21.8, abs=1e-12)


def test_colmap_rejects_names_with_whitespace(tmp_path):
    p = _poses(n=2)
    bad = [p[0], NamedPose("my photo.jpg", p[1].c2w, p[1].intrinsics)]
    with pytest.raises(ValueError, match="whitespace.*my photo.jpg"):
        export_colmap(tmp_path, bad)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- nerfstudio

@pytest.mark.parametrize("mixed", [False, True], ids=["shared", "per_frame"])
def test_nerfstudio_round_trip_through_read_dataset(tmp_path, mixed):
    poses = _poses(n=5, mixed=mixed)
    out = export_nerfstudio(tmp_path / "transforms.json", poses)
    _write_images(tmp_path, poses)
    data = read_dataset(tmp_path, eval=False, random_init_points=8)
    assert data.source == "transforms_json"
    views = {v.name: (v.c2w, v.intrinsics) for v in data.train}
    _assert_same(poses, views, key=lambda n: n[len("images/"):-len(".png")])  # reader: stems

    raw = json.loads(out.read_text())
    assert raw["camera_model"] == "OPENCV"
    assert ("fl_x" in raw) == (not mixed) and ("fl_x" in raw["frames"][0]) == mixed
    # OpenGL axes (columns 1, 2 negated) and the +0.5 pixel-centre convention, in the file
    m = np.array(raw["frames"][3]["transform_matrix"])
    assert np.array_equal(m[:, 0], poses[3].c2w[:, 0])
    assert np.array_equal(m[:3, 1:3], -poses[3].c2w[:3, 1:3])
    k = raw["frames"][1] if mixed else raw
    assert k["cx"] == poses[1].intrinsics.cx_px + 0.5 and k["w"] == poses[1].intrinsics.width


def test_nerfstudio_shared_intrinsics_option(tmp_path):
    poses = _poses(n=3, mixed=False)
    raw = json.loads(export_nerfstudio(tmp_path / "a.json", poses, shared_intrinsics=False)
                     .read_text())
    assert "fl_x" not in raw and all("fl_x" in f for f in raw["frames"])
    with pytest.raises(ValueError, match="shared_intrinsics=True.*frame_001"):
        export_nerfstudio(tmp_path / "b.json", _poses(n=3, mixed=True), shared_intrinsics=True)
    with pytest.raises(ValueError, match="shared_intrinsics must be"):
        export_nerfstudio(tmp_path / "c.json", poses, shared_intrinsics="yes")


# ----------------------------------------------------------------------------- all formats

def test_a_chain_through_every_format_keeps_the_poses(tmp_path):
    """cameras.json -> CameraEntry -> COLMAP -> View -> nerfstudio -> View: the same poses."""
    poses = _poses(n=4)
    (tmp_path / "a").mkdir()
    export_poses(tmp_path / "a", poses, "cameras_json")
    entries = read_cameras_json(tmp_path / "a" / "cameras.json")
    renamed = [CameraEntry(e.id, e.img_name[len("images/"):], e.width, e.height, e.c2w, e.fx, e.fy)
               for e in entries]
    export_poses(tmp_path / "b" / "sparse" / "0", renamed, "colmap")
    _write_images(tmp_path / "b" / "images", as_named_poses(renamed))
    views = read_colmap(tmp_path / "b", eval=False).train
    export_poses(tmp_path / "c" / "transforms.json", views, "nerfstudio")
    _write_images(tmp_path / "c", as_named_poses(views))
    back = read_dataset(tmp_path / "c", eval=False, random_init_points=8).train
    _assert_same(poses, {v.name: (v.c2w, v.intrinsics) for v in back},
                 key=lambda n: n[len("images/"):-len(".png")])


def test_export_poses_writes_atomically_and_returns_its_files(tmp_path):
    poses = _poses(n=3)
    files = export_poses(tmp_path, poses, "nerfstudio")
    files += export_poses(tmp_path, poses, "cameras_json")
    files += export_poses(tmp_path / "sparse", poses, "colmap")
    assert sorted(f.name for f in files) == ["cameras.json", "cameras.txt", "images.txt",
                                              "points3D.txt", "transforms.json"]
    assert all(f.is_file() for f in files)
    # rewriting replaces the whole file; no temporary file stays behind
    export_poses(tmp_path, poses[:1], "nerfstudio")
    assert len(json.loads((tmp_path / "transforms.json").read_text())["frames"]) == 1
    left = sorted(p.name for p in tmp_path.rglob("*") if p.is_file())
    assert left == ["cameras.json", "cameras.txt", "images.txt", "points3D.txt", "transforms.json"]
    assert set(FORMATS) == {"cameras_json", "colmap", "nerfstudio"}


def test_bad_input_names_what_is_wrong(tmp_path):
    p = _poses(n=2)
    intr = p[0].intrinsics
    with pytest.raises(ValueError, match="format must be one of"):
        export_poses(tmp_path, p, "ply")
    with pytest.raises(ValueError, match="empty"):
        export_poses(tmp_path, [], "colmap")
    with pytest.raises(ValueError, match="share the name"):
        export_poses(tmp_path, [p[0], p[0]], "nerfstudio")
    with pytest.raises(ValueError, match=r"poses\[1\] must be a NamedPose"):
        as_named_poses([p[0], {"name": "x"}])
    with pytest.raises(ValueError, match="list of named poses"):
        as_named_poses("frame.png")
    sheared = np.eye(4)
    sheared[0, 1] = 0.1
    with pytest.raises(ValueError, match="'x.png'.*not orthonormal"):
        NamedPose("x.png", sheared, intr)
    with pytest.raises(ValueError, match=r"shape \[4, 4\]"):
        NamedPose("x.png", np.eye(3), intr)
    with pytest.raises(ValueError, match="NaN or infinite"):
        NamedPose("x.png", np.full((4, 4), np.nan), intr)
    with pytest.raises(ValueError, match="name must be"):
        NamedPose("", np.eye(4), intr)
    with pytest.raises(ValueError, match="intrinsics must be an Intrinsics"):
        NamedPose("x.png", np.eye(4), (48, 32, 40.0, 40.0))
    assert list(tmp_path.iterdir()) == []


def test_named_pose_keeps_its_own_copy():
    c2w = np.eye(4)
    p = NamedPose("a.png", c2w[:3], Intrinsics(8, 8, 10.0, 10.0))  # a 3x4 is completed
    c2w[0, 3] = 5.0
    assert p.c2w.shape == (4, 4) and p.c2w[0, 3] == 0.0 and not p.c2w.flags.writeable


def test_lego_views_round_trip(lego_root, tmp_path):
    """Real poses (NeRF-synthetic JSON, rotations orthonormal to ~1e-7) survive each format.

    The JSON formats keep them to 1e-9; COLMAP's quaternion makes the rotation exactly orthonormal,
    so 1e-6 there.
    """
    views = read_dataset(lego_root).test[:6]
    (tmp_path / "ns").mkdir()
    export_poses(tmp_path / "ns", views, "nerfstudio")
    _write_images(tmp_path / "ns", [NamedPose(v.name + ".png", v.c2w, v.intrinsics)
                                    for v in views])
    back = read_dataset(tmp_path / "ns", eval=False, random_init_points=8).train
    _assert_same(as_named_poses(views), {v.name: (v.c2w, v.intrinsics) for v in back})
    export_poses(tmp_path / "cm" / "sparse" / "0", views, "colmap")
    _write_images(tmp_path / "cm" / "images", as_named_poses(views))
    back = read_colmap(tmp_path / "cm", eval=False).train
    _assert_same(as_named_poses(views), {v.name: (v.c2w, v.intrinsics) for v in back}, tol=1e-6)


def test_one_pose_tolerance_everywhere(tmp_path):
    # A rotation orthonormal to 4e-4 (a pose typed with 4 decimals) is accepted by every reader
    # and by the export alike; one at 5e-3 by none (pose.convert.RIGID_ATOL).
    from icomma_plugin.app.inputs import read_poses_file
    from icomma_plugin.pose.convert import RIGID_ATOL, as_rigid

    intr = Intrinsics(48, 32, 40.0, 40.0)
    for err, ok in ((0.2 * RIGID_ATOL, True), (5 * RIGID_ATOL, False)):
        c2w = np.eye(4)
        c2w[0, 0] = 1.0 + err
        text = tmp_path / f"poses_{ok}.txt"
        text.write_text("a.png " + " ".join(f"{v:.6f}" for v in c2w.ravel()) + "\n")
        checks = [
            lambda: as_rigid(c2w, "c2w"),
            lambda: NamedPose("a.png", c2w, intr),
            lambda: read_poses_file(text, "data.init.poses_file"),
        ]
        for check in checks:
            if ok:
                check()
            else:
                with pytest.raises(ValueError, match="orthonormal"):
                    check()
