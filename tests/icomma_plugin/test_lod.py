"""icomma_plugin.lod: splitting into upstream-size models, and the level-of-detail reduction."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.fit.losses import psnr
from icomma_plugin.gaussians import quat_to_rotmat
from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.lod import (
    LodConfig,
    _rotmat_to_quat,
    reduce_model,
    split_gaussians,
    stacked_opacity,
)
from icomma_plugin.pose.convert import look_at_c2w
from icomma_plugin.render import render
from tests.helpers.demo import demo_model


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _model(means, scales, opacities, quats=None, degree: int = 0, dc=None) -> GaussianModel:
    means = torch.as_tensor(means, dtype=torch.float32)
    P = means.shape[0]
    op = torch.as_tensor(opacities, dtype=torch.float32).view(P, 1)
    quat = torch.tensor([[1.0, 0, 0, 0]]).repeat(P, 1) if quats is None else quats
    dc = torch.randn(P, 1, 3, generator=torch.Generator().manual_seed(1)) if dc is None else dc
    K = (degree + 1) ** 2 - 1
    return GaussianModel(means, dc, torch.zeros(P, K, 3), torch.log(op / (1 - op)),
                         torch.log(torch.as_tensor(scales, dtype=torch.float32)), quat, degree)


def _camera(eye=(0.0, -4.0, 0.0), side: int = 64) -> tuple:
    intr = Intrinsics(side, side, side * 1.2, side * 1.2)
    return intr, look_at_c2w(np.array(eye), np.zeros(3), up=(0.0, 0.0, 1.0))


def _render(model, intr, c2w) -> torch.Tensor:
    w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)
    with torch.no_grad():
        return render(model, intr, w2c, torch.zeros(3)).color


@pytest.fixture(scope="module")
def demo48(tmp_path_factory):
    scene, model = demo_model(tmp_path_factory.mktemp("demo48"), 48)
    return scene, model


# ------------------------------------------------------------------------------------------------
# stacked_opacity
# ------------------------------------------------------------------------------------------------
def test_stacked_opacity_profile_beats_the_naive_choices():
    o = torch.linspace(0.05, 0.99, 20, dtype=torch.float64)
    n = 6
    r = torch.linspace(0, 4, 400, dtype=torch.float64)
    G = torch.exp(-0.5 * r * r)

    def err(c):
        return (((1 - (1 - c[:, None] * G) ** n) - o[:, None] * G) ** 2 * r).sum(-1)

    c = stacked_opacity(o, n)
    assert torch.all((c > 0) & (c < 1)) and torch.all(c[1:] > c[:-1])
    assert torch.all(err(c) <= err(1 - (1 - o) ** (1.0 / n)) + 1e-12)  # centre-matched
    assert torch.all(err(c) <= err(o / n) + 1e-12)  # tail-matched
    assert torch.equal(stacked_opacity(o, 1), o)
    with pytest.raises(ValueError, match="n must be"):
        stacked_opacity(o, 0)


# ------------------------------------------------------------------------------------------------
# split_gaussians
# ------------------------------------------------------------------------------------------------
def test_split_counts_and_parents():
    m = _model(torch.randn(7, 3), torch.full((7, 3), 0.1), torch.full((7,), 0.5))
    g = torch.Generator().manual_seed(0)
    out = split_gaussians(m, target=30, generator=g)
    assert out.num_gaussians == 30
    # children of a parent are consecutive and carry its colour
    dc = out.sh_dc[:, 0, 0]
    runs = torch.unique_consecutive(dc, return_counts=True)[1]
    assert runs.numel() == 7 and sorted(runs.tolist()) == [4] * 5 + [5] * 2
    assert split_gaussians(m, factor=3).num_gaussians == 21
    a = split_gaussians(m, factor=3, generator=torch.Generator().manual_seed(5))
    b = split_gaussians(m, factor=3, generator=torch.Generator().manual_seed(5))
    assert all(torch.equal(x, y) for x, y in zip(a.tensors().values(), b.tensors().values()))


def test_split_gives_opaque_gaussians_more_children():
    m = _model(torch.randn(4, 3), torch.full((4, 3), 0.1), [0.1, 0.9, 0.5, 0.9])
    counts = torch.unique_consecutive(split_gaussians(m, target=40).sh_dc[:, 0, 0],
                                      return_counts=True)[1].tolist()
    w = torch.tensor([0.1, 0.9, 0.5, 0.9]) ** 4
    expect = (1 + torch.floor(36 * w / w.sum())).long()
    expect[torch.argsort(-w, stable=True)[: 40 - int(expect.sum())]] += 1
    assert counts == expect.tolist() and sum(counts) == 40 and counts[1] > counts[2] > counts[0]
    even = split_gaussians(m, target=40, opacity_power=0.0)
    assert torch.unique_consecutive(even.sh_dc[:, 0, 0], return_counts=True)[1].tolist() == [10] * 4
    with pytest.raises(ValueError, match="opacity_power"):
        split_gaussians(m, target=40, opacity_power=-1.0)


@pytest.mark.parametrize("kwargs, match", [
    (dict(), "exactly one of"),
    (dict(factor=2, target=20), "exactly one of"),
    (dict(factor=0), "factor must be"),
    (dict(target=3), "target must be"),
    (dict(factor=2, mode="densify"), "mode must be"),
    (dict(factor=2, spread=1.0), "spread must be"),
])
def test_split_bad_arguments(kwargs, match):
    m = _model(torch.randn(7, 3), torch.full((7, 3), 0.1), torch.full((7,), 0.5))
    with pytest.raises(ValueError, match=match):
        split_gaussians(m, **kwargs)


def _parent_cov(q, s):
    R = quat_to_rotmat(q[None].double())[0]
    return R @ torch.diag(s.double() ** 2) @ R.T


def test_split_upstream_rule():
    q = torch.tensor([[0.9, 0.2, -0.3, 0.1]])
    s = torch.tensor([[0.3, 0.1, 0.05]])
    m = _model(torch.tensor([[1.0, 2.0, 3.0]]), s, [0.7], quats=q)
    N = 20000
    out = split_gaussians(m, factor=N, mode="upstream")
    assert torch.allclose(out.scales(), (s / (0.8 * N)).expand(N, 3), rtol=1e-5)
    assert torch.equal(out.opacity_logit, m.opacity_logit.expand(N, 1))
    assert torch.equal(out.quat, q.expand(N, 4))
    # children sampled from the parent's Gaussian: offsets have its covariance
    d = (out.means - m.means).double()
    assert d.mean(0).abs().max() < 0.01
    assert torch.allclose(d.T @ d / N, _parent_cov(q[0], s[0]), atol=2e-3)


def test_split_preserve_keeps_the_covariance_and_the_stack_opacity():
    q = torch.tensor([[0.9, 0.2, -0.3, 0.1]])
    s = torch.tensor([[0.3, 0.1, 0.05]])
    m = _model(torch.tensor([[1.0, 2.0, 3.0]]), s, [0.7], quats=q)
    N = 20000
    out = split_gaussians(m, factor=N, mode="preserve", spread=0.3)
    d = (out.means - m.means).double()
    child = _parent_cov(q[0], out.scales()[0])
    assert torch.allclose(d.T @ d / N + child, _parent_cov(q[0], s[0]), atol=2e-3)
    c = stacked_opacity(torch.tensor([0.7]), N)
    assert torch.allclose(out.opacities(), c.expand(N, 1), rtol=1e-4)


def test_split_preserve_renders_the_same_image(demo48):
    scene, model = demo48
    split = split_gaussians(model, factor=4)
    intr = Intrinsics(48, 48, 48 * 0.9, 48 * 0.9)
    for eye in ((4.0, 0.0, 2.2), (0.0, 4.0, 2.2)):
        c2w = look_at_c2w(np.array(eye), np.zeros(3), up=(0.0, 0.0, 1.0))
        full = _render(model, intr, c2w).clamp(0, 1)
        assert psnr(_render(split, intr, c2w), full) >= 35.0
        # the literal upstream rule does not keep the image
        upstream = split_gaussians(model, factor=4, mode="upstream")
        assert psnr(_render(upstream, intr, c2w), full) < 35.0


# ------------------------------------------------------------------------------------------------
# reduce_model
# ------------------------------------------------------------------------------------------------
def test_rotmat_to_quat_round_trip():
    q = torch.nn.functional.normalize(torch.randn(500, 4, generator=torch.Generator()
                                                   .manual_seed(3), dtype=torch.float64), dim=-1)
    back = _rotmat_to_quat(quat_to_rotmat(q))
    assert torch.allclose(quat_to_rotmat(back), quat_to_rotmat(q), atol=1e-12)
    assert torch.all(back[:, 0] >= 0)


def test_transparent_gaussians_are_left_out_exactly():
    g = torch.Generator().manual_seed(0)
    P = 400
    means = torch.rand(P, 3, generator=g) - 0.5
    op = torch.rand(P, generator=g) * 0.9 + 0.05
    op[::4] = 0.5 / 255.0
    m = _model(means, torch.full((P, 3), 0.03), op)
    intr, c2w = _camera()
    red, info = reduce_model(m, intr, [c2w], LodConfig(merge_below_px=0.0))
    assert info.dropped_opacity == P // 4 and red.num_gaussians == P - P // 4
    assert torch.equal(_render(red, intr, c2w), _render(m, intr, c2w))


def test_merge_is_moment_matched():
    means = [[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [0.0, 0.002, 0.0], [0.5, 0.5, 0.5]]
    scales = [[1e-3, 1e-3, 1e-3], [2e-3, 1e-3, 1e-3], [1e-3, 1e-3, 3e-3], [1.0, 1.0, 1.0]]
    op = [0.5, 0.8, 0.3, 0.9]
    m = _model(means, scales, op, degree=1)
    intr, c2w = _camera(eye=(0.0, -40.0, 0.0))
    red, info = reduce_model(m, intr, [c2w], LodConfig(cell_px=4.0))
    assert (info.merged_inputs, info.merged_outputs, info.kept) == (3, 1, 1)
    assert red.num_gaussians == 2 and torch.equal(red.means[0], m.means[3])
    w = torch.tensor(op[:3], dtype=torch.float64) * torch.tensor(scales[:3]).double().prod(-1)
    mu = (w[:, None] * torch.tensor(means[:3]).double()).sum(0) / w.sum()
    assert torch.allclose(red.means[1].double(), mu, atol=1e-7)
    second = sum(w[i] * (torch.diag(torch.tensor(scales[i]).double() ** 2)
                         + torch.outer(torch.tensor(means[i]).double(),
                                       torch.tensor(means[i]).double())) for i in range(3))
    cov = second / w.sum() - torch.outer(mu, mu)
    got = _parent_cov(red.quat[1], red.scales()[1])
    assert torch.allclose(got, cov, atol=1e-9, rtol=1e-3)
    assert math.isclose(float(red.opacities()[1]), 1 - 0.5 * 0.2 * 0.7, rel_tol=1e-5)
    dc = (w[:, None] * m.sh_dc[:3, 0].double()).sum(0) / w.sum()
    assert torch.allclose(red.sh_dc[1, 0].double(), dc, atol=1e-6)


def _dust(P=3000, seed=0):
    """A cloud of sub-pixel Gaussians (from 16 units, 64 px: 0.2 unit a pixel) in a 1-unit box."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(P, 3, generator=g) - 0.5
    scales = torch.rand(P, 3, generator=g) * 2e-3 + 1e-3
    op = torch.rand(P, generator=g) * 0.5 + 0.2
    return _model(means, scales, op)


def test_subpixel_merge_keeps_the_image_and_is_deterministic():
    m = _dust()
    intr, c2w = _camera(eye=(0.0, -16.0, 0.0))
    red, info = reduce_model(m, intr, [c2w])
    assert info.output_count == red.num_gaussians < m.num_gaussians / 2
    assert psnr(_render(red, intr, c2w), _render(m, intr, c2w).clamp(0, 1)) > 30.0
    again, _ = reduce_model(m, intr, [c2w])
    assert all(torch.equal(a, b) for a, b in zip(red.tensors().values(),
                                                 again.tensors().values()))
    # seen only from far away, nothing is below a pixel from close by
    _, near = _camera(eye=(0.0, -1.0, 0.0))
    assert reduce_model(m, intr, [c2w, near])[1].merged_inputs < info.merged_inputs


def test_cap_on_the_count():
    m = _dust()
    intr, c2w = _camera(eye=(0.0, -16.0, 0.0))
    red, info = reduce_model(m, intr, [c2w], LodConfig(max_gaussians=100))
    assert red.num_gaussians <= 100 and info.cell_scale > 1.0 and not info.capped
    # a cap that the threshold alone meets leaves the cells at their size
    big = _model(torch.rand(400, 3, generator=torch.Generator().manual_seed(2)) - 0.5,
                 torch.full((400, 3), 0.1), torch.full((400,), 0.5))
    red, info = reduce_model(big, intr, [c2w], LodConfig(max_gaussians=300))
    assert red.num_gaussians <= 300 and info.merge_scale > 1.0 and info.cell_scale == 1.0


def test_drop_unseen():
    m = _model([[0.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, -10.0, 0.0]], torch.full((3, 3), 0.05),
               [0.5, 0.5, 0.5])
    intr, c2w = _camera(eye=(0.0, -4.0, 0.0))
    red, info = reduce_model(m, intr, [c2w], LodConfig(drop_unseen=True))
    assert info.dropped_unseen == 1 and red.num_gaussians == 2
    assert reduce_model(m, intr, [c2w])[0].num_gaussians == 3


@pytest.mark.parametrize("cfg, match", [
    (dict(min_opacity=1.0), "min_opacity"),
    (dict(merge_below_px=-1.0), "merge_below_px"),
    (dict(cell_px=0.0), "cell_px"),
    (dict(cell_sigmas=-1.0), "cell_sigmas"),
    (dict(max_gaussians=0), "max_gaussians"),
    (dict(cap_growth=1.0), "cap_growth"),
    (dict(drop_unseen=1), "drop_unseen"),
])
def test_lod_config_checks(cfg, match):
    with pytest.raises(ValueError, match=match):
        LodConfig(**cfg)


def test_reduce_model_bad_arguments():
    m = _dust(P=10)
    intr, c2w = _camera()
    with pytest.raises(ValueError, match="cameras_c2w"):
        reduce_model(m, intr, np.eye(3)[None])
    with pytest.raises(ValueError, match="cameras_c2w"):
        reduce_model(m, intr, [])
    with pytest.raises(ValueError, match="intrinsics"):
        reduce_model(m, (64, 64), [c2w])
    with pytest.raises(ValueError, match="cfg must be"):
        reduce_model(m, intr, [c2w], {"merge_below_px": 1.0})
