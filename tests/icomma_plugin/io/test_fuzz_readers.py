"""Fuzzing the file readers: a clean error naming the file, or a valid result.

For a corrupted PLY, COLMAP (binary and text), cameras.json, transforms.json or cfg_args file;
never a crash, a hang or an allocation sized by a corrupt count.

Two kinds of test per format: random corruption (hypothesis, fixed example counts,
derandomized: fuzz_strategies.fuzz_settings) of a valid seed file (fuzz_seeds.py, both in
tests/helpers/), and an exhaustive sweep that sets every field of the seed to each telling value
once (random edits rarely put NaN into one chosen coordinate; a sweep always does). Outcomes are
checked by fuzz_strategies.read_clean and the assert_valid_* functions below.
"""
from __future__ import annotations

import json
import math
import re
import struct

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.io.cameras_json import CameraEntry, read_cameras_json, write_cameras_json
from icomma_plugin.io.datasets import SceneData, read_colmap, read_dataset
from icomma_plugin.io.model_folder import (
    ModelFolder,
    format_cfg_args,
    load_model_folder,
    parse_cfg_args,
    write_model_folder,
)
from icomma_plugin.io.ply import (
    read_gaussian_ply,
    read_points_ply,
    write_gaussian_ply,
    write_points_ply,
)
from tests.helpers import fuzz_seeds as seeds
from tests.helpers.fuzz_strategies import (
    corrupt_bytes,
    corrupt_json,
    corrupt_ply,
    corrupt_text,
    fuzz_settings,
    json_paths,
    pack,
    read_clean,
)
from tests.helpers.gaussians import random_gaussians

# Corrupt values such as 1e308 make numpy warn about overflow on the way to a clean error.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """One folder reused by every example of a test (hypothesis runs them in one call)."""
    return tmp_path_factory.mktemp("fuzz")


# ----------------------------------------------------------------------------- validity

def assert_valid_gaussians(m):
    assert isinstance(m, GaussianModel) and 0 <= m.sh_degree <= 3
    for name, t in m.tensors().items():
        assert t.dtype == torch.float32 and t.shape[0] == m.num_gaussians, name
        assert bool(torch.isfinite(t).all()), f"non-finite {name} returned"


def assert_valid_points(result):
    xyz, rgb = result
    assert xyz.dtype == np.float64 and xyz.ndim == 2 and xyz.shape[1] == 3
    assert np.isfinite(xyz).all(), "non-finite points returned"
    if rgb is not None:
        assert rgb.shape == xyz.shape and ((rgb >= 0) & (rgb <= 1)).all(), "colours not in [0, 1]"


def assert_valid_cameras(entries):
    assert isinstance(entries, list)
    for e in entries:
        assert isinstance(e, CameraEntry)
        assert isinstance(e.width, int) and isinstance(e.height, int)
        assert e.width > 0 and e.height > 0
        assert math.isfinite(e.fx) and math.isfinite(e.fy) and e.fx > 0 and e.fy > 0
        assert e.c2w.shape == (4, 4) and np.isfinite(e.c2w).all()
        R = e.c2w[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-3 and np.linalg.det(R) > 0


def assert_valid_scene(s):
    assert isinstance(s, SceneData)
    for v in s.views("all"):
        assert v.c2w.shape == (4, 4) and np.isfinite(v.c2w).all()
        i = v.intrinsics
        assert all(math.isfinite(x) for x in (i.fx, i.fy, i.cx_px, i.cy_px)), "intrinsics"
        if v.distortion is not None:
            assert all(math.isfinite(c) for c in v.distortion), "non-finite distortion returned"
    if s.points is not None:
        assert s.points.ndim == 2 and s.points.shape[1] == 3
        assert np.isfinite(s.points).all(), "non-finite points returned"
        assert s.colors.shape == s.points.shape
        assert ((s.colors >= 0) & (s.colors <= 1)).all(), "colours not in [0, 1]"


# ----------------------------------------------------------------------------- PLY

@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_gaussian_ply(work, data):
    src = work / "_seed.ply"
    write_gaussian_ply(random_gaussians(data.draw(st.sampled_from([0, 1, 3])),
                                       data.draw(st.integers(0, 3))), src)
    seed = src.read_bytes()
    if data.draw(st.booleans()):
        seed = seeds.as_ascii(seed)
    p = work / "point_cloud.ply"
    p.write_bytes(data.draw(corrupt_ply(seed)))
    m, _ = read_clean(lambda: read_gaussian_ply(p), [str(p)])
    if m is not None:
        assert_valid_gaussians(m)


@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_points_ply(work, data):
    n = data.draw(st.sampled_from([0, 1, 4]))
    rng = np.random.default_rng(n)
    src = work / "_seed_pts.ply"
    write_points_ply(src, rng.normal(size=(n, 3)), rng.integers(0, 256, size=(n, 3)))
    seed = src.read_bytes()
    if data.draw(st.booleans()):
        seed = seeds.as_ascii(seed)
    p = work / "input.ply"
    p.write_bytes(data.draw(corrupt_ply(seed)))
    r, _ = read_clean(lambda: read_points_ply(p), [str(p)])
    if r is not None:
        assert_valid_points(r)


# ----------------------------------------------------------------------------- cameras.json

@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_cameras_json(work, data):
    src = work / "_seed_cameras.json"
    write_cameras_json(src, seeds.cameras(data.draw(st.integers(1, 3))))
    p = work / "cameras.json"
    p.write_bytes(data.draw(corrupt_json(json.loads(src.read_text()))))
    r, _ = read_clean(lambda: read_cameras_json(p), [str(p)])
    if r is not None:
        assert_valid_cameras(r)


# ----------------------------------------------------------------------------- cfg_args / folder

@fuzz_settings(300)
@given(data=st.data())
def test_fuzz_parse_cfg_args(data):
    text = data.draw(corrupt_text(format_cfg_args(seeds.CFG))).decode("utf-8", "replace")
    r, _ = read_clean(lambda: parse_cfg_args(text, "the/cfg_args"), ["the/cfg_args"])
    if r is not None:
        assert isinstance(r, dict) and all(isinstance(k, str) for k in r)


@pytest.fixture(scope="module")
def model_folder(tmp_path_factory):
    """A model folder and the valid bytes of its three files (restored before each example)."""
    root = tmp_path_factory.mktemp("model")
    write_model_folder(root, random_gaussians(3, 1), seeds.CFG, seeds.cameras(2), iteration=7)
    rels = ["cfg_args", "cameras.json", "point_cloud/iteration_7/point_cloud.ply"]
    return root, {r: (root / r).read_bytes() for r in rels}


@fuzz_settings(150)
@given(data=st.data())
def test_fuzz_model_folder(model_folder, data):
    """One of the folder's three files corrupted; load_model_folder stays clean."""
    root, valid = model_folder
    for rel, b in valid.items():
        (root / rel).write_bytes(b)
    rel = data.draw(st.sampled_from(sorted(valid)))
    f, b = root / rel, valid[rel]
    if rel == "cfg_args":
        f.write_bytes(data.draw(corrupt_text(b.decode())))
    elif rel == "cameras.json":
        f.write_bytes(data.draw(corrupt_json(json.loads(b))))
    else:
        f.write_bytes(data.draw(corrupt_ply(b)))
    r, _ = read_clean(lambda: load_model_folder(root), [str(f)])
    if r is not None:
        assert isinstance(r, ModelFolder) and isinstance(r.white_background, bool)
        assert_valid_gaussians(r.model)
        assert_valid_cameras(r.cameras)


# ----------------------------------------------------------------------------- COLMAP

@pytest.fixture(scope="module")
def colmap_root(tmp_path_factory):
    """A COLMAP folder with its image files; each example rewrites the sparse/0 files."""
    root = tmp_path_factory.mktemp("colmap")
    for im in seeds.COLMAP_IMAGES:
        f = root / "images" / im[4]
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b"")  # read_colmap only checks the files exist; images load lazily
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    return root, sparse


def _check_colmap(root, sparse, f):
    # Errors about the whole model (e.g. an image's camera missing) name the sparse folder.
    s, _ = read_clean(lambda: read_colmap(root), [str(f), str(sparse), str(root / "images")])
    if s is not None:
        assert_valid_scene(s)


@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_colmap_binary(colmap_root, data):
    files, slots = seeds.colmap_binary()
    root, sparse = colmap_root
    which = data.draw(st.sampled_from(sorted(files)))
    seeds.write_colmap_files(sparse, files, which,
                             data.draw(corrupt_bytes(files[which], slots[which])))
    _check_colmap(root, sparse, sparse / which)


@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_colmap_text(colmap_root, data):
    files = seeds.colmap_text()
    root, sparse = colmap_root
    which = data.draw(st.sampled_from([n for n in sorted(files) if n.endswith(".txt")]))
    seeds.write_colmap_files(sparse, files, which,
                             data.draw(corrupt_text(files[which].decode())))
    _check_colmap(root, sparse, sparse / which)


# ----------------------------------------------------------------------------- transforms.json

@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A capture folder whose images and points.ply stay; each example rewrites its json."""
    root = tmp_path_factory.mktemp("capture")
    (root / "images").mkdir()
    for k in range(3):
        Image.fromarray(np.full((6, 8, 3), 40 * k, np.uint8)).save(root / "images" / f"f_{k}.png")
    write_points_ply(root / "points.ply", np.eye(3), np.full((3, 3), 200, np.uint8))
    return root


def _check_transforms(root, f):
    s, _ = read_clean(lambda: read_dataset(root, random_init_points=64), [str(f)])
    if s is not None:
        assert s.source == "transforms_json"
        assert_valid_scene(s)


@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_transforms_json(capture, data):
    f = capture / "transforms.json"
    f.write_bytes(data.draw(corrupt_json(seeds.transforms(data.draw(st.integers(0, 2))))))
    _check_transforms(capture, f)


# ----------------------------------------------------------------------------- field sweeps

_SWEEP = {"Q": [0, 1, 2**32, 2**63, 2**64 - 1], "q": [0, 2**63], "i": [-1, 0, 2**31 - 1],
          "d": [math.nan, math.inf, -math.inf, 1e308, 0.0, -1.0], "B": [0, 255]}
_SWEEP_TOKENS = ["nan", "inf", "-1", "0", "300", "1e308", "9" * 400, "x"]
_SWEEP_JSON = [math.nan, math.inf, 1e308, -1.0, 0, 10**30, 10**400, "", None, [], {}, [[1.0]]]


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_sweep_colmap_binary_fields(colmap_root, name):
    files, slots = seeds.colmap_binary()
    root, sparse = colmap_root
    b = files[name]
    for off, fmt in slots[name]:
        for v in _SWEEP[fmt]:
            bad = b[:off] + pack(fmt, v) + b[off + struct.calcsize(fmt):]
            seeds.write_colmap_files(sparse, files, name, bad)
            _check_colmap(root, sparse, sparse / name)


@pytest.mark.parametrize("name", ["cameras.txt", "images.txt", "points3D.txt"])
def test_sweep_colmap_text_tokens(colmap_root, name):
    files = seeds.colmap_text()
    root, sparse = colmap_root
    text = files[name].decode()
    for m in re.finditer(r"\S+", text):
        if text[:m.start()].rsplit("\n", 1)[-1].startswith("#"):
            continue  # a comment
        for v in _SWEEP_TOKENS:
            bad = (text[:m.start()] + v + text[m.end():]).encode()
            seeds.write_colmap_files(sparse, files, name, bad)
            _check_colmap(root, sparse, sparse / name)


def _replaced(obj, path, value):
    obj = json.loads(json.dumps(obj))
    parent = obj
    for k in path[:-1]:
        parent = parent[k]
    parent[path[-1]] = value
    return obj


def test_sweep_cameras_json_nodes(work):
    seed = [c.to_json() for c in seeds.cameras(2)]
    p = work / "cameras.json"
    for path in json_paths(seed)[1:]:
        for v in _SWEEP_JSON:
            p.write_text(json.dumps(_replaced(seed, path, v)))
            r, _ = read_clean(lambda: read_cameras_json(p), [str(p)])
            if r is not None:
                assert_valid_cameras(r)


@pytest.mark.parametrize("variant", [0, 1, 2])
def test_sweep_transforms_json_nodes(capture, variant):
    seed = seeds.transforms(variant)
    f = capture / "transforms.json"
    # Frame 0 stands for the others, except frame 1's own camera keys (variant 1).
    paths = [p for p in json_paths(seed)[1:]
             if not (p[:1] == ("frames",) and len(p) > 1
                     and (p[1] == 2 or (p[1] == 1 and "transform_matrix" in p)))]
    for path in paths:
        for v in _SWEEP_JSON:
            f.write_text(json.dumps(_replaced(seed, path, v)))
            _check_transforms(capture, f)
