"""Dataset readers (icomma_plugin.io.datasets) on small files written here, plus the real lego data.

Files are written by helpers independent of the readers (tests/helpers/: COLMAP struct layouts
as in COLMAP's read_write_model.py, look-at poses; here: rotations from axis-angle via
cv2.Rodrigues), so conventions are checked against known geometry rather than against the
reader's own helpers.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from icomma_plugin.camera import Intrinsics
from icomma_plugin.io.datasets import (
    DatasetError,
    SceneData,
    View,
    detect_dataset_kind,
    read_blender,
    read_cameras_json_scene,
    read_colmap,
    read_dataset,
    read_llff,
)
from tests.helpers.colmap import write_colmap_bin, write_colmap_txt
from tests.helpers.geometry import look_at_c2w, project
from tests.helpers.images import write_png

# ----------------------------------------------------------------------------- helpers


def solid(h, w, rgb, alpha=None):
    c = 3 if alpha is None else 4
    arr = np.zeros((h, w, c), np.uint8)
    arr[..., :3] = rgb
    if alpha is not None:
        arr[..., 3] = alpha
    return arr


def quat_from_axis_angle(axis, angle):
    """COLMAP qvec (w, x, y, z) and the rotation matrix (via cv2.Rodrigues) it stands for."""
    n = np.asarray(axis, float)
    n /= np.linalg.norm(n)
    q = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * n])
    R, _ = cv2.Rodrigues(n * angle)
    return q, R


def colmap_scene(root: Path, fmt: str = "bin", extra_unregistered: bool = True):
    """A 9-image COLMAP scene where every image sees world point X at a known pixel.

    Camera 1 is PINHOLE 32x24 with an off-centre principal point, camera 2 SIMPLE_PINHOLE 20x16.
    """
    cameras = [(1, "PINHOLE", 32, 24, [30.0, 28.0, 18.0, 11.0]),  # cx_colmap 18 (centre 16)
               (2, "SIMPLE_PINHOLE", 20, 16, [22.0, 10.0, 8.0])]
    X = np.array([0.2, -0.1, 0.3])
    images, expected = [], {}
    rng = np.random.default_rng(1)
    for k in range(9):
        iid = 10 + k
        cid = 1 if k % 3 else 2
        q, R = quat_from_axis_angle(rng.normal(size=3), rng.uniform(0.2, 2.5))
        xc = np.array([0.3, -0.2, 2.0]) * (1 + 0.1 * k)  # X in camera coordinates
        t = xc - R @ X                                   # so that R X + t = xc
        cam = cameras[cid - 1]
        if cam[1] == "PINHOLE":
            fx, fy, cx, cy = cam[4]
        else:
            fx = fy = cam[4][0]
            cx, cy = cam[4][1:]
        uv_colmap = (fx * xc[0] / xc[2] + cx, fy * xc[1] / xc[2] + cy)  # COLMAP: centres at +0.5
        name = f"img_{k:02d}.png"
        images.append((iid, q, t, cid, name, [(uv_colmap[0], uv_colmap[1], 7)]))
        expected[name] = dict(R=R, t=t, uv_colmap=np.array(uv_colmap), cam=cid)
        w, h = cam[2], cam[3]
        write_png(root / "images" / name, solid(h, w, (10 * k, 100, 200)))
    points = [(7, X, (255, 128, 0), 0.5, [(im[0], 0) for im in images]),
              (8, np.array([1.0, 2.0, 3.0]), (0, 0, 255), 0.1, [])]
    writer = write_colmap_bin if fmt == "bin" else write_colmap_txt
    writer(root / "sparse" / "0", cameras, images, points)
    if extra_unregistered:
        write_png(root / "images" / "zz_not_registered.png", solid(24, 32, (0, 0, 0)))
    return X, expected


# ----------------------------------------------------------------------------- Blender


def blender_scene(root: Path, white=False, with_ext=False):
    """Frames in OpenGL axes.

    A camera at (0, 0, 4) looking down -z (identity rotation), and one at (4, 0, 0) looking at the
    origin.
    """
    W, H = 8, 6
    angle = 2 * math.atan(W / (2 * 10.0))  # fx = 10
    gl_front = np.eye(4)
    gl_front[2, 3] = 4.0
    # looks along -x
    gl_side = np.array([[0, 0, 1, 4.0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]])
    for split, mats in (("train", [gl_front, gl_side]), ("val", [gl_side]), ("test", [gl_front])):
        frames = []
        for i, m in enumerate(mats):
            stem = f"./{split}/r_{i}"
            arr = solid(H, W, (255, 0, 0), alpha=255)
            arr[0, 0] = (255, 0, 0, 0)      # fully transparent
            arr[0, 1] = (255, 0, 0, 128)    # half transparent red
            write_png(root / f"{stem}.png", arr)
            frames.append({"file_path": stem + (".png" if with_ext and i == 0 else ""),
                           "rotation": 0.0, "transform_matrix": m.tolist()})
        (root / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": angle, "frames": frames}))
    return W, H


def test_blender_conventions_and_splits(tmp_path):
    W, H = blender_scene(tmp_path)
    s = read_blender(tmp_path, white_background=True)
    assert isinstance(s, SceneData) and s.source == "blender" and s.white_background
    assert [v.name for v in s.train] == ["r_0", "r_1"] and [v.name for v in s.test] == ["r_0"]
    assert all(v.split == "train" for v in s.train) and s.test[0].split == "test"
    assert s.test[0].image_path.parent.name == "test"
    v = s.train[0]
    assert v.intrinsics.width == W and v.intrinsics.height == H
    assert v.intrinsics.fx == pytest.approx(10.0) and v.intrinsics.fy == pytest.approx(10.0)
    assert v.intrinsics.cx is None and v.intrinsics.cy is None
    # Blender flip: identity OpenGL rotation -> diag(1, -1, -1) in OpenCV axes
    np.testing.assert_allclose(v.c2w[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(v.campos, [0, 0, 4])
    np.testing.assert_allclose(v.w2c @ v.c2w, np.eye(4), atol=1e-12)
    # the origin is in front of the camera, at the image centre; world +x is to the right and
    # world +y (OpenGL up of this camera) is up in the image (smaller row)
    intr = v.intrinsics
    np.testing.assert_allclose(project(v, intr, [0, 0, 0]), [(W - 1) / 2, (H - 1) / 2], atol=1e-9)
    u, r = project(v, intr, [0.4, 0, 0])
    assert u == pytest.approx((W - 1) / 2 + 10 * 0.4 / 4)
    assert project(v, intr, [0, 0.4, 0])[1] == pytest.approx((H - 1) / 2 - 10 * 0.4 / 4)
    # the side camera at (4, 0, 0) also sees the origin at the centre
    side = s.train[1]
    np.testing.assert_allclose(
        project(side, intr, [0, 0, 0]), [(W - 1) / 2, (H - 1) / 2], atol=1e-9
    )
    np.testing.assert_allclose(side.c2w[:3, 2], [-1, 0, 0], atol=1e-12)  # looks along -x
    # splits
    assert len(read_blender(tmp_path, test_split="val").test) == 1
    assert read_blender(tmp_path, test_split="val").test[0].image_path.parent.name == "val"
    merged = read_blender(tmp_path, eval=False)
    assert (
        len(merged.train) == 3
        and merged.test == []
        and all(v.split == "train" for v in merged.train)
    )
    with pytest.raises(ValueError, match="test_split"):
        read_blender(tmp_path, test_split="training")
    assert s.points is None and s.colors is None
    assert s.scene_radius() == pytest.approx(1.1 * math.hypot(2, 2))  # centres (0,0,4), (4,0,0)


def test_blender_composite_and_scale(tmp_path):
    W, H = blender_scene(tmp_path, with_ext=True)
    s = read_blender(tmp_path, white_background=True)
    v = s.train[0]
    assert v.image_path.name == "r_0.png"
    rgb, alpha = v.load()
    assert rgb.shape == (3, H, W) and alpha.shape == (1, H, W) and rgb.dtype == torch.float32
    a = 128 / 255
    torch.testing.assert_close(rgb[:, 0, 0], torch.tensor([1.0, 1.0, 1.0]))  # transparent -> white
    torch.testing.assert_close(rgb[:, 0, 1], torch.tensor([1.0, 1 - a, 1 - a]), atol=1e-6, rtol=0)
    torch.testing.assert_close(rgb[:, 2, 2], torch.tensor([1.0, 0.0, 0.0]))
    assert alpha[0, 0, 0] == 0 and alpha[0, 0, 1] == pytest.approx(a) and alpha[0, 3, 3] == 1
    black = read_blender(tmp_path, white_background=False).train[0].load()[0]
    torch.testing.assert_close(black[:, 0, 0], torch.zeros(3))
    torch.testing.assert_close(black[:, 0, 1], torch.tensor([a, 0.0, 0.0]), atol=1e-6, rtol=0)
    # explicit background and no compositing
    grey = v.load(background=torch.tensor([0.5, 0.5, 0.5]))[0]
    torch.testing.assert_close(grey[:, 0, 0], torch.full((3,), 0.5))
    raw = v.load(composite=False)[0]
    torch.testing.assert_close(raw[:, 0, 0], torch.tensor([1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="background"):
        v.load(background=[1.0, 2.0])
    # scaling: the image size matches the scaled intrinsics
    for scale in (0.5, 0.25, 2.0, 0.3):
        rgb_s, alpha_s = v.load(scale=scale)
        k = v.intrinsics.scaled(scale)
        assert rgb_s.shape == (3, k.height, k.width) and alpha_s.shape == (1, k.height, k.width)
    with pytest.raises(ValueError, match="scale"):
        v.load(scale=0)


def test_blender_ngp_keys_and_random_points(tmp_path):
    write_png(tmp_path / "train" / "a.png", solid(6, 8, (1, 2, 3)))
    write_png(tmp_path / "train" / "b.jpg", solid(6, 8, (1, 2, 3)))
    frames = [
        {"file_path": "train/a", "transform_matrix": np.eye(4).tolist()},
        {"file_path": "train/b", "transform_matrix": np.eye(4).tolist(), "cx": 5.0, "fl_y": 12.0},
    ]
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"fl_x": 11.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6, "frames": frames}))
    s = read_blender(tmp_path, random_init_points=True, seed=3)
    a, b = s.train
    assert b.image_path.suffix == ".jpg"
    assert a.intrinsics.fx == 11 and a.intrinsics.fy == 11
    assert a.intrinsics.cx_px == pytest.approx(3.5) and a.intrinsics.cy_px == pytest.approx(2.5)
    assert b.intrinsics.cx == pytest.approx(4.5) and b.intrinsics.fy == 12.0  # per-frame wins
    assert s.test == []
    assert s.points.shape == (100_000, 3) and s.colors.shape == (100_000, 3)
    assert s.points.min() >= -1.3 and s.points.max() <= 1.3 and abs(s.points.mean()) < 0.05
    assert 0.5 <= s.colors.min() and s.colors.max() < 0.5 + 0.3 / 255
    np.testing.assert_array_equal(read_blender(tmp_path, random_init_points=10, seed=3).points,
                                  read_blender(tmp_path, random_init_points=10, seed=3).points)


@pytest.mark.parametrize("damage,match", [
    ("json", "malformed JSON"),
    ("frames", "frames"),
    ("matrix_shape", "4x4"),
    ("not_rotation", "not a rotation"),
    ("missing_image", "r_1"),
    ("no_focal", "focal"),
])
def test_blender_damaged(tmp_path, damage, match):
    blender_scene(tmp_path)
    path = tmp_path / "transforms_train.json"
    data = json.loads(path.read_text())
    if damage == "json":
        path.write_text(path.read_text()[:-5])
    else:
        if damage == "frames":
            data["frames"] = {"a": 1}
        elif damage == "matrix_shape":
            data["frames"][1]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
        elif damage == "not_rotation":
            data["frames"][1]["transform_matrix"][0][0] = 3.0
        elif damage == "missing_image":
            (tmp_path / "train" / "r_1.png").unlink()
        elif damage == "no_focal":
            del data["camera_angle_x"]
        path.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=match) as e:
        read_blender(tmp_path)
    assert "transforms_train.json" in str(e.value) or "r_1" in str(e.value)


# ----------------------------------------------------------------------------- COLMAP


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_colmap_poses_intrinsics_points(tmp_path, fmt, caplog):
    X, expected = colmap_scene(tmp_path, fmt)
    with caplog.at_level("INFO"):
        s = read_colmap(tmp_path, eval=True)
    assert "zz_not_registered.png" in caplog.text  # unregistered image skipped, logged
    assert s.source == "colmap"
    names = sorted(expected)
    assert [v.name for v in s.test] == [names[0], names[8]]  # llffhold 8 on sorted names
    assert [v.name for v in s.train] == [n for i, n in enumerate(names) if i % 8]
    for v in s.views("all"):
        e = expected[v.name]
        np.testing.assert_allclose(v.w2c[:3, :3], e["R"], atol=1e-9)   # qvec is w-first, w2c
        np.testing.assert_allclose(v.w2c[:3, 3], e["t"], atol=1e-9)
        np.testing.assert_allclose(v.campos, -e["R"].T @ e["t"], atol=1e-9)
        # the point projects onto the observation COLMAP stores (its pixel origin is +0.5)
        np.testing.assert_allclose(project(v, v.intrinsics, X) + 0.5, e["uv_colmap"], atol=1e-9)
        if e["cam"] == 1:  # off-centre principal point kept, in our convention
            assert (v.intrinsics.width, v.intrinsics.height) == (32, 24)
            assert v.intrinsics.cx == pytest.approx(17.5) and v.intrinsics.cy == pytest.approx(10.5)
            assert (v.intrinsics.fx, v.intrinsics.fy) == (30.0, 28.0)
        else:  # centred: cx None (the image centre) and its own size
            assert (v.intrinsics.width, v.intrinsics.height) == (20, 16)
            assert v.intrinsics.cx is None and v.intrinsics.fx == 22.0
        assert v.distortion is None
        rgb, alpha = v.load()
        assert rgb.shape == (3, v.intrinsics.height, v.intrinsics.width) and alpha is None
    assert s.points.shape == (2, 3) and s.colors.shape == (2, 3)
    np.testing.assert_allclose(s.points[0], X)
    np.testing.assert_allclose(s.colors[0], [1.0, 128 / 255, 0.0])
    centres = np.stack([v.campos for v in s.train])
    assert s.scene_radius() == pytest.approx(
        1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max()
    )
    # other split options
    assert read_colmap(tmp_path, eval=False).test == []
    s2 = read_colmap(tmp_path, test_list=["img_03", "img_05.png"])
    assert [v.name for v in s2.test] == ["img_03.png", "img_05.png"]
    (tmp_path / "list.txt").write_text("# test images\nimg_04.png\n")
    assert [v.name for v in read_colmap(tmp_path, test_list=tmp_path / "list.txt").test] == [
        "img_04.png"
    ]
    (tmp_path / "sparse" / "0" / "test.txt").write_text("img_02.png\n")
    assert [v.name for v in read_colmap(tmp_path).test] == ["img_02.png"]


def test_colmap_binary_and_text_agree(tmp_path):
    colmap_scene(tmp_path / "b", "bin")
    colmap_scene(tmp_path / "t", "txt")
    sb, st = read_colmap(tmp_path / "b"), read_colmap(tmp_path / "t")
    for vb, vt in zip(sb.views("all"), st.views("all")):
        assert vb.name == vt.name and vb.intrinsics == vt.intrinsics
        np.testing.assert_allclose(vb.c2w, vt.c2w, atol=1e-12)
    np.testing.assert_allclose(sb.points, st.points)


def _grid_pattern(u, v):
    """Smooth pattern of straight vertical + horizontal stripes (period 12 px)."""
    return 0.5 + 0.25 * np.sin(2 * np.pi * u / 12.0) + 0.25 * np.cos(2 * np.pi * v / 12.0)


@pytest.mark.parametrize("model,params,dist", [
    ("OPENCV", [50.0, 52.0, 33.0, 23.5, -0.25, 0.05, 0.004, -0.003], (-0.25, 0.05, 0.004, -0.003)),
    ("SIMPLE_RADIAL", [50.0, 32.0, 24.0, -0.15], (-0.15, 0.0, 0.0, 0.0)),
    ("RADIAL", [50.0, 32.0, 24.0, 0.2, -0.05], (0.2, -0.05, 0.0, 0.0)),
])
def test_colmap_undistortion(tmp_path, model, params, dist):
    """A distorted image of a straight-stripe grid undistorts back to the ideal pinhole image."""
    W, H = 64, 48
    if model == "OPENCV":
        fx, fy, cxc, cyc = params[:4]
    else:
        fx = fy = params[0]
        cxc, cyc = params[1:3]
    K = np.array([[fx, 0, cxc - 0.5], [0, fy, cyc - 0.5], [0, 0, 1.0]])  # our/OpenCV pixel centres
    # distorted image D(p_d) = I(undistort(p_d)), I the ideal pinhole image
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    # COLMAP's OPENCV distortion on normalised coordinates, inverted by fixed-point iteration
    k1, k2, p1, p2 = dist
    xd, yd = (uu - K[0, 2]) / fx, (vv - K[1, 2]) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(200):
        r2 = x * x + y * y
        radial = k1 * r2 + k2 * r2 * r2
        dx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
        x, y = xd - dx, yd - dy
    D = _grid_pattern(fx * x + K[0, 2], fy * y + K[1, 2])
    ideal = _grid_pattern(uu, vv)
    img16 = np.round(np.repeat(D[..., None], 3, 2) * 65535).astype(np.uint16)
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "d.png"), img16)
    q, _ = quat_from_axis_angle([0, 0, 1], 0.0)
    write_colmap_txt(tmp_path / "sparse" / "0", [(1, model, W, H, params)],
                     [(1, q, [0, 0, 0], 1, "d.png", [])], [])
    v = read_colmap(tmp_path, eval=False).train[0]
    np.testing.assert_allclose(v.distortion[:4], dist)
    assert v.intrinsics.K().numpy() == pytest.approx(K)
    rgb, _ = v.load()
    out = rgb[0].double().numpy()
    inner = (slice(6, H - 6), slice(6, W - 6))
    err = np.abs(out[inner] - ideal[inner])
    before = np.abs(D[inner] - ideal[inner]).mean()
    assert before > 0.03                                    # the distortion is visible...
    assert err.mean() < 0.01 and err.max() < 0.05           # ...and undistortion removes it
    # a half-pixel error in the principal point convention would be detected
    shifted = _grid_pattern(uu + 0.5, vv + 0.5)
    assert np.abs(out[inner] - shifted[inner]).mean() > 3 * err.mean()
    # scaled load keeps the scaled intrinsics' size
    rgb2, _ = v.load(scale=0.5)
    assert rgb2.shape == (3, 24, 32)


@pytest.mark.parametrize("which", ["cameras.bin", "images.bin", "points3D.bin"])
def test_colmap_truncated_binary(tmp_path, which):
    colmap_scene(tmp_path, "bin")
    p = tmp_path / "sparse" / "0" / which
    p.write_bytes(p.read_bytes()[:-7])
    with pytest.raises(DatasetError, match="truncated") as e:
        read_colmap(tmp_path)
    assert which in str(e.value)


def test_colmap_damaged_inputs(tmp_path):
    # unknown model id in binary
    colmap_scene(tmp_path / "a", "bin")
    write_colmap_bin(tmp_path / "a" / "sparse" / "0", [(1, 99, 32, 24, [1.0, 2.0, 3.0])], [], [])
    with pytest.raises(DatasetError, match=r"cameras\.bin.*unknown COLMAP camera model id 99"):
        read_colmap(tmp_path / "a")
    # unknown model name in text
    colmap_scene(tmp_path / "b", "txt")
    p = tmp_path / "b" / "sparse" / "0" / "cameras.txt"
    p.write_text(p.read_text().replace("SIMPLE_PINHOLE", "FANCY_LENS"))
    with pytest.raises(
        DatasetError, match=r"cameras\.txt:\d+: unknown COLMAP camera model 'FANCY_LENS'"
    ):
        read_colmap(tmp_path / "b")
    # wrong parameter count in text
    colmap_scene(tmp_path / "c", "txt")
    p = tmp_path / "c" / "sparse" / "0" / "cameras.txt"
    p.write_text(p.read_text().replace("SIMPLE_PINHOLE 20 16 22.0", "SIMPLE_PINHOLE 20 16"))
    with pytest.raises(DatasetError, match=r"cameras\.txt:\d+: model SIMPLE_PINHOLE needs 3"):
        read_colmap(tmp_path / "c")
    # a registered image whose file is missing
    colmap_scene(tmp_path / "d", "bin")
    (tmp_path / "d" / "images" / "img_04.png").unlink()
    with pytest.raises(DatasetError, match=r"img_04\.png"):
        read_colmap(tmp_path / "d")
    # an unsupported (fisheye) model used by an image
    colmap_scene(tmp_path / "e", "txt")
    p = tmp_path / "e" / "sparse" / "0" / "cameras.txt"
    p.write_text(p.read_text().replace("PINHOLE 32 24 30.0 28.0 18.0 11.0",
                                       "OPENCV_FISHEYE 32 24 30.0 28.0 18.0 11.0 0.1 0 0 0"))
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE.*not supported"):
        read_colmap(tmp_path / "e")
    # images refer to a missing camera
    colmap_scene(tmp_path / "f", "txt")
    p = tmp_path / "f" / "sparse" / "0" / "images.txt"
    p.write_text(p.read_text().replace(" 2 img_00.png", " 5 img_00.png"))
    with pytest.raises(DatasetError, match="camera 5"):
        read_colmap(tmp_path / "f")
    # malformed number in images.txt
    colmap_scene(tmp_path / "g", "txt")
    p = tmp_path / "g" / "sparse" / "0" / "images.txt"
    lines = p.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.endswith("img_01.png"))
    lines[i] = lines[i].replace(lines[i].split()[2], "abc", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"images\.txt:\d+: a pose value must be a number"):
        read_colmap(tmp_path / "g")
    # an image file whose size disagrees with its camera: clear error on load
    colmap_scene(tmp_path / "h", "bin")
    write_png(tmp_path / "h" / "images" / "img_01.png", solid(5, 5, (0, 0, 0)))
    v = read_colmap(tmp_path / "h").view("img_01.png")
    with pytest.raises(DatasetError, match=r"img_01\.png is 5x5"):
        v.load()


def test_colmap_unregistered_pose_skipped(tmp_path, caplog):
    X, expected = colmap_scene(tmp_path, "txt")
    p = tmp_path / "sparse" / "0" / "images.txt"
    lines = p.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.endswith("img_02.png"))
    el = lines[i].split()
    lines[i] = " ".join(el[:1] + ["0", "0", "0", "0"] + el[5:])
    p.write_text("\n".join(lines) + "\n")
    with caplog.at_level("WARNING"):
        s = read_colmap(tmp_path, eval=False)
    assert "img_02.png" in caplog.text
    assert "img_02.png" not in [v.name for v in s.train] and len(s.train) == 8


# ----------------------------------------------------------------------------- LLFF


def test_llff(tmp_path):
    n = 10
    rows, c2ws = [], []
    for i in range(n):
        a = 2 * math.pi * i / n
        c2w = look_at_c2w([3 * math.cos(a), 3 * math.sin(a), 0.5 + 0.1 * i])
        c2ws.append(c2w)
        llff = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [12.0, 16.0, 20.0]], 1)
        rows.append(np.concatenate([llff.ravel(), [1.0 + i, 10.0 + i]]))
        write_png(tmp_path / "images" / f"IMG_{i:03d}.JPG.png", solid(12, 16, (i, 0, 0)))
        write_png(tmp_path / "images_2" / f"IMG_{i:03d}.png", solid(6, 8, (i, 0, 0)))
    np.save(tmp_path / "poses_bounds.npy", np.array(rows))
    s = read_llff(tmp_path)
    assert s.source == "llff"
    assert [v.name for v in s.test] == ["IMG_000.JPG", "IMG_008.JPG"]
    assert len(s.train) == 8
    for v in s.views("all"):
        i = v.meta["index"]
        np.testing.assert_allclose(v.c2w, c2ws[i], atol=1e-12)
        assert v.bounds == (1.0 + i, 10.0 + i)
        assert (v.intrinsics.width, v.intrinsics.height, v.intrinsics.fx) == (16, 12, 20.0)
        np.testing.assert_allclose(project(v, v.intrinsics, [0, 0, 0])[0], 7.5, atol=1e-9)
    # an independent LLFF-axes camera: at (0, 0, 5), down = -y, right = +x, back = +z
    m = np.array([[0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 1, 5.0]])
    rows2 = [np.concatenate([np.concatenate([m, [[12.0], [16.0], [20.0]]], 1).ravel(), [1, 9]])] * n
    np.save(tmp_path / "poses_bounds.npy", np.array(rows2))
    v = read_llff(tmp_path, eval=False).train[0]
    intr = v.intrinsics
    np.testing.assert_allclose(project(v, intr, [0, 0, 0]), [7.5, 5.5], atol=1e-9)
    assert project(v, intr, [1, 0, 0])[0] > 7.5    # world +x (camera right) -> right
    assert project(v, intr, [0, 1, 0])[1] < 5.5    # world +y (camera up) -> up
    # factor: the downsampled folder, focal scaled
    s2 = read_llff(tmp_path, factor=2)
    assert s2.train[0].intrinsics.width == 8 and s2.train[0].intrinsics.fx == pytest.approx(10.0)
    assert s2.train[0].load()[0].shape == (3, 6, 8)
    with pytest.raises(DatasetError, match="images_4"):
        read_llff(tmp_path, factor=4)


def test_llff_damaged(tmp_path):
    for i in range(3):
        write_png(tmp_path / "images" / f"{i}.png", solid(4, 4, (0, 0, 0)))
    np.save(tmp_path / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy.*shape \[N, 17\].*\(3, 15\)"):
        read_llff(tmp_path)
    good = np.concatenate([np.eye(3), np.zeros((3, 1)), [[4.0], [4.0], [5.0]]], 1).ravel()
    np.save(tmp_path / "poses_bounds.npy", np.array([np.concatenate([good, [1, 2]])] * 2))
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy has 2 poses but .*images has 3"):
        read_llff(tmp_path)
    (tmp_path / "poses_bounds.npy").write_bytes(b"not numpy")
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy"):
        read_llff(tmp_path)


# ----------------------------------------------------------------------------- cameras.json


def _cameras_json(tmp_path, names=("a", "b", "c")):
    entries = []
    for i, n in enumerate(names):
        c2w = look_at_c2w([2.0 + i, 1.0, 1.5])
        entries.append({"id": i, "img_name": n, "width": 16, "height": 12,
                        "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
                        "fy": 21.0, "fx": 20.0})
    model = tmp_path / "model"
    model.mkdir()
    (model / "cameras.json").write_text(json.dumps(entries))
    return model, entries


def test_cameras_json_scene(tmp_path):
    model, entries = _cameras_json(tmp_path)
    imgs = tmp_path / "imgs"
    write_png(imgs / "a.png", solid(12, 16, (1, 2, 3)))
    Image.fromarray(solid(12, 16, (1, 2, 3))).save(imgs / "b.jpg")
    write_png(imgs / "c.png", solid(6, 8, (1, 2, 3)))  # downsampled copy
    s = read_cameras_json_scene(model, images=imgs)
    assert (
        s.source == "cameras_json" and s.test == [] and [v.name for v in s.train] == ["a", "b", "c"]
    )
    a, b, c = s.train
    assert b.image_path.name == "b.jpg"
    np.testing.assert_allclose(a.c2w[:3, 3], entries[0]["position"])
    np.testing.assert_allclose(a.c2w[:3, :3], entries[0]["rotation"])
    assert (a.intrinsics.fx, a.intrinsics.fy, a.intrinsics.width) == (20.0, 21.0, 16)
    assert (c.intrinsics.width, c.intrinsics.fx, c.intrinsics.fy) == (8, 10.0, 10.5)
    assert c.load()[0].shape == (3, 6, 8)
    np.testing.assert_allclose(project(a, a.intrinsics, [0, 0, 0]), [7.5, 5.5], atol=1e-9)
    s2 = read_cameras_json_scene(model / "cameras.json", images=imgs, test_names=["b"])
    assert [v.name for v in s2.test] == ["b"] and s2.test[0].split == "test"
    assert [v.name for v in read_cameras_json_scene(model, images=imgs, llffhold=2).test] == [
        "a",
        "c",
    ]
    # dispatch needs model/images by default
    with pytest.raises(DatasetError, match="images"):
        read_dataset(model)
    assert read_dataset(model, images=imgs).source == "cameras_json"
    (imgs / "b.jpg").unlink()
    with pytest.raises(DatasetError, match=r"'b'.*imgs"):
        read_cameras_json_scene(model, images=imgs)
    (model / "cameras.json").write_text("[{")
    with pytest.raises(DatasetError, match=r"cameras\.json"):
        read_cameras_json_scene(model, images=imgs)


# ----------------------------------------------------------------------------- dispatch


def test_read_dataset_dispatch(tmp_path):
    blender_scene(tmp_path / "blender")
    colmap_scene(tmp_path / "colmap", "bin")
    assert detect_dataset_kind(tmp_path / "blender") == "blender"
    assert detect_dataset_kind(tmp_path / "colmap") == "colmap"
    assert (
        read_dataset(tmp_path / "blender", white_background=True, test_split="val").source
        == "blender"
    )
    assert read_dataset(tmp_path / "colmap", llffhold=4).source == "colmap"
    with pytest.raises(ValueError, match="read_colmap.*test_split"):
        read_dataset(tmp_path / "colmap", test_split="val")
    with pytest.raises(ValueError, match="kind"):
        read_dataset(tmp_path / "colmap", kind="nerfstudio")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError) as e:
        read_dataset(tmp_path / "empty")
    msg = str(e.value)
    for looked in ("sparse/", "transforms_train.json", "poses_bounds.npy", "cameras.json", "empty"):
        assert looked in msg
    with pytest.raises(DatasetError, match="does not exist"):
        read_dataset(tmp_path / "nowhere")
    (tmp_path / "colmap2" / "sparse").mkdir(parents=True)
    with pytest.raises(DatasetError, match="cameras.bin/cameras.txt"):
        read_dataset(tmp_path / "colmap2")


def test_view_validation(tmp_path):
    intr = Intrinsics(4, 4, 5.0, 5.0)
    with pytest.raises(DatasetError, match="4x4"):
        View("x", intr, np.eye(3), tmp_path / "x.png")
    with pytest.raises(ValueError, match="split"):
        View("x", intr, np.eye(4), tmp_path / "x.png", split="val")
    v = View("x", intr, np.eye(4), tmp_path / "x.png")
    with pytest.raises(DatasetError, match=r"x\.png"):
        v.load()
    (tmp_path / "x.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(DatasetError, match=r"cannot decode.*x\.png"):
        v.load()


# ----------------------------------------------------------------------------- real data


@pytest.mark.shared_data
def test_real_lego(lego_root):
    s = read_dataset(lego_root, white_background=True)
    assert s.source == "blender" and len(s.train) == 100 and len(s.test) == 200
    for v in (s.train[0], s.test[-1]):
        assert (v.intrinsics.width, v.intrinsics.height) == (400, 400)
        assert v.intrinsics.fx == pytest.approx(555.56, abs=0.01)
        assert v.intrinsics.fy == pytest.approx(555.56, abs=0.01)
        # cameras sit on a sphere of radius ~4 and look at the origin (it projects near the centre)
        assert np.linalg.norm(v.campos) == pytest.approx(4.03, abs=0.05)
        uv = project(v, v.intrinsics, [0, 0, 0])
        assert np.all(np.abs(uv - 199.5) < 40)
    rgb, alpha = s.test[0].load()
    assert rgb.shape == (3, 400, 400) and alpha.shape == (1, 400, 400)
    assert 0 <= float(rgb.min()) and float(rgb.max()) <= 1
    torch.testing.assert_close(rgb[:, 0, 0], torch.ones(3))  # transparent corner over white
    assert float(alpha[0, 200, 200]) > 0.5                    # the model is in the middle
    rgb_b, _ = read_dataset(lego_root, white_background=False).test[0].load(scale=0.5)
    assert rgb_b.shape == (3, 200, 200) and float(rgb_b[:, 0, 0].abs().max()) == 0.0
    assert 3.0 < s.scene_radius() < 8.0
    assert len(read_dataset(lego_root, test_split="val").test) == 100


def _llff_with_sparse(root: Path, n: int = 10):
    """An LLFF folder (poses_bounds.npy + images/) with a COLMAP sparse/0 beside it.

    Returns the camera-to-world poses (OpenCV axes) and the sparse points written.
    """
    rows, c2ws = [], []
    for i in range(n):
        a = 2 * math.pi * i / n
        c2w = look_at_c2w([3 * math.cos(a), 3 * math.sin(a), 0.5])
        c2ws.append(c2w)
        llff = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [12.0, 16.0, 20.0]], 1)
        rows.append(np.concatenate([llff.ravel(), [1.0, 6.0]]))
        write_png(root / "images" / f"IMG_{i:03d}.png", solid(12, 16, (i, 0, 0)))
    np.save(root / "poses_bounds.npy", np.array(rows))
    cameras = [(1, "SIMPLE_PINHOLE", 16, 12, [20.0, 8.0, 6.0])]
    images = [(1, [1.0, 0, 0, 0], [0.0, 0.0, 3.0], 1, "IMG_000.png", [])]
    pts = [(1, np.array([0.1, -0.2, 0.3]), (255, 0, 0), 0.5, []),
           (2, np.array([-0.4, 0.2, 0.0]), (0, 255, 0), 0.5, [])]
    write_colmap_bin(root / "sparse" / "0", cameras, images, pts)
    return c2ws, np.array([p[1] for p in pts])


def test_llff_with_sparse_lacking_images_bin_falls_back_to_llff_poses(tmp_path, caplog):
    """Issue 16 bug 3: sparse/0 without images.bin, complete poses_bounds.npy -> LLFF poses."""
    c2ws, pts = _llff_with_sparse(tmp_path)
    (tmp_path / "sparse" / "0" / "images.bin").unlink()
    with caplog.at_level("WARNING"):
        kind = detect_dataset_kind(tmp_path)
        s = read_dataset(tmp_path)
    assert kind == "llff" and s.source == "llff"
    assert len(s.train) + len(s.test) == 10
    for v in s.views("all"):
        np.testing.assert_allclose(v.c2w, c2ws[v.meta["index"]], atol=1e-12)
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("images.bin" in m and "poses_bounds.npy" in m for m in warned), warned
    # the sparse points (same world frame as the LLFF poses) are the initial cloud
    np.testing.assert_allclose(s.points, pts)
    np.testing.assert_allclose(s.colors, [[1.0, 0, 0], [0, 1.0, 0]])


def test_llff_reads_points_of_a_complete_sparse_model(tmp_path):
    """An LLFF folder with a complete COLMAP model beside it.

    The kind is colmap (per-image intrinsics); read_llff uses the model's points.
    """
    _, pts = _llff_with_sparse(tmp_path)
    assert detect_dataset_kind(tmp_path) == "colmap"
    s = read_llff(tmp_path)
    np.testing.assert_allclose(s.points, pts)
    assert s.init_box is None
    shutil.rmtree(tmp_path / "sparse")
    s = read_llff(tmp_path)
    assert s.points is None and s.init_box is not None  # no cloud: the fit makes its own


def test_a_photo_with_an_exif_rotation_is_read_as_stored_and_said_once(tmp_path, caplog):
    """A phone's sideways-stored portrait: pixels as stored (COLMAP's, upstream's), one warning."""
    from PIL import Image

    from icomma_plugin.app.problem import read_query_image
    from icomma_plugin.io.datasets import exif_orientation

    arr = np.zeros((20, 30, 3), np.uint8)
    arr[:, :10] = 255  # a white left third: which way it is read shows
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 deg clockwise to display"
    for k in range(2):
        Image.fromarray(arr).save(tmp_path / f"p{k}.jpg", exif=exif, quality=95)
    Image.fromarray(arr).save(tmp_path / "plain.png")
    assert exif_orientation(tmp_path / "p0.jpg") == 6
    assert exif_orientation(tmp_path / "plain.png") == 1
    assert exif_orientation(tmp_path / "absent.jpg") == 1
    with caplog.at_level("WARNING"):
        for name in ("p0.jpg", "p1.jpg"):
            rgb, _ = read_query_image(tmp_path / name, torch.zeros(3))
            assert tuple(rgb.shape) == (3, 20, 30) and float(rgb[:, :, :10].mean()) > 0.9
    said = [r.getMessage() for r in caplog.records if "EXIF orientation 6" in r.getMessage()]
    assert len(said) == 1 and "p0.jpg" in said[0] and "as stored" in said[0], said


def test_read_dataset_puts_the_principal_point_at_the_centre_when_asked(tmp_path):
    """``principal_point="centre"``: upstream 3DGS's camera for every view; the rest as read."""
    colmap_scene(tmp_path, "bin")
    given, centred = (read_dataset(tmp_path, principal_point=pp) for pp in ("dataset", "centre"))
    assert any(v.intrinsics.cx is not None for v in given.train + given.test)
    for a, b in zip(given.train + given.test, centred.train + centred.test):
        assert b.intrinsics.cx is None and b.intrinsics.cy is None
        assert (b.intrinsics.fx, b.intrinsics.width) == (a.intrinsics.fx, a.intrinsics.width)
        np.testing.assert_array_equal(a.w2c, b.w2c)
    with pytest.raises(ValueError, match="principal_point must be one of.*'middle'"):
        read_dataset(tmp_path, principal_point="middle")
