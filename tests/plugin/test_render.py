import pytest
import torch

pytest.importorskip("gaussian_renderer_pose")

from icomma_plugin.camera import Intrinsics  # noqa: E402
from icomma_plugin.gaussians import GaussianModel  # noqa: E402
from icomma_plugin.pose.se3 import se3_exp  # noqa: E402
from icomma_plugin.render import render  # noqa: E402

BACKEND = "reference"


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
    out = render(m, K, _w2c(d), torch.zeros(3, dtype=d), backend=BACKEND)
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
    target = render(m, K, _w2c(), bg, backend=BACKEND).color.detach()
    base = se3_exp(torch.tensor([0.03, -0.02, 0.05, 0.02, -0.03, 0.01], dtype=torch.float64))

    def loss_of(xi):
        out = render(m, K, se3_exp(xi) @ base @ _w2c(), bg, backend=BACKEND)
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
    out = render(m, K, w2c, torch.zeros(3), backend=BACKEND)
    assert out.color.dtype == torch.float32
    out.color.sum().backward()
    assert w2c.grad is not None and torch.isfinite(w2c.grad).all()


def test_sh_degree_and_errors():
    m = _blobs(degree=1)
    K = Intrinsics(16, 12, 15.0, 15.0)
    bg = torch.zeros(3, dtype=torch.float64)
    c1 = render(m, K, _w2c(), bg, backend=BACKEND).color
    c0 = render(m, K, _w2c(), bg, backend=BACKEND, sh_degree=0).color
    assert not torch.allclose(c0, c1)
    with pytest.raises(ValueError, match="sh_degree"):
        render(m, K, _w2c(), bg, sh_degree=2)
    with pytest.raises(ValueError, match="w2c"):
        render(m, K, torch.eye(3), bg)
    with pytest.raises(ValueError, match="bg"):
        render(m, K, _w2c(), torch.zeros(4))
    with pytest.raises(ValueError, match="intrinsics"):
        render(m, None, _w2c(), bg)
