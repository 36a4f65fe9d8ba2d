import math

import pytest
import torch
from torch.autograd import gradcheck

from icomma_plugin.pose.se3 import (
    hat,
    se3_exp,
    se3_log,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    vee,
)

ANGLES = [0.0, 1e-9, 1e-6, 1e-4, 0.0315, 0.0320, 0.3, 1.0, 2.0, 3.0, math.pi - 1e-3, math.pi - 1e-6]


def _dirs(n, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=dtype)
    return d / d.norm(dim=-1, keepdim=True)


def _ortho_err(R):
    eye = torch.eye(3, dtype=R.dtype)
    return (R @ R.transpose(-1, -2) - eye).abs().max().item()


def test_hat_vee():
    v = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    w = torch.tensor([0.5, 4.0, -1.0], dtype=torch.float64)
    K = hat(v)
    assert torch.allclose(K @ w, torch.linalg.cross(v, w))
    assert torch.allclose(K, -K.T)
    assert torch.equal(vee(K), v)
    batch = torch.randn(4, 5, 3)
    assert hat(batch).shape == (4, 5, 3, 3)
    assert torch.allclose(vee(hat(batch)), batch)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-6), (torch.float64, 1e-13)])
@pytest.mark.parametrize("angle", ANGLES)
def test_exp_log_round_trip(dtype, tol, angle):
    phi = _dirs(64, dtype) * angle
    rho = torch.randn(64, 3, dtype=dtype)
    xi = torch.cat([rho, phi], -1)
    T = se3_exp(xi)
    assert T.shape == (64, 4, 4) and T.dtype == dtype
    assert _ortho_err(T[:, :3, :3]) < tol
    assert torch.equal(T[:, 3], torch.tensor([0, 0, 0, 1], dtype=dtype).expand(64, 4))
    assert (se3_log(T) - xi).abs().max().item() < tol * 4
    assert (so3_log(so3_exp(phi)) - phi).abs().max().item() < tol * 4


def test_exact_at_zero():
    for dtype in (torch.float32, torch.float64):
        T = se3_exp(torch.zeros(6, dtype=dtype))
        assert torch.equal(T, torch.eye(4, dtype=dtype))
        assert torch.equal(so3_log(torch.eye(3, dtype=dtype)), torch.zeros(3, dtype=dtype))
        assert torch.equal(se3_log(torch.eye(4, dtype=dtype)), torch.zeros(6, dtype=dtype))


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 0.03, 0.5, 3.0])
def test_numpy_twist_is_the_torch_twist(angle):
    """A numpy twist (the host-side solvers') gives the float64 torch exponential's matrix."""
    import numpy as np

    rng = np.random.default_rng(7)
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3), angle * axis / np.linalg.norm(axis)])
    T = se3_exp(xi)
    assert isinstance(T, np.ndarray) and T.dtype == np.float64 and T.shape == (4, 4)
    np.testing.assert_allclose(T, se3_exp(torch.as_tensor(xi)).numpy(), rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="xi"):
        se3_exp(np.zeros(5))


def test_known_values():
    # 90 degrees about z maps x to y; translation along rho with phi = 0 is a pure shift.
    R = so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert torch.allclose(R @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-15)
    T = se3_exp(torch.tensor([1.0, 2.0, 3.0, 0, 0, 0], dtype=torch.float64))
    assert torch.equal(T[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    # t = V rho with V the left Jacobian.
    xi = torch.tensor([0.3, -0.2, 0.5, 0.4, 1.1, -0.7], dtype=torch.float64)
    T = se3_exp(xi)
    assert torch.allclose(T[:3, 3], so3_left_jacobian(xi[3:]) @ xi[:3])
    assert torch.allclose(so3_left_jacobian_inv(xi[3:]) @ so3_left_jacobian(xi[3:]),
                          torch.eye(3, dtype=torch.float64))


def test_log_exactly_pi():
    for axis in ([1.0, 0, 0], [0, 1.0, 0], [1.0, 1.0, 1.0], [0.3, -0.5, 0.8]):
        a = torch.tensor(axis, dtype=torch.float64)
        phi = a / a.norm() * math.pi
        R = so3_exp(phi)
        out = so3_log(R)
        assert abs(out.norm().item() - math.pi) < 1e-12
        # phi or -phi: both are logarithms of R.
        assert torch.allclose(so3_exp(out), R, atol=1e-12)
    R = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)).requires_grad_()
    (g,) = torch.autograd.grad(so3_log(R).sum(), R)
    assert torch.isfinite(g).all()


def test_batched_shapes():
    xi = 0.5 * torch.randn(2, 3, 6, generator=torch.Generator().manual_seed(0),
                           dtype=torch.float64)  # rotations well below pi: log inverts exp
    T = se3_exp(xi)
    assert T.shape == (2, 3, 4, 4)
    assert torch.allclose(se3_log(T), xi, atol=1e-10)


@pytest.mark.parametrize("angle", [0.0, 1e-4, 0.03, 0.7, 2.5, math.pi - 1e-3])
def test_gradcheck_exp(angle):
    g = torch.Generator().manual_seed(1)
    phi = _dirs(1, torch.float64, seed=3)[0] * angle
    xi = torch.cat([torch.randn(3, generator=g, dtype=torch.float64), phi]).requires_grad_()
    assert gradcheck(se3_exp, (xi,), eps=1e-6, atol=1e-7)
    assert gradcheck(so3_exp, (phi.clone().requires_grad_(),), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("angle", [0.0, 1e-4, 0.03, 0.7, 2.5, math.pi - 1e-3])
def test_log_exp_jacobian_is_identity(angle):
    phi = _dirs(1, torch.float64, seed=4)[0] * angle
    xi = torch.cat([torch.tensor([0.2, -0.4, 0.1], dtype=torch.float64), phi])
    J = torch.autograd.functional.jacobian(lambda x: se3_log(se3_exp(x)), xi)
    assert torch.allclose(J, torch.eye(6, dtype=torch.float64), atol=1e-8)


def test_finite_gradients_float32_at_zero():
    xi = torch.zeros(5, 6, requires_grad=True)
    (g,) = torch.autograd.grad((se3_exp(xi) * torch.randn(5, 4, 4)).sum(), xi)
    assert torch.isfinite(g).all()
    T = torch.eye(4).expand(3, 4, 4).clone().requires_grad_()
    (g,) = torch.autograd.grad(se3_log(T).sum(), T)
    assert torch.isfinite(g).all()


def test_derivative_at_zero_is_generator():
    # d/d(xi) se3_exp at 0 = the se(3) generators: d exp / d phi_k = hat(e_k), d / d rho_k = e_k.
    xi = torch.zeros(6, dtype=torch.float64)
    J = torch.autograd.functional.jacobian(se3_exp, xi)  # [4, 4, 6]
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = 1.0
        assert torch.allclose(J[:3, :3, 3 + k], hat(e))
        assert torch.allclose(J[:3, 3, k], e)


def test_shape_errors():
    with pytest.raises(ValueError, match="xi"):
        se3_exp(torch.zeros(5))
    with pytest.raises(ValueError, match="R"):
        so3_log(torch.zeros(3, 4))
    with pytest.raises(ValueError, match="phi"):
        so3_exp(torch.zeros(3, dtype=torch.int64))
