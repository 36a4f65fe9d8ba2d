import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.losses import compare_loss, match_loss, reprojection_match_loss
from icomma_plugin.pose.se3 import se3_exp

# ----------------------------------------------------------------------------- compare_loss


def test_compare_loss_hand_computed():
    render = torch.zeros(3, 2, 2, requires_grad=True)
    query = torch.zeros(3, 2, 2)
    query[0, 1, 1] = 1.0
    assert compare_loss(render, query).item() == pytest.approx(1 / 12)
    assert torch.allclose(compare_loss(render, query), torch.nn.functional.mse_loss(render, query))
    mask = torch.zeros(1, 2, 2)
    mask[0, 1, 1] = 1.0
    assert compare_loss(render, query, mask).item() == pytest.approx(1 / 3)
    mask[0, 0, 0] = 1.0  # a second, error-free pixel halves it
    assert compare_loss(render, query, mask).item() == pytest.approx(1 / 6)
    soft = torch.full((1, 2, 2), 0.5)
    assert compare_loss(render, query, soft).item() == pytest.approx(1 / 12)
    loss = compare_loss(render, query, mask)
    loss.backward()
    assert render.grad[0, 1, 1].item() == pytest.approx(2 * (0 - 1) / 6)
    assert render.grad[0, 0, 1].item() == 0.0  # outside the mask


def test_compare_loss_empty_mask_is_zero():
    out = compare_loss(torch.rand(3, 4, 5), torch.rand(3, 4, 5), torch.zeros(1, 4, 5))
    assert out.item() == 0.0


def test_compare_loss_shape_errors():
    with pytest.raises(ValueError, match="query"):
        compare_loss(torch.zeros(3, 4, 5), torch.zeros(3, 5, 4))
    with pytest.raises(ValueError, match="mask"):
        compare_loss(torch.zeros(3, 4, 5), torch.zeros(3, 4, 5), torch.zeros(4, 5))
    with pytest.raises(ValueError, match="render"):
        compare_loss(torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 4, 5))


# ----------------------------------------------------------------------------- match_loss


def test_match_loss_hand_computed_same_size():
    kr = torch.tensor([[10.0, 20.0], [100.0, 100.0]], requires_grad=True)
    kq = torch.tensor([[74.0, 68.0], [100.0, 100.0]])
    # Match 0: (64/640)^2 + (48/480)^2 = 0.02; match 1: 0 -> mean 0.01 (iComMa's value).
    loss = match_loss(kr, kq, (640, 480), (640, 480))
    assert loss.item() == pytest.approx(0.01)
    loss.backward()
    assert kr.grad[0, 0].item() == pytest.approx(2 * (-64 / 640) / 640 / 2)
    assert kr.grad[1].abs().sum().item() == 0.0


def test_match_loss_different_sizes():
    # The centre / the top-left pixel of a half-size render match those of the query exactly.
    kr = torch.tensor([[159.5, 119.5], [0.0, 0.0]])
    kq = torch.tensor([[319.5, 239.5], [0.5, 0.5]])
    assert match_loss(kr, kq, (320, 240), (640, 480)).item() == pytest.approx(0.0, abs=1e-12)
    # A 10% width offset in each image's own units.
    kr = torch.tensor([[32.0 + 159.5, 119.5]])
    kq = torch.tensor([[319.5, 239.5]])
    assert match_loss(kr, kq, (320, 240), (640, 480)).item() == pytest.approx(0.01)


def test_match_loss_errors():
    with pytest.raises(ValueError, match="same N"):
        match_loss(torch.zeros(3, 2), torch.zeros(2, 2), (4, 4), (4, 4))
    with pytest.raises(ValueError, match="N = 0"):
        match_loss(torch.zeros(0, 2), torch.zeros(0, 2), (4, 4), (4, 4))
    with pytest.raises(ValueError, match="size_query"):
        match_loss(torch.zeros(1, 2), torch.zeros(1, 2), (4, 4), (0, 4))
    with pytest.raises(ValueError, match="kpts_render"):
        match_loss(torch.zeros(3, 3), torch.zeros(3, 2), (4, 4), (4, 4))


# ----------------------------------------------------------------------------- reprojection


def _scene(dtype=torch.float64):
    g = torch.Generator().manual_seed(0)
    K = Intrinsics(64, 48, 50.0, 52.0, cx=30.0, cy=25.0)
    pts = torch.rand(30, 3, generator=g, dtype=dtype) * 2 - 1  # around the origin
    w2c = torch.eye(4, dtype=dtype)
    w2c[2, 3] = 5.0
    x = pts @ w2c[:3, :3].T + w2c[:3, 3]
    kq = torch.stack([K.fx * x[:, 0] / x[:, 2] + K.cx_px, K.fy * x[:, 1] / x[:, 2] + K.cy_px], 1)
    return K, pts, w2c, kq


def test_reprojection_zero_at_truth():
    K, pts, w2c, kq = _scene()
    loss = reprojection_match_loss(pts, kq, w2c, K)
    assert loss.ndim == 0 and loss.item() < 1e-25


def test_reprojection_hand_computed():
    K = Intrinsics(100, 50, 10.0, 10.0)  # centre (49.5, 24.5)
    pts = torch.tensor([[1.0, 0.0, 2.0]])
    kq = torch.tensor([[49.5, 24.5]])
    # Projects to (49.5 + 5, 24.5): ((5/100)^2 + 0) = 0.0025.
    loss = reprojection_match_loss(pts, kq, torch.eye(4), K)
    assert loss.item() == pytest.approx(0.0025)


def test_reprojection_gradient_direction():
    K, pts, w2c_gt, kq = _scene()
    for k in range(6):
        xi0 = torch.zeros(6, dtype=torch.float64)
        xi0[k] = 0.02
        xi = xi0.clone().requires_grad_()
        loss = reprojection_match_loss(pts, kq, se3_exp(xi) @ w2c_gt, K)
        (g,) = torch.autograd.grad(loss, xi)
        # The gradient points back towards the true pose along the perturbed coordinate
        # (except depth, which is weakly observed), and a small descent step lowers the loss.
        if k != 2:
            assert g[k] > 0
        assert torch.dot(g, xi0) > 0
        xi1 = xi.detach() - 1e-5 * g / g.norm()
        step = reprojection_match_loss(pts, kq, se3_exp(xi1) @ w2c_gt, K)
        assert step < loss


def test_reprojection_excludes_points_behind_and_none():
    K, pts, w2c, kq = _scene()
    behind = torch.cat([pts, torch.tensor([[0.0, 0.0, -6.0]], dtype=torch.float64)])
    kq2 = torch.cat([kq, torch.tensor([[0.0, 0.0]], dtype=torch.float64)])
    assert reprojection_match_loss(behind, kq2, w2c, K).item() < 1e-25
    flipped = w2c.clone()
    flipped[2, 3] = -5.0
    assert reprojection_match_loss(pts, kq, flipped, K) is None


def test_reprojection_dtype_follows_w2c_and_errors():
    K, pts, w2c, kq = _scene(torch.float32)
    out = reprojection_match_loss(pts.double(), kq, w2c, K)
    assert out.dtype == torch.float32
    with pytest.raises(ValueError, match="w2c"):
        reprojection_match_loss(pts, kq, torch.eye(3), K)
    with pytest.raises(ValueError, match="intrinsics_query"):
        reprojection_match_loss(pts, kq, w2c, None)
    with pytest.raises(ValueError, match="same N"):
        reprojection_match_loss(pts[:3], kq, w2c, K)
