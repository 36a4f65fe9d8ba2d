import argparse
import json
import logging
import math

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.io.cameras_json import (
    CameraEntry,
    entry_to_intrinsics,
    find_entry,
    read_cameras_json,
    write_cameras_json,
)
from icomma_plugin.io.model_folder import (
    format_cfg_args,
    load_model_folder,
    parse_cfg_args,
    write_model_folder,
)
from icomma_plugin.io.ply import read_points_ply, write_gaussian_ply
from icomma_plugin.pose.convert import look_at_c2w
from tests.helpers.gaussians import random_gaussians

CFG_2023 = ("Namespace(data_device='cuda', eval=True, images='images', "
            "model_path='./output/7a3c1b2e-4', resolution=-1, sh_degree=3, "
            "source_path='/data/nerf_synthetic/lego', white_background=True)")
CFG_2024 = ("Namespace(data_device='cuda', depths='', eval=True, images='images', "
            "model_path='/home/u/output/bicycle', resolution=4, sh_degree=3, "
            "source_path='/home/u/360_v2/bicycle', train_test_exp=False, white_background=False)\n")


def _cameras(n=3):
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        c2w = look_at_c2w([4 * math.cos(a), 4 * math.sin(a), 1.0], [0, 0, 0], up=[0, 0, 1])
        out.append(CameraEntry(i, f"r_{i}", 800, 600, c2w, 1111.1 + i, 1100.5))
    return out


# ----------------------------------------------------------------------------- cfg_args


def test_parse_cfg_args_2023_and_2024():
    c = parse_cfg_args(CFG_2023)
    assert c == {"data_device": "cuda", "eval": True, "images": "images",
                 "model_path": "./output/7a3c1b2e-4", "resolution": -1, "sh_degree": 3,
                 "source_path": "/data/nerf_synthetic/lego", "white_background": True}
    c = parse_cfg_args(CFG_2024)
    assert c["depths"] == "" and c["train_test_exp"] is False and c["resolution"] == 4
    assert list(c) == sorted(c)


def test_format_cfg_args_matches_namespace_repr():
    c = parse_cfg_args(CFG_2024)
    text = format_cfg_args(c)
    assert text == str(argparse.Namespace(**c)) == CFG_2024.strip()
    assert parse_cfg_args(text) == c
    assert format_cfg_args({"b": 1, "a": "x"}) == "Namespace(a='x', b=1)"
    with pytest.raises(ValueError, match="literal"):
        format_cfg_args({"a": object()})


@pytest.mark.parametrize("text", [
    "Namespace(source_path=__import__('os').system('touch {marker}'))",
    "__import__('os').system('touch {marker}')",
    "Namespace(a=open('{marker}', 'w').write('x'))",
    "Namespace(**{{'a': __import__('os').system('touch {marker}')}})",
    "Namespace(a=(lambda: open('{marker}', 'w'))())",
])
def test_malicious_cfg_args_not_executed(tmp_path, text):
    marker = tmp_path / "pwned"
    cfg = tmp_path / "cfg_args"
    with pytest.raises(ValueError) as ei:
        parse_cfg_args(text.format(marker=marker), path=cfg)
    assert str(cfg) in str(ei.value)
    assert not marker.exists()


@pytest.mark.parametrize("text,needle", [
    ("Namespace(a=1", "Namespace"),
    ("dict(a=1)", "Namespace"),
    ("Namespace(1, a=2)", "keyword"),
    ("Namespace(a=1, a=2)", "twice"),
    ("", "Namespace"),
])
def test_bad_cfg_args(text, needle):
    with pytest.raises(ValueError, match=needle):
        parse_cfg_args(text, path="/m/cfg_args")


# ----------------------------------------------------------------------------- cameras.json


def test_cameras_json_round_trip_and_layout(tmp_path):
    cams = _cameras()
    p = tmp_path / "cameras.json"
    write_cameras_json(p, cams)
    raw = json.loads(p.read_text())
    assert list(raw[1]) == ["id", "img_name", "width", "height", "position", "rotation", "fy", "fx"]
    assert np.allclose(raw[1]["position"], cams[1].c2w[:3, 3])
    assert np.allclose(raw[1]["rotation"], cams[1].c2w[:3, :3])
    back = read_cameras_json(p)
    for a, b in zip(cams, back):
        assert (a.id, a.img_name, a.width, a.height, a.fx, a.fy) == (
            b.id, b.img_name, b.width, b.height, b.fx, b.fy)
        assert np.array_equal(a.c2w, b.c2w) and b.c2w.dtype == np.float64
    assert np.allclose(back[0].w2c @ back[0].c2w, np.eye(4))


def test_reads_upstream_camera_to_json(tmp_path):
    # Replica of upstream camera_to_JSON from a CameraInfo (R = c2w rotation, T = w2c translation).
    c2w = look_at_c2w([1.0, -3.0, 2.0], [0, 0, 0.2])
    w2c = np.linalg.inv(c2w)
    R, T = w2c[:3, :3].T, w2c[:3, 3]
    Rt = np.zeros((4, 4))
    Rt[:3, :3], Rt[:3, 3], Rt[3, 3] = R.transpose(), T, 1.0
    W2C = np.linalg.inv(Rt)  # (upstream's name; it is the c2w)
    fovx = 0.69
    fx = 800 / (2 * math.tan(fovx / 2))
    entry = {"id": 0, "img_name": "r_0", "width": 800, "height": 800,
             "position": W2C[:3, 3].tolist(), "rotation": [x.tolist() for x in W2C[:3, :3]],
             "fy": fx, "fx": fx}
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps([entry]))
    (e,) = read_cameras_json(p)
    assert np.allclose(e.c2w, c2w, atol=1e-12)
    k = entry_to_intrinsics(e)
    assert k == Intrinsics(800, 800, fx, fx)
    assert math.isclose(k.fov_x, fovx)


@pytest.mark.parametrize("mutate,needles", [
    (lambda d: d[1].pop("fx"), ["entry 1", "fx"]),
    (lambda d: d[2].__setitem__("width", "800"), ["entry 2", "width"]),
    (lambda d: d[0].__setitem__("position", [0, 1]), ["entry 0", "position"]),
    (lambda d: d[0].__setitem__("rotation", [[1, 0, 0], [0, 2, 0], [0, 0, 1]]),
     ["entry 0", "rotation", "not a rotation"]),
    (lambda d: d[1].__setitem__("fy", -3.0), ["entry 1", "fy"]),
])
def test_bad_cameras_json(tmp_path, mutate, needles):
    p = tmp_path / "cameras.json"
    data = [c.to_json() for c in _cameras()]
    mutate(data)
    p.write_text(json.dumps(data))
    with pytest.raises(ValueError) as ei:
        read_cameras_json(p)
    for n in [str(p)] + needles:
        assert n in str(ei.value)


def test_cameras_json_not_json_or_not_list(tmp_path):
    p = tmp_path / "cameras.json"
    p.write_text("{broken")
    with pytest.raises(ValueError, match="invalid JSON"):
        read_cameras_json(p)
    p.write_text("{}")
    with pytest.raises(ValueError, match="list"):
        read_cameras_json(p)


def test_find_entry():
    cams = _cameras()
    cams[2] = CameraEntry(2, "frame_0002.png", 800, 600, cams[2].c2w, 1000.0, 1000.0)
    assert find_entry(cams, 1) is cams[1]
    assert find_entry(cams, "r_0") is cams[0]
    assert find_entry(cams, "r_0.png") is cams[0]  # extension-insensitive
    assert find_entry(cams, "frame_0002") is cams[2]
    with pytest.raises(ValueError, match="r_0"):
        find_entry(cams, "nope")
    with pytest.raises(ValueError, match="id 9"):
        find_entry(cams, 9)
    # lego's train and test splits both have an r_0: the error gives the ids to use instead
    twin = CameraEntry(7, "r_0", 800, 800, cams[0].c2w, 1000.0, 1000.0)
    with pytest.raises(ValueError, match=r"ids \[0, 7\]"):
        find_entry(cams + [twin], "r_0")
    assert find_entry(cams + [twin], 7) is twin


# ----------------------------------------------------------------------------- model folder


def _write(root, iterations=(7000, 30000), cfg=CFG_2023, **kw):
    for it in iterations:
        write_model_folder(root, random_gaussians(6, seed=it), parse_cfg_args(cfg), _cameras(), it,
                           **kw)


def test_write_and_load_latest(tmp_path):
    root = tmp_path / "model"
    xyz = np.random.default_rng(0).uniform(-1.3, 1.3, (50, 3))
    _write(root, input_points=(xyz, np.full((50, 3), 0.5)))
    assert (root / "cfg_args").read_text() == CFG_2023
    mf = load_model_folder(root)
    assert mf.iteration == 30000 and mf.path == root
    assert mf.cfg["white_background"] is True and mf.white_background
    for k, v in random_gaussians(6, seed=30000).tensors().items():
        assert torch.equal(getattr(mf.model, k), v)
    assert len(mf.cameras) == 3 and mf.cameras[2].img_name == "r_2"
    assert load_model_folder(root, iteration=7000).iteration == 7000
    assert load_model_folder(root, iteration=-1).iteration == 30000
    pts, rgb = read_points_ply(root / "input.ply")
    assert np.allclose(pts, xyz, atol=1e-6) and np.allclose(rgb, 128 / 255)


def test_latest_is_numeric_not_lexicographic(tmp_path):
    root = tmp_path / "m"
    _write(root, iterations=(900, 30000, 7000))
    (root / "point_cloud" / "iteration_abc").mkdir()  # ignored
    assert load_model_folder(root).iteration == 30000


def test_requested_iteration_missing_lists_available(tmp_path):
    root = tmp_path / "m"
    _write(root)
    with pytest.raises(ValueError) as ei:
        load_model_folder(root, iteration=5000)
    msg = str(ei.value)
    assert "5000" in msg and "[7000, 30000]" in msg and str(root) in msg


def test_missing_cameras_json_gives_empty_list(tmp_path, caplog):
    root = tmp_path / "m"
    _write(root, iterations=(30000,))
    (root / "cameras.json").unlink()
    with caplog.at_level(logging.WARNING, logger="icomma_plugin.io.model_folder"):
        mf = load_model_folder(root)
    assert mf.cameras == [] and "cameras.json" in caplog.text


def test_bad_folders(tmp_path):
    def err(path, *needles, named=None):
        with pytest.raises(ValueError) as ei:
            load_model_folder(path)
        for n in (str(named or path),) + needles:
            assert n in str(ei.value), str(ei.value)

    err(tmp_path / "absent", "not found")
    root = tmp_path / "m"
    root.mkdir()
    (root / "cameras.json").write_text("[]")
    err(root, "missing cfg_args", "cameras.json")
    (root / "cfg_args").write_text(CFG_2024)
    err(root, "no point_cloud/")
    (root / "point_cloud" / "junk").mkdir(parents=True)
    err(root, "no iteration_<N>", "junk/")
    (root / "point_cloud" / "iteration_100").mkdir()
    err(root, "missing", "point_cloud.ply")
    write_gaussian_ply(random_gaussians(6),
                       root / "point_cloud" / "iteration_100" / "point_cloud.ply")
    assert load_model_folder(root).iteration == 100
    (root / "cfg_args").write_text("Namespace(a=__import__('os'))")
    err(root, "not a Python literal", "'a'", named=root / "cfg_args")
    (root / "cfg_args").write_text(CFG_2024)
    (root / "point_cloud" / "iteration_100" / "point_cloud.ply").write_text("garbage")
    err(root, "not a PLY", named=root / "point_cloud" / "iteration_100" / "point_cloud.ply")


def test_never_overwrites_iteration_silently(tmp_path, caplog):
    root = tmp_path / "m"
    _write(root, iterations=(30000,))
    before = (root / "point_cloud" / "iteration_30000" / "point_cloud.ply").read_bytes()
    with pytest.raises(ValueError, match="overwrite=True"):
        write_model_folder(root, random_gaussians(6, seed=5), parse_cfg_args(CFG_2023), [], 30000)
    assert (root / "point_cloud" / "iteration_30000" / "point_cloud.ply").read_bytes() == before
    write_model_folder(root, random_gaussians(6, seed=5), parse_cfg_args(CFG_2023), [], 30000,
                       overwrite=True)
    assert torch.equal(load_model_folder(root).model.means, random_gaussians(6, seed=5).means)
    # Writing an earlier iteration keeps the later one (and says the later one stays the default).
    with caplog.at_level(logging.WARNING, logger="icomma_plugin.io.model_folder"):
        write_model_folder(root, random_gaussians(6, seed=6), parse_cfg_args(CFG_2023), [], 100)
    assert "later iterations [30000]" in caplog.text
    assert load_model_folder(root).iteration == 30000
    assert not [p for p in root.rglob("*.tmp")]
    with pytest.raises(ValueError, match="iteration"):
        write_model_folder(root, random_gaussians(6), {}, [], -5)


def test_the_fits_principal_point_convention(tmp_path):
    """cfg_args says; else metrics.json (an icomma fit before it said) means the dataset's."""
    root = tmp_path / "m"
    _write(root, iterations=(30000,))
    mf = load_model_folder(root)
    assert mf.principal_point == "centre" and mf.principal_point_assumed  # upstream's train.py
    (root / "metrics.json").write_text("{}")
    assert load_model_folder(root).principal_point == "dataset"
    assert not load_model_folder(root).principal_point_assumed
    assert load_model_folder(root).with_principal_point("centre").principal_point == "centre"
    assert mf.with_principal_point("auto") is mf and mf.with_principal_point(None) is mf
    with pytest.raises(ValueError, match="auto, dataset or centre.*'middle'"):
        mf.with_principal_point("middle")
    _write(tmp_path / "said", iterations=(30000,),
           cfg=CFG_2023.replace("Namespace(", "Namespace(principal_point='centre', "))
    (tmp_path / "said" / "metrics.json").write_text("{}")
    assert load_model_folder(tmp_path / "said").principal_point == "centre"
