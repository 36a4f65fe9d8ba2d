"""COLMAP's 2D observations and each record's precision (io/datasets/colmap_tracks.py).

On small models written by tests/helpers/colmap.py (COLMAP's layouts, not the reader's).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from icomma_plugin.io.datasets.colmap_tracks import (
    precision_of,
    read_image_tracks,
    record_precision,
)
from icomma_plugin.pose.convert import cameras_extent
from icomma_plugin.pose.precision import pose_precision
from tests.helpers.colmap import qvec_tvec, write_colmap_bin, write_colmap_txt
from tests.helpers.geometry import look_at_c2w

W, H = 640, 480


def _model(seed=0, distorted=True):
    """Four photos of 50 points; camera 1 is photo 1's alone, 2 is shared, 3 is distorted.

    With ``distorted=False`` camera 3 is a SIMPLE_PINHOLE (photo 4's alone).

    Returns (cameras, images, points, {name: (w2c, params, xy, xyz)}) with noisy observations;
    photo 2 also observes a point id that points3D lacks, and two observations have no point.
    """
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-1.0, 1.0, (50, 3))
    cameras = [(1, "SIMPLE_PINHOLE", W, H, [520.0, 320.5, 240.5]),
               (2, "PINHOLE", W, H, [500.0, 505.0, 319.0, 241.0]),
               (3, "SIMPLE_RADIAL", W, H, [500.0, 320.0, 240.0, 0.01]) if distorted
               else (3, "SIMPLE_PINHOLE", W, H, [500.0, 320.0, 240.0])]
    cam_of = {1: 1, 2: 2, 3: 2, 4: 3}
    images, truth = [], {}
    for i in range(1, 5):
        a = 2 * math.pi * i / 7
        w2c = np.linalg.inv(look_at_c2w([4 * math.cos(a), 4 * math.sin(a), 1.0]))
        model, p = cameras[cam_of[i] - 1][1], cameras[cam_of[i] - 1][4]
        fx, fy, cx, cy = p if model == "PINHOLE" else (p[0], p[0], p[1], p[2])
        xc = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        xy = np.stack([fx * xc[:, 0] / xc[:, 2] + cx, fy * xc[:, 1] / xc[:, 2] + cy], 1)
        xy += rng.normal(0.0, 0.7, xy.shape)
        obs = [(float(x), float(y), k + 1) for k, (x, y) in enumerate(xy)]
        obs += [(10.0, 20.0, -1), (30.0, 40.0, -1)]
        if i == 2:
            obs.append((50.0, 60.0, 999))  # a point that points3D does not hold
        q, t = qvec_tvec(w2c)
        name = f"sub/IMG_{i}.jpg"
        images.append((i, q, t, cam_of[i], name, obs))
        truth[name] = (w2c, (fx, fy, cx, cy), xy, xyz)
    points = [(k + 1, xyz[k], (128, 128, 128), 0.5, []) for k in range(50)]
    return cameras, images, points, truth


@pytest.mark.parametrize("writer", [write_colmap_bin, write_colmap_txt])
def test_tracks_and_record_precision_from_the_files(tmp_path, writer):
    cameras, images, points, truth = _model()
    writer(tmp_path / "sparse" / "0", cameras, images, points)
    cams, tracks, pts = read_image_tracks(tmp_path / "sparse" / "0")
    assert set(tracks) == set(truth) and len(pts) == 50
    t1 = tracks["sub/IMG_1.jpg"]
    assert len(t1.xy) == 50 and t1.camera_id == 1  # the two observations without a point dropped
    np.testing.assert_allclose(t1.w2c, truth["sub/IMG_1.jpg"][0], atol=1e-9)
    np.testing.assert_allclose(t1.xy, truth["sub/IMG_1.jpg"][2], atol=1e-9)

    with pytest.raises(ValueError, match="points must be"):
        record_precision(tmp_path, points="loose")
    table = record_precision(tmp_path)  # a distorted camera: the points held fixed for all
    assert set(table) == {"sub/IMG_1.jpg", "sub/IMG_2.jpg", "sub/IMG_3.jpg"}  # 4: distorted
    assert not any(v["points_free"] for v in table.values())
    assert table["sub/IMG_1.jpg"]["focal_free"]  # a camera of its own: its focal was estimated
    assert not table["sub/IMG_2.jpg"]["focal_free"] and not table["sub/IMG_3.jpg"]["focal_free"]
    assert table["sub/IMG_2.jpg"]["points"] == 50  # the unknown point id left out
    w2c, (fx, fy, cx, cy), xy, xyz = truth["sub/IMG_1.jpg"]
    want = pose_precision(w2c, fx, fy, cx, cy, xyz, xy, focal="shared")  # the points fixed
    got = table["sub/IMG_1.jpg"]
    assert got["rot_std_deg"] == pytest.approx(want.rot_std_deg, rel=1e-6)
    assert got["rms_px"] == pytest.approx(0.7, rel=0.25)
    extent = cameras_extent([np.linalg.inv(truth[n][0]) for n in truth])  # every posed photo
    assert got["centre_std_rel"] == pytest.approx(want.centre_std / extent, rel=1e-6)
    assert precision_of(table, "IMG_1.jpg") is got  # a reader's name without the folder
    assert precision_of(table, "IMG_1.png") is got  # or another extension
    assert precision_of(table, "IMG_9.jpg") is None


def test_with_the_points_free_the_bundle_says_more_than_each_photo_alone(tmp_path):
    """Pinhole cameras only: the whole reconstruction's uncertainty, the points estimated too."""
    cameras, images, points, truth = _model(distorted=False)
    write_colmap_bin(tmp_path / "sparse" / "0", cameras, images, points)
    free = record_precision(tmp_path)
    fixed = record_precision(tmp_path, points="fixed")
    assert set(free) == set(fixed) == set(truth)
    for name in truth:
        assert free[name]["points_free"] and not fixed[name]["points_free"]
        assert free[name]["rot_std_deg"] > fixed[name]["rot_std_deg"]  # the points move too
        assert len(free[name]["rot_cov"]) == 3


def test_no_model_or_no_points_gives_an_empty_table(tmp_path):
    assert record_precision(tmp_path) == {}
    cameras, images, _, _ = _model()
    write_colmap_bin(tmp_path / "sparse" / "0", cameras, images, [])
    (tmp_path / "sparse" / "0" / "points3D.bin").unlink()
    assert record_precision(tmp_path) == {}


def test_a_truncated_images_file_gives_an_empty_table_not_a_crash(tmp_path, caplog):
    cameras, images, points, _ = _model()
    write_colmap_bin(tmp_path / "sparse" / "0", cameras, images, points)
    p = tmp_path / "sparse" / "0" / "images.bin"
    p.write_bytes(p.read_bytes()[:200])
    with caplog.at_level("INFO"):
        assert record_precision(tmp_path) == {}
    assert any("truncated" in r.getMessage() for r in caplog.records)


def test_a_point_id_out_of_range_in_a_text_model_is_one_clear_error(tmp_path):
    from icomma_plugin.io.datasets import DatasetError
    from icomma_plugin.io.datasets.colmap import read_images_text

    cameras, images, points, _ = _model()
    iid, q, t, cid, name, obs = images[0]
    images[0] = (iid, q, t, cid, name, obs + [(1.0, 2.0, 2 ** 70)])
    write_colmap_txt(tmp_path / "sparse" / "0", cameras, images, points)
    with pytest.raises(DatasetError, match="out of the int64 range"):
        read_images_text(tmp_path / "sparse" / "0" / "images.txt", with_points=True)
    assert record_precision(tmp_path) == {}  # said in the log, not raised


def test_a_photo_without_a_valid_pose_is_left_out(tmp_path):
    cameras, images, points, truth = _model(distorted=False)
    iid, q, t, cid, name, obs = images[1]
    images[1] = (iid, [0.0, 0.0, 0.0, 0.0], t, cid, name, obs)  # COLMAP's "no pose"
    write_colmap_bin(tmp_path / "sparse" / "0", cameras, images, points)
    table = record_precision(tmp_path)
    assert set(table) == set(truth) - {name}
    assert all(v["points_free"] and np.isfinite(v["rot_std_deg"]) for v in table.values())
