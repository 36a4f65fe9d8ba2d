import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.pose.se3 import se3_exp
from icomma_plugin.render import render


def _blobs(P=12, dtype=torch.float64, seed=0, degree=1):
    g = torch.Generator().manual_seed(seed)
    K = (degree + 1) ** 2 - 1
    r = lambda *s: torch.randn(*s, generator=g, dtype=dtype)  # noqa: E731
    return GaussianModel(
        means=r(P, 3) * 0.4,
        sh_dc=r(P, 1, 3),
        sh_rest=r(P, K, 3) * 0.3,
        opacity_logit=torch.full((P, 1), 0.5, dtype=dtype),
        scale_log=torch.full((P, 3), -1.6, dtype=dtype),
        quat=r(P, 4),
        sh_degree=degree,
    )


def _w2c(dtype=torch.float64):
    w2c = torch.eye(4, dtype=dtype)
    w2c[2, 3] = 3.0
    return w2c


def test_single_gaussian_lands_on_projected_pixel():
    # A tiny isotropic Gaussian: its alpha footprint is symmetric about the projected centre,
    # which must follow u = fx x / z + cx with an off-centre principal point.
    d = torch.float64
    m = GaussianModel(
        means=torch.tensor([[0.2, -0.1, 0.0]], dtype=d),
        sh_dc=torch.zeros(1, 1, 3, dtype=d),
        sh_rest=torch.zeros(1, 0, 3, dtype=d),
        opacity_logit=torch.full((1, 1), 2.0, dtype=d),
        scale_log=torch.full((1, 3), -6.0, dtype=d),
        quat=torch.tensor([[1.0, 0, 0, 0]], dtype=d),
        sh_degree=0,
    )
    K = Intrinsics(40, 30, 45.0, 44.0, cx=17.0, cy=16.0)
    out = render(m, K, _w2c(d), torch.zeros(3, dtype=d), backend="reference")
    assert out.color.shape == (3, 30, 40) and out.alpha.shape == (1, 30, 40)
    a = out.alpha[0]
    ys, xs = torch.meshgrid(torch.arange(30, dtype=d), torch.arange(40, dtype=d), indexing="ij")
    u = (a * xs).sum() / a.sum()
    v = (a * ys).sum() / a.sum()
    assert abs(u.item() - (45.0 * 0.2 / 3.0 + 17.0)) < 0.05
    assert abs(v.item() - (44.0 * -0.1 / 3.0 + 16.0)) < 0.05
    assert out.radii[0] > 0


def test_pose_gradient_flows_and_matches_finite_differences():
    m = _blobs()
    K = Intrinsics(24, 20, 22.0, 22.0)
    bg = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    target = render(m, K, _w2c(), bg, backend="reference").color.detach()
    base = se3_exp(torch.tensor([0.03, -0.02, 0.05, 0.02, -0.03, 0.01], dtype=torch.float64))

    def loss_of(xi):
        out = render(m, K, se3_exp(xi) @ base @ _w2c(), bg, backend="reference")
        return ((out.color - target) ** 2).mean()

    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    loss = loss_of(xi)
    (g,) = torch.autograd.grad(loss, xi)
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    # Directional derivative along the gradient vs central differences.
    d = g / g.norm()
    eps = 1e-5
    with torch.no_grad():
        fd = (loss_of(eps * d) - loss_of(-eps * d)) / (2 * eps)
    assert torch.isclose(fd, g @ d, rtol=2e-3, atol=1e-9), (fd.item(), (g @ d).item())


def test_float32_model_and_w2c_cast():
    m = _blobs(dtype=torch.float32)
    K = Intrinsics(16, 12, 15.0, 15.0)
    w2c = _w2c(torch.float64).requires_grad_()
    out = render(m, K, w2c, torch.zeros(3), backend="reference")
    assert out.color.dtype == torch.float32
    out.color.sum().backward()
    assert w2c.grad is not None and torch.isfinite(w2c.grad).all()


def test_sh_degree_and_errors():
    m = _blobs(degree=1)
    K = Intrinsics(16, 12, 15.0, 15.0)
    bg = torch.zeros(3, dtype=torch.float64)
    c1 = render(m, K, _w2c(), bg, backend="reference").color
    c0 = render(m, K, _w2c(), bg, backend="reference", sh_degree=0).color
    assert not torch.allclose(c0, c1)
    with pytest.raises(ValueError, match="sh_degree"):
        render(m, K, _w2c(), bg, sh_degree=2)
    with pytest.raises(ValueError, match="w2c"):
        render(m, K, torch.eye(3), bg)
    with pytest.raises(ValueError, match="bg"):
        render(m, K, _w2c(), torch.zeros(4))
    with pytest.raises(ValueError, match="intrinsics"):
        render(m, None, _w2c(), bg)


def test_without_zero_sh_renders_the_same_and_remembers_its_scan(monkeypatch):
    m = _blobs(degree=2)
    assert m.without_zero_sh() is m  # higher bands in use
    K = Intrinsics(16, 12, 15.0, 15.0)
    bg = torch.zeros(3, dtype=torch.float64)
    m.sh_rest.zero_()  # an in-place change is seen (the version counter moves)
    low = m.without_zero_sh()
    assert low.sh_degree == 0
    assert torch.equal(render(low, K, _w2c(), bg, backend="reference").color,
                       render(m, K, _w2c(), bg, backend="reference").color)
    scans = []
    real_any = torch.Tensor.any
    monkeypatch.setattr(torch.Tensor, "any",
                        lambda t, *a, **k: scans.append(1) or real_any(t, *a, **k))
    det = m.detach()
    assert det.without_zero_sh().sh_degree == 0 and m.without_zero_sh().sh_degree == 0
    assert scans == []  # remembered, also by a detached copy (same storage and counter)
    det.sh_rest[0, 0, 0] = 1.0
    assert m.without_zero_sh() is m and len(scans) == 1
    with torch.inference_mode():  # no version counter: scanned each time, still right
        inf = _blobs(degree=1)
    assert inf.without_zero_sh() is inf and inf.without_zero_sh() is inf and len(scans) == 3


# ---------------------------------------------------------------------------------- prepared scene
from icomma_plugin.gaussians import SH_C0  # noqa: E402
from icomma_plugin.render import PreparedScene, prepare_scene  # noqa: E402


def _render_with_pose_grad(model, K, bg, backend, **kw):
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    w2c = se3_exp(xi) @ se3_exp(torch.tensor([0.05, -0.03, 0.02, 0.04, 0.03, -0.02],
                                             dtype=torch.float64)) @ _w2c()
    out = render(model, K, w2c, bg, backend=backend, **kw)
    (out.color.square().sum() + out.depth.sum() + out.alpha.sum()).backward()
    return out, xi.grad


@pytest.mark.parametrize("model_degree,degree", [(0, None), (2, 0), (2, 1), (2, None)])
def test_prepared_scene_renders_bit_identical(backend, backend_dtype, model_degree, degree):
    # Every output and the pose gradient are the same bits as render(model): at degree 0 the
    # colours are precomputed (view independent), above it the SH go to the rasterizer.
    dtype = backend_dtype
    m = _blobs(P=60, dtype=dtype, seed=3, degree=model_degree)
    m.sh_dc[:5] = -3.0  # raw colour below 0: the rasterizer's clamp must be reproduced
    assert bool((SH_C0 * m.sh_dc + 0.5 < 0).any())
    K = Intrinsics(32, 24, 30.0, 30.0, cx=15.0, cy=12.5)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=dtype)
    scene = prepare_scene(m, degree)
    assert isinstance(scene, PreparedScene)
    assert (scene.colors is not None) == (scene.sh_degree == 0)
    plain, g_plain = _render_with_pose_grad(m, K, bg, backend, sh_degree=degree)
    fast, g_fast = _render_with_pose_grad(scene, K, bg, backend)
    assert float(plain.alpha.detach().max()) > 0.5  # the scene is in view
    for name in plain._fields:
        assert torch.equal(getattr(plain, name), getattr(fast, name)), name
    assert torch.equal(g_plain, g_fast)
    assert float(g_plain.abs().sum()) > 0


def test_prepared_scene_is_frozen_and_checked_once():
    m = _blobs(degree=1)
    for t in m.tensors().values():
        t.requires_grad_(True)
    scene = prepare_scene(m)
    for t in (scene.means, scene.opacities, scene.scales, scene.rotations, scene.shs):
        assert not t.requires_grad and t.is_contiguous()
    assert torch.equal(scene.scales, m.scales().detach())
    assert (scene.num_gaussians, scene.dtype, scene.sh_degree) == (12, torch.float64, 1)
    assert scene.shs.shape == (12, 4, 3)
    assert prepare_scene(m, 0).shs is None and prepare_scene(m, 0).colors.shape == (12, 3)


def test_prepared_scene_errors():
    m = _blobs(degree=1)
    K = Intrinsics(16, 12, 15.0, 15.0)
    bg = torch.zeros(3, dtype=torch.float64)
    with pytest.raises(ValueError, match="model must be a GaussianModel, got str"):
        prepare_scene("scene")
    with pytest.raises(ValueError, match="model must be a GaussianModel, got PreparedScene"):
        prepare_scene(prepare_scene(m))
    with pytest.raises(ValueError, match="must be a GaussianModel or a PreparedScene, got str"):
        render("scene", K, _w2c(), bg)
    with pytest.raises(ValueError, match=r"sh_degree must be an int in \[0, 1\]"):
        prepare_scene(m, 2)
    with pytest.raises(ValueError, match=r"sh_degree must be None or 0 \(the degree the scene was"):
        render(prepare_scene(m, 0), K, _w2c(), bg, sh_degree=1)
    bad = _blobs(degree=1)
    bad.scale_log[4, 1] = 1000.0  # exp overflows to inf: caught on the activated value
    with pytest.raises(ValueError, match=r"model.scale_log \(after exp\) must be finite, got 1 "
                                         r"NaN/Inf entry$"):
        prepare_scene(bad)
    bad = _blobs(degree=1)
    bad.sh_rest[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="model.sh_dc / model.sh_rest must be finite"):
        prepare_scene(bad)
    bad.sh_rest[0, 0, 0] = 0.0
    bad.means[2, 0] = float("inf")
    with pytest.raises(ValueError, match="model.means must be finite"):
        prepare_scene(bad)
