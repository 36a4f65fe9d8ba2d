"""The instant-ngp / nerfstudio `transforms.json` reader and the undistortion validity masks.

Every capture is written here in tmp_path (small synthetic PNGs); the expected geometry and
the expected undistorted images come from closed-form formulas written in this file (the
forward lens models), independent of the reader and of OpenCV.
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from icomma_plugin.io.datasets import (
    DatasetError,
    View,
    ViewImage,
    detect_dataset_kind,
    read_dataset,
    read_transforms_json,
    undistort_image,
)
from icomma_plugin.camera import Intrinsics
from icomma_plugin.io.ply import write_points_ply
from tests.helpers.geometry import gl_look_at_c2w, project
from tests.helpers.images import write_png

# ----------------------------------------------------------------------------- helpers


def ring(n, radius=4.0):
    a = [2 * math.pi * k / n for k in range(n)]
    return [gl_look_at_c2w((radius * math.cos(t), radius * math.sin(t), 0.5 * (k % 3)))
            for k, t in enumerate(a)]


def write_capture(root: Path, n=10, W=16, H=12, missing=(), order=None, top=None, per_frame=None,
                  ext=True) -> dict:
    """A capture of n frames named f_000.. in file order `order`.

    Images W x H (absent for the indices in `missing`), top-level keys `top` (default:
    fl_x/fl_y/cx/cy/w/h).
    """
    top = dict(fl_x=20.0, fl_y=21.0, cx=8.5, cy=5.75, w=W, h=H) if top is None else top
    frames = []
    for k, m in enumerate(ring(n)):
        name = f"images/f_{k:03d}"
        if k not in missing:
            write_png(root / f"{name}.png", np.full((H, W, 3), 10 * k, np.uint8))
        f = {"file_path": name + (".png" if ext else ""), "transform_matrix": m.tolist()}
        f.update((per_frame or {}).get(k, {}))
        frames.append(f)
    if order is not None:
        frames = [frames[i] for i in order]
    data = dict(top, frames=frames)
    (root / "transforms.json").write_text(json.dumps(data))
    return data


# ----------------------------------------------------------------------------- reader


def test_poses_intrinsics_split_and_detection(tmp_path, caplog):
    rng = np.random.default_rng(0)
    order = rng.permutation(20).tolist()  # file order is not name order
    write_capture(tmp_path, n=20, missing=(3, 11), order=order, ext=False,
                  per_frame={5: {"fl_x": 30.0, "cx": 7.0}})
    assert detect_dataset_kind(tmp_path) == "transforms_json"
    with caplog.at_level(logging.WARNING):
        s = read_dataset(tmp_path)
    assert s.source == "transforms_json"
    # one warning naming how many and which frames were skipped
    warns = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warns) == 1 and "2 of 20" in warns[0]
    assert "images/f_003" in warns[0] and "images/f_011" in warns[0]
    # hold-out: every 8th of the 18 present frames sorted by name
    present = [f"f_{k:03d}" for k in range(20) if k not in (3, 11)]
    assert [v.name for v in s.test] == present[::8]
    assert [v.name for v in s.train] == [n for i, n in enumerate(present) if i % 8]
    assert all(v.image_path.suffix == ".png" for v in s.views("all"))
    # intrinsics: +0.5 pixel-centre convention -> ours; per-frame keys win
    v0 = s.view("f_000")
    i0 = v0.intrinsics
    assert (i0.width, i0.height, i0.fx, i0.fy) == (16, 12, 20.0, 21.0)
    assert i0.cx == pytest.approx(8.0) and i0.cy == pytest.approx(5.25)
    i5 = s.view("f_005").intrinsics
    assert i5.fx == 30.0 and i5.fy == 21.0 and i5.cx == pytest.approx(6.5)
    assert v0.distortion is None
    # OpenGL -> OpenCV: the look-at target projects to the principal point, world +z (the
    # cameras' up) is up in the image (smaller row), and z looks forward
    for v in s.views("all"):
        np.testing.assert_allclose(
            project(v, v.intrinsics, [0, 0, 0]), [v.intrinsics.cx_px, v.intrinsics.cy_px], atol=1e-9
        )
        assert project(v, v.intrinsics, [0, 0, 0.3])[1] < v.intrinsics.cy_px
        gl = np.array(ring(20)[int(v.name[2:])])
        np.testing.assert_allclose(v.c2w[:3, 0], gl[:3, 0])
        np.testing.assert_allclose(v.c2w[:3, 1:3], -gl[:3, 1:3])
        np.testing.assert_allclose(v.campos, gl[:3, 3])
    # eval=False and a test list
    assert len(read_transforms_json(tmp_path, eval=False).train) == 18
    t = read_transforms_json(tmp_path, test_list=["f_004", "images/f_009.png"])
    assert [v.name for v in t.test] == ["f_004", "f_009"]
    # a Blender folder (transforms_train.json) is not taken for a single-file capture
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": []}))
    assert detect_dataset_kind(tmp_path) == "blender"


def test_camera_angles_and_image_size_from_file(tmp_path):
    W, H = 16, 12
    fov_x = 2 * math.atan(W / (2 * 20.0))
    write_capture(tmp_path, n=3, top={"camera_angle_x": fov_x})
    s = read_transforms_json(tmp_path, eval=False)
    i = s.train[0].intrinsics
    assert (i.width, i.height) == (W, H)  # read from the PNG
    assert i.fx == pytest.approx(20.0) and i.fy == pytest.approx(20.0)
    assert i.cx is None and i.cy is None
    fov_y = 2 * math.atan(H / (2 * 24.0))
    write_capture(tmp_path, n=3, top={"camera_angle_x": fov_x, "camera_angle_y": fov_y})
    i = read_transforms_json(tmp_path, eval=False).train[0].intrinsics
    assert i.fx == pytest.approx(20.0) and i.fy == pytest.approx(24.0)


def test_initial_points_random_box_and_ply(tmp_path):
    write_capture(tmp_path, n=8)
    s = read_transforms_json(tmp_path, random_init_points=5000, seed=1)
    centre, half = s.init_box
    # the cameras look at the origin from a ring of radius 4: the cube is centred there and
    # holds every camera
    np.testing.assert_allclose(centre, 0.0, atol=1e-6)
    assert half == pytest.approx(4.0, rel=1e-6)
    assert s.points.shape == (5000, 3) and np.abs(s.points).max() <= half
    assert abs(s.points.mean()) < 0.2 and s.points.std() > 1.5
    np.testing.assert_array_equal(s.points, read_transforms_json(
        tmp_path, random_init_points=5000, seed=1).points)
    # nerfstudio's ply_file_path: that cloud, as stored (same world frame as the poses)
    xyz = np.array([[0.1, 0.2, 0.3], [1.0, -1.0, 0.5]])
    write_points_ply(tmp_path / "sparse_pc.ply", xyz, np.array([[255, 0, 0], [0, 128, 255]]))
    data = json.loads((tmp_path / "transforms.json").read_text())
    data["ply_file_path"] = "sparse_pc.ply"
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    s = read_transforms_json(tmp_path)
    np.testing.assert_allclose(s.points, xyz, atol=1e-6)
    np.testing.assert_allclose(s.colors[1], [0, 128 / 255, 1.0], atol=1e-6)
    assert s.init_box is None
    data["ply_file_path"] = "nope.ply"
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"ply_file_path.*nope\.ply"):
        read_transforms_json(tmp_path)


# ----------------------------------------------------------------------------- lens models


def perspective_distort(x, y, k1, k2, k3, p1, p2):
    """nerfstudio / OpenCV radial-tangential model on normalised coordinates."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def fisheye_distort(x, y, k1, k2, k3, k4):
    """OpenCV / COLMAP / nerfstudio equidistant fisheye model on normalised coordinates."""
    r = np.sqrt(x * x + y * y)
    th = np.arctan(r)
    thd = th * (1 + k1 * th ** 2 + k2 * th ** 4 + k3 * th ** 6 + k4 * th ** 8)
    s = np.where(r > 1e-12, thd / np.maximum(r, 1e-12), 1.0)
    return x * s, y * s


def pattern(u, v):
    """A smooth image (pixel coordinates, centres at integers)."""
    return 0.5 + 0.3 * np.sin(u / 3.1) * np.cos(v / 4.3) + 0.15 * np.sin((u + v) / 7.0)


LENSES = {
    # camera_model / keys -> (distort function, its coefficients in the function's order)
    "OPENCV": ({"k1": 0.12, "k2": -0.03, "k3": 0.05, "p1": 0.004, "p2": -0.003},
               perspective_distort, ("k1", "k2", "k3", "p1", "p2")),
    # strong enough for the border of the same-K pinhole image to fall outside the photo
    "OPENCV_FISHEYE": ({"k1": 0.5, "k2": 0.05, "k3": -0.02, "k4": 0.01},
                       fisheye_distort, ("k1", "k2", "k3", "k4")),
}


@pytest.mark.parametrize("model", sorted(LENSES))
def test_undistortion_and_validity_mask(tmp_path, model):
    """The reader maps each model's coefficients to OpenCV correctly.

    The undistorted image is the pattern sampled through the forward lens model, and exactly the
    pixels whose source lies outside the photo are masked (and 0).
    """
    keys, distort, order = LENSES[model]
    W, H = 64, 48
    fx, fy, cx, cy = 40.0, 42.0, 31.0, 24.5  # file convention (+0.5); ours: 30.5, 24.0
    write_png(tmp_path / "images" / "a.png", np.zeros((H, W, 3), np.uint8))  # replaced below
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    img16 = np.round(np.repeat(pattern(uu, vv)[..., None], 3, 2) * 65535).astype(np.uint16)
    Image.fromarray(img16[..., 0]).save(tmp_path / "images" / "a.png")  # 16-bit grey
    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}
    top = dict(fl_x=fx, fl_y=fy, cx=cx, cy=cy, w=W, h=H, camera_model=model, **keys)
    (tmp_path / "transforms.json").write_text(json.dumps(dict(top, frames=[frame])))
    v = read_transforms_json(tmp_path, eval=False).train[0]
    assert v.distortion_model == ("fisheye" if model == "OPENCV_FISHEYE" else "opencv")
    im = v.load_image()
    assert isinstance(im, ViewImage) and im.alpha is None and im.valid.shape == (1, H, W)
    assert im.valid.dtype == torch.float32 and set(im.valid.unique().tolist()) == {0.0, 1.0}
    # expected: out(p) = photo(distort(p)), source in our pixel convention
    ox, oy = cx - 0.5, cy - 0.5
    xd, yd = distort((uu - ox) / fx, (vv - oy) / fy, *[keys[k] for k in order])
    su, sv = fx * xd + ox, fy * yd + oy
    inside = (su >= 0) & (su <= W - 1) & (sv >= 0) & (sv <= H - 1)
    margin = (su >= 0.05) & (su <= W - 1.05) & (sv >= 0.05) & (sv <= H - 1.05)
    valid = im.valid[0].numpy() > 0.5
    assert (~inside).sum() > 50                       # the lens pulls the border inside
    assert not (valid & ~inside).any()                # never valid where the source is outside
    assert valid[margin].all()                        # valid wherever the source is inside
    out = im.rgb[0].double().numpy()
    far = (su < -1) | (su > W) | (sv < -1) | (sv > H)
    assert far.any() and np.abs(out[far]).max() == 0.0  # filled from outside: 0
    err = np.abs(out - pattern(su, sv))[valid]
    assert err.mean() < 4e-3 and err.max() < 0.03     # bilinear error on a smooth pattern
    # the distortion is visible: ignoring it would be far off
    assert np.abs(out - pattern(uu, vv))[valid].mean() > 10 * err.mean()
    # load() still returns (rgb, alpha); a resized mask is conservative
    rgb, alpha = v.load(scale=0.5)
    assert rgb.shape == (3, 24, 32) and alpha is None
    half = v.load_image(scale=0.5).valid[0].numpy() > 0.5
    blocks = valid.reshape(24, 2, 32, 2).all(axis=(1, 3))
    assert not (half & ~blocks).any() and half.sum() >= 0.97 * blocks.sum()


def test_undistort_image_helper(tmp_path):
    W, H = 40, 30
    K = np.array([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]])
    img = np.ones((H, W, 3), np.float32)
    out, valid = undistort_image(img, K, (0.3, 0.0, 0.0, 0.0))  # pincushion-style border loss
    assert out.shape == (H, W, 3) and valid.dtype == bool and not valid.all()
    np.testing.assert_array_equal(out[..., 0] >= 0.999, valid)  # ones stay 1 exactly where valid
    assert valid[H // 2, W // 2] and not valid[0, 0]
    with pytest.raises(ValueError, match="model"):
        undistort_image(img, K, (0.1, 0, 0, 0), model="polar")
    with pytest.raises(ValueError, match="fisheye"):
        undistort_image(img, K, (0.1, 0, 0, 0, 0), model="fisheye")
    # no distortion: load_image reports every pixel valid (None)
    p = write_png(tmp_path / "x.png", np.zeros((H, W, 3), np.uint8))
    v = View("x", Intrinsics(W, H, 30.0, 30.0), np.eye(4), p)
    assert v.load_image().valid is None and v.load_image().valid_fraction == 1.0


# ----------------------------------------------------------------------------- bad input


def _damage(tmp_path, kind):
    data = write_capture(tmp_path, n=4)
    f2 = data["frames"][2]
    if kind == "missing_frames":
        del data["frames"]
    elif kind == "missing_file_path":
        del f2["file_path"]
    elif kind == "missing_focal":
        del data["fl_x"], data["fl_y"]
    elif kind == "nan_matrix":
        f2["transform_matrix"][1][2] = float("nan")
    elif kind == "no_matrix":
        del f2["transform_matrix"]
    elif kind == "bad_matrix_shape":
        f2["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    elif kind == "size_mismatch":
        write_png(tmp_path / "images" / "f_002.png", np.zeros((12, 18, 3), np.uint8))
    elif kind == "unknown_model":
        data["camera_model"] = "PANORAMA_42"
    elif kind == "unsupported_model":
        f2["camera_model"] = "EQUIRECTANGULAR"
    elif kind == "perspective_k4":
        data.update(camera_model="OPENCV", k1=0.1, k4=0.01)
    elif kind == "fisheye_p1":
        data.update(camera_model="OPENCV_FISHEYE", k1=0.1, p1=0.01)
    elif kind == "string_focal":
        f2["fl_x"] = "20"
    (tmp_path / "transforms.json").write_text(json.dumps(data))


@pytest.mark.parametrize("kind,frame,key", [
    ("missing_frames", None, "frames"),
    ("missing_file_path", 2, "file_path"),
    ("missing_focal", 0, "fl_x"),
    ("nan_matrix", 2, "transform_matrix"),
    ("no_matrix", 2, "transform_matrix"),
    ("bad_matrix_shape", 2, "transform_matrix"),
    ("size_mismatch", 2, "w"),
    ("unknown_model", 0, "camera_model"),
    ("unsupported_model", 2, "camera_model"),
    ("perspective_k4", 0, "k4"),
    ("fisheye_p1", 0, "p1"),
    ("string_focal", 2, "fl_x"),
])
def test_bad_input_names_file_frame_and_key(tmp_path, kind, frame, key):
    _damage(tmp_path, kind)
    with pytest.raises(DatasetError) as e:
        read_dataset(tmp_path)
    msg = str(e.value)
    assert "transforms.json" in msg and f"'{key}'" in msg, msg
    if frame is not None:
        assert f"frame {frame}" in msg, msg
    if kind == "unknown_model":
        assert "PANORAMA_42" in msg and "OPENCV_FISHEYE" in msg
    if kind == "size_mismatch":
        assert "18x12" in msg and "f_002.png" in msg


def test_bad_input_misc(tmp_path):
    (tmp_path / "transforms.json").write_text("{\"frames\": [")
    with pytest.raises(DatasetError, match=r"malformed JSON.*transforms\.json"):
        read_transforms_json(tmp_path)
    write_capture(tmp_path, n=3, missing=(0, 1, 2))
    with pytest.raises(DatasetError, match="none of its 3 frames"):
        read_transforms_json(tmp_path)
    write_capture(tmp_path, n=3)
    with pytest.raises(ValueError, match="random_init_points"):
        read_transforms_json(tmp_path, random_init_points=0)


# ----------------------------------------------------------------------------- real capture


@pytest.mark.shared_data
def test_real_fox(fox_root, caplog):
    with caplog.at_level(logging.WARNING):
        s = read_dataset(fox_root)
    assert s.source == "transforms_json" and len(s.train) == 43 and len(s.test) == 7
    assert any("17 of 67" in r.getMessage() for r in caplog.records)
    names = sorted(v.name for v in s.views("all"))
    assert [v.name for v in s.test] == names[::8]
    v = s.test[0]
    i = v.intrinsics
    assert (i.width, i.height) == (1080, 1920)
    assert (i.fx, i.fy) == (1375.52, 1374.49)
    assert i.cx == pytest.approx(554.058) and i.cy == pytest.approx(964.768)
    assert v.distortion == pytest.approx((0.0578421, -0.0805099, -0.000980296, 0.00015575))
    # the cameras look at the figurine near the origin from 3.8 to 6.3 units away
    assert np.linalg.norm(s.init_box[0]) < 0.3 and 4.0 < s.init_box[1] < 8.0
    for w in s.views("all"):
        assert np.all(
            np.abs(project(w, w.intrinsics, s.init_box[0]) - [i.cx_px, i.cy_px]) < [540, 960]
        )
    im = v.load_image(scale=0.25)
    assert im.rgb.shape == (3, 480, 270) and im.valid.shape == (1, 480, 270)
    valid = im.valid[0]
    assert 0.9 < im.valid_fraction < 1.0
    assert valid[240, 135] == 1 and valid[0, 0] == 0  # the corners come from outside the photo
