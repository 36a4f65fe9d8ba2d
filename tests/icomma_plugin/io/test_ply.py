import logging

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.io.ply import (
    read_gaussian_ply,
    read_points_ply,
    write_gaussian_ply,
    write_points_ply,
)
from tests.helpers.gaussians import random_gaussians


def _upstream_attributes(degree):
    # gaussian-splatting GaussianModel.construct_list_of_attributes
    K = (degree + 1) ** 2 - 1
    names = ["x", "y", "z", "nx", "ny", "nz"]
    names += [f"f_dc_{i}" for i in range(3)]
    names += [f"f_rest_{i}" for i in range(3 * K)]
    names += ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    return names


def _upstream_save_ply(m: GaussianModel, path, dtypes=None, values=None):
    """Replica of upstream GaussianModel.save_ply (features stored as [P, coeffs, 3])."""
    P = m.num_gaussians
    xyz = m.means.numpy()
    normals = np.zeros_like(xyz)
    f_dc = m.sh_dc.transpose(1, 2).flatten(start_dim=1).numpy()
    f_rest = m.sh_rest.transpose(1, 2).flatten(start_dim=1).numpy()
    attrs = np.concatenate(
        (xyz, normals, f_dc, f_rest, m.opacity_logit.numpy(), m.scale_log.numpy(), m.quat.numpy()),
        axis=1,
    )
    names = _upstream_attributes(m.sh_degree)
    dtypes = dtypes or {}
    dtype_full = [(n, dtypes.get(n, "f4")) for n in names]
    elements = np.empty(P, dtype=dtype_full)
    elements[:] = list(map(tuple, attrs))
    for n, v in (values or {}).items():
        elements[n] = v
    PlyData([PlyElement.describe(elements, "vertex")]).write(str(path))


def _assert_same(a: GaussianModel, b: GaussianModel):
    assert a.sh_degree == b.sh_degree
    for k, v in a.tensors().items():
        assert torch.equal(v, getattr(b, k)), k


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip(tmp_path, degree):
    m = random_gaussians(7, degree)
    p = tmp_path / "sub" / "point_cloud.ply"
    write_gaussian_ply(m, p)
    back = read_gaussian_ply(p)
    _assert_same(m, back)
    assert back.dtype == torch.float32
    assert [f.name for f in tmp_path.joinpath("sub").iterdir()] == ["point_cloud.ply"]  # no temp


def test_header_layout_matches_upstream(tmp_path):
    p = tmp_path / "a.ply"
    write_gaussian_ply(random_gaussians(7, 3), p)
    ply = PlyData.read(str(p))
    assert ply.text is False and ply.byte_order == "<"
    props = ply["vertex"].properties
    assert [q.name for q in props] == _upstream_attributes(3)
    assert len(props) == 62
    assert all(np.dtype(q.val_dtype) == np.dtype("<f4") for q in props)
    assert np.all(ply["vertex"]["nx"] == 0)


def test_reads_upstream_written_file_channel_major(tmp_path):
    P, K = 4, 15
    m = random_gaussians(P, 3)
    # Identifiable SH values: sh_rest[p, k, c] = 100 p + 10 k + c.
    p_, k_, c_ = torch.meshgrid(torch.arange(P), torch.arange(K), torch.arange(3), indexing="ij")
    m = GaussianModel(m.means, m.sh_dc, (100 * p_ + 10 * k_ + c_).float(), m.opacity_logit,
                      m.scale_log, m.quat, 3)
    path = tmp_path / "upstream.ply"
    _upstream_save_ply(m, path)
    raw = PlyData.read(str(path))["vertex"]
    # On disk channel-major: f_rest_{c*15 + k} holds coefficient k+1 of channel c.
    assert raw["f_rest_16"][2] == 100 * 2 + 10 * 1 + 1
    back = read_gaussian_ply(path)
    _assert_same(m, back)
    # Our writer produces the same bytes as upstream's save_ply on a little-endian machine.
    ours = tmp_path / "ours.ply"
    write_gaussian_ply(m, ours)
    assert ours.read_bytes() == path.read_bytes()


def test_f_rest_names_sorted_numerically(tmp_path):
    # Properties stored in lexicographic order (f_rest_1, f_rest_10, ..., f_rest_2) must still
    # be read by number, as upstream load_ply sorts them.
    names = _upstream_attributes(2)
    rest = [n for n in names if n.startswith("f_rest_")]
    order = names[:9] + sorted(rest) + names[9 + len(rest):]
    assert order != names
    arr = np.empty(3, dtype=[(n, "f4") for n in order])
    for i, n in enumerate(names):
        arr[n] = np.arange(3, dtype=np.float32) + i
    p = tmp_path / "lex.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(p))
    back = read_gaussian_ply(p)
    assert back.sh_degree == 2
    # f_rest_{c*8 + k} -> sh_rest[:, k, c]; value of point 0 = index of the name in `names`.
    for c in range(3):
        for k in range(8):
            assert back.sh_rest[0, k, c].item() == names.index(f"f_rest_{c * 8 + k}")
    assert back.quat[1, 0].item() == names.index("rot_0") + 1


def _err(path, *needles):
    with pytest.raises(ValueError) as ei:
        read_gaussian_ply(path)
    msg = str(ei.value)
    assert str(path) in msg
    for n in needles:
        assert n in msg, msg
    return msg


def test_missing_file(tmp_path):
    _err(tmp_path / "nope.ply", "not found")


def test_not_a_ply(tmp_path):
    p = tmp_path / "x.ply"
    p.write_text("hello world\n")
    _err(p, "not a PLY")


def test_truncated(tmp_path):
    p = tmp_path / "t.ply"
    write_gaussian_ply(random_gaussians(10), p)
    data = p.read_bytes()
    p.write_bytes(data[:-37])
    _err(p, "end-of-file")
    p.write_bytes(data[:150])  # cut inside the header
    _err(p, "cannot parse")


def test_missing_fields(tmp_path):
    names = [n for n in _upstream_attributes(0) if n not in ("opacity", "scale_1")]
    arr = np.zeros(2, dtype=[(n, "f4") for n in names])
    p = tmp_path / "m.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(p))
    _err(p, "missing", "opacity", "scale_1")


def test_no_vertex_element(tmp_path):
    arr = np.zeros(2, dtype=[("x", "f4")])
    p = tmp_path / "f.ply"
    PlyData([PlyElement.describe(arr, "face")]).write(str(p))
    _err(p, "no 'vertex' element", "face")


def test_bad_f_rest_count(tmp_path):
    names = _upstream_attributes(0)
    names = names[:9] + [f"f_rest_{i}" for i in range(10)] + names[9:]
    arr = np.zeros(2, dtype=[(n, "f4") for n in names])
    p = tmp_path / "r.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(p))
    _err(p, "10 f_rest", "0, 9, 24, 45")


@pytest.mark.parametrize("field,dtype,word", [("opacity", "f8", "float64"), ("x", "i4", "int32")])
def test_wrong_types(tmp_path, field, dtype, word):
    p = tmp_path / "w.ply"
    _upstream_save_ply(random_gaussians(3, 1), p, dtypes={field: dtype})
    _err(p, "float32", field, word)


def test_nan_and_inf(tmp_path):
    p = tmp_path / "n.ply"
    m = random_gaussians(5, 0)
    _upstream_save_ply(m, p, values={
        "opacity": np.array([np.nan, 0, np.nan, 0, 0], np.float32),
        "x": np.array([0, np.inf, 0, 0, 0], np.float32),
    })
    msg = _err(p, "3 non-finite", "'opacity': 2", "'x': 1")
    assert "NaN" in msg


def test_zero_gaussians_allowed_with_warning(tmp_path, caplog):
    p = tmp_path / "z.ply"
    write_gaussian_ply(GaussianModel.empty(sh_degree=3), p)
    with caplog.at_level(logging.WARNING, logger="icomma_plugin.io.ply"):
        m = read_gaussian_ply(p)
    assert m.num_gaussians == 0 and m.sh_degree == 3
    assert "zero Gaussians" in caplog.text


def test_write_refuses_non_finite(tmp_path):
    m = random_gaussians(2, 0)
    m.scale_log[1, 2] = float("nan")
    with pytest.raises(ValueError, match="scale_2"):
        write_gaussian_ply(m, tmp_path / "bad.ply")
    assert not any(tmp_path.iterdir())


def test_points_ply_round_trip(tmp_path):
    xyz = np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32)
    rgb = np.random.default_rng(1).integers(0, 256, size=(20, 3)).astype(np.uint8)
    p = tmp_path / "input.ply"
    write_points_ply(p, xyz, rgb)
    ply = PlyData.read(str(p))
    assert [q.name for q in ply["vertex"].properties] == [
        "x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert np.dtype(ply["vertex"].properties[6].val_dtype) == np.uint8
    xyz2, rgb2 = read_points_ply(p)
    assert np.array_equal(xyz2.astype(np.float32), xyz)
    assert np.allclose(rgb2 * 255, rgb)
