"""One deterministic test per reader bug the fuzz tests found (each failed before its fix).

Every case writes the smallest file that showed the bug and asserts the clean outcome: a
ValueError (DatasetError) naming the file and the field, raised before any large allocation.
"""
from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from PIL import Image

from icomma_plugin.io.cameras_json import CameraEntry, read_cameras_json, write_cameras_json
from icomma_plugin.io.datasets import DatasetError, read_colmap, read_transforms_json
from icomma_plugin.io.model_folder import load_model_folder, write_model_folder
from icomma_plugin.io.ply import (
    read_gaussian_ply,
    read_points_ply,
    write_gaussian_ply,
    write_points_ply,
)
from tests.helpers import fuzz_seeds as seeds
from tests.helpers.fuzz_strategies import read_clean
from tests.helpers.gaussians import random_gaussians


def _clean_error(call, path, *needles):
    """The call raises a clean error naming ``path`` and every needle (under the guards)."""
    r, err = read_clean(call, [str(path)])
    assert err is not None, f"expected an error, got {r!r}"
    for n in needles:
        assert n in str(err), str(err)
    return str(err)


# ----------------------------------------------------------------------------- PLY

def _with_count(path, count):
    data = path.read_bytes()
    head, sep, body = data.partition(b"end_header\n")
    lines = [f"element vertex {count}".encode() if ln.startswith(b"element vertex") else ln
             for ln in head.split(b"\n")]
    path.write_bytes(b"\n".join(lines) + sep + body)


@pytest.mark.parametrize("count", [2**31 - 1, 10**12, 10**18 - 1])
def test_ply_huge_vertex_count_rejected_before_allocation(tmp_path, count):
    # plyfile allocated count x row size up front: 139 GiB for 2^31 - 1 Gaussians.
    p = tmp_path / "point_cloud.ply"
    write_gaussian_ply(random_gaussians(2, 0), p)
    _with_count(p, count)
    _clean_error(lambda: read_gaussian_ply(p), p, "end-of-file", str(count))
    q = tmp_path / "input.ply"
    write_points_ply(q, np.zeros((2, 3)))
    _with_count(q, count)
    _clean_error(lambda: read_points_ply(q), q, "end-of-file", str(count))


def test_ply_huge_ascii_count_and_list_element_after_vertex(tmp_path):
    p = tmp_path / "a.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 99999999999\nproperty float x\n"
                  b"property float y\nproperty float z\nend_header\n0 0 0\n")
    _clean_error(lambda: read_points_ply(p), p, "end-of-file")
    # A face element after the vertices, with a corrupt list length: never read.
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
                  b"property float y\nproperty float z\nelement face 1\n"
                  b"property list uint double idx\nend_header\n"
                  + struct.pack("<fffI", 1, 2, 3, 2**32 - 1))
    xyz, rgb = read_points_ply(p)
    assert xyz.tolist() == [[1.0, 2.0, 3.0]] and rgb is None


def test_points_ply_non_finite_and_out_of_range_colours(tmp_path):
    p = tmp_path / "input.ply"
    write_points_ply(p, np.zeros((3, 3)))
    data = bytearray(p.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    data[body:body + 4] = struct.pack("<f", math.nan)  # x of point 0
    p.write_bytes(bytes(data))
    _clean_error(lambda: read_points_ply(p), p, "1 non-finite")
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                  b"property float z\nproperty float red\nproperty float green\n"
                  b"property float blue\nend_header\n0 0 0 300 0 -1\n")
    _clean_error(lambda: read_points_ply(p), p, "outside 0..255")


# ----------------------------------------------------------------------------- cameras.json

def _entry_json(**change):
    e = seeds.cameras(1)[0].to_json()
    e.update(change)
    return e


@pytest.mark.parametrize("raw, needle", [
    ("[" * 100_000, "RecursionError"),                       # was: RecursionError escaped
    ('[{"id": 1' + "0" * 5000 + "}]", "invalid JSON"),        # was: ValueError, no file name
])
def test_cameras_json_deep_or_huge_literal(tmp_path, raw, needle):
    p = tmp_path / "cameras.json"
    p.write_text(raw)
    _clean_error(lambda: read_cameras_json(p), p, needle)


@pytest.mark.parametrize("field, value", [
    ("fx", 10**400), ("position", [0, 10**400, 0]),  # was: OverflowError in math.isfinite
    ("width", 10**30), ("height", 2**20 + 1),          # was: accepted
])
def test_cameras_json_numbers_beyond_range(tmp_path, field, value):
    p = tmp_path / "cameras.json"
    p.write_text(json.dumps([_entry_json(**{field: value})]))
    msg = _clean_error(lambda: read_cameras_json(p), p, f"'{field}'")
    assert len(msg) < 400  # the 400-digit value is quoted cut short


def test_cameras_json_size_limit_is_inclusive(tmp_path):
    p = tmp_path / "cameras.json"
    e = seeds.cameras(1)[0]
    write_cameras_json(p, [CameraEntry(0, "a", 2**20, 1, e.c2w, 1.0, 1.0)])
    assert read_cameras_json(p)[0].width == 2**20


# ----------------------------------------------------------------------------- model folder

@pytest.fixture
def folder(tmp_path):
    root = tmp_path / "m"
    write_model_folder(root, random_gaussians(2, 1), seeds.CFG, seeds.cameras(2), iteration=7)
    return root


def test_cfg_args_not_utf8(folder):
    f = folder / "cfg_args"
    f.write_bytes(b"\xee" + f.read_bytes())  # was: UnicodeDecodeError escaped
    _clean_error(lambda: load_model_folder(folder), f, "UTF-8")


@pytest.mark.parametrize("value", ["'False'", "0", "None"])
def test_cfg_args_white_background_must_be_bool(folder, value):
    f = folder / "cfg_args"
    f.write_text(f.read_text().replace("white_background=True", f"white_background={value}"))
    # was: bool('False') is True, silently a white background
    _clean_error(lambda: load_model_folder(folder), f, "'white_background'")


def test_model_folder_huge_ply_count(folder):
    f = folder / "point_cloud" / "iteration_7" / "point_cloud.ply"
    _with_count(f, 2**31 - 1)
    _clean_error(lambda: load_model_folder(folder), f, "end-of-file")


# ----------------------------------------------------------------------------- COLMAP

def _colmap(root, fmt, edit=None):
    """Write the fuzz seed scene; ``edit(name, data) -> data`` changes one file."""
    for im in seeds.COLMAP_IMAGES:
        f = root / "images" / im[4]
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b"")
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    files = seeds.colmap_binary()[0] if fmt == "bin" else seeds.colmap_text()
    files = {n: (edit(n, b) if edit and b is not None else b) for n, b in files.items()}
    seeds.write_colmap_files(sparse, files)
    return sparse


def _replace_in(name, old, new):
    return lambda n, b: b.replace(old, new, 1) if n == name else b


def test_colmap_text_not_utf8(tmp_path):
    sparse = _colmap(tmp_path, "txt", lambda n, b: b"\x80" + b if n == "cameras.txt" else b)
    _clean_error(lambda: read_colmap(tmp_path), sparse / "cameras.txt", "UTF-8")


def test_colmap_text_width_beyond_float(tmp_path):
    wide = b" " + b"9" * 400 + b" 24 "
    sparse = _colmap(tmp_path, "txt", _replace_in("cameras.txt", b" 32 24 ", wide))
    # was: OverflowError comparing the principal point with the image centre
    _clean_error(lambda: read_colmap(tmp_path), sparse, "camera 1")


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_colmap_non_finite_distortion(tmp_path, fmt):
    if fmt == "bin":
        edit = _replace_in("cameras.bin", struct.pack("<d", 0.01), struct.pack("<d", math.nan))
    else:
        edit = _replace_in("cameras.txt", b"0.01", b"nan")
    sparse = _colmap(tmp_path, fmt, edit)
    _clean_error(lambda: read_colmap(tmp_path), sparse, "camera 2", "non-finite distortion")


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_colmap_non_finite_points(tmp_path, fmt):
    if fmt == "bin":
        edit = _replace_in("points3D.bin", struct.pack("<d", 0.2), struct.pack("<d", math.inf))
    else:
        edit = _replace_in("points3D.txt", b"0.2", b"inf")
    sparse = _colmap(tmp_path, fmt, edit)
    _clean_error(lambda: read_colmap(tmp_path), sparse / f"points3D.{fmt}", "non-finite")


@pytest.mark.parametrize("rgb", [b"300", b"-1", b"9" * 400])
def test_colmap_text_colour_out_of_range(tmp_path, rgb):
    sparse = _colmap(tmp_path, "txt", _replace_in("points3D.txt", b" 255 128 0 ",
                                                  b" " + rgb + b" 128 0 "))
    _clean_error(lambda: read_colmap(tmp_path), sparse / "points3D.txt", "0..255")


def test_colmap_image_name_too_long(tmp_path):
    sparse = _colmap(tmp_path, "txt", _replace_in("images.txt", b"img_00.png", b"9" * 400))
    # was: OSError (ENAMETOOLONG) from Path.is_file
    _clean_error(lambda: read_colmap(tmp_path), sparse, "image 10", "name")


# ----------------------------------------------------------------------------- transforms.json

@pytest.fixture
def capture(tmp_path):
    (tmp_path / "images").mkdir()
    for k in range(3):
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(tmp_path / "images" / f"f_{k}.png")
    write_points_ply(tmp_path / "points.ply", np.eye(3))
    return tmp_path


def _read_tf(root):
    return read_transforms_json(root, random_init_points=16)


@pytest.mark.parametrize("raw", ['{"frames": ' + "[" * 100_000, '{"w": 1' + "0" * 5000 + "}"])
def test_transforms_deep_or_huge_literal(capture, raw):
    f = capture / "transforms.json"
    f.write_text(raw)  # was: RecursionError / a ValueError without the file name
    _clean_error(lambda: _read_tf(capture), f, "malformed JSON")


def test_transforms_int_beyond_float(capture):
    f = capture / "transforms.json"
    seed = seeds.transforms(2)
    f.write_text(json.dumps(dict(seed, fl_x=10**400)))  # was: OverflowError in math.isfinite
    _clean_error(lambda: _read_tf(capture), f, "'fl_x'")
    seed["frames"][0]["transform_matrix"][0][3] = 10**400  # was: OverflowError in np.array
    f.write_text(json.dumps(seed))
    _clean_error(lambda: _read_tf(capture), f, "frame 0", "'transform_matrix'")


def test_transforms_huge_translation_random_points(capture):
    f = capture / "transforms.json"
    seed = seeds.transforms(2)
    seed["frames"][0]["transform_matrix"][0][3] = 1e308  # was: Inf random initial points
    f.write_text(json.dumps(seed))
    with pytest.raises(DatasetError, match="too large"):
        _read_tf(capture)
