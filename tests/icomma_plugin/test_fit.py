"""Tests of icomma_plugin.fit: densification unit tests, a tiny end-to-end fit, model folder I/O."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.fit import (
    FitConfig,
    FitView,
    GaussianTrainState,
    Trainer,
    expon_lr,
    mean_knn_sq_dist,
    model_from_points,
    photometric_loss,
    psnr,
    random_cube_points,
    render_state,
    resolution_scale,
    ssim,
)
from icomma_plugin.fit.state import PARAM_NAMES
from icomma_plugin.gaussians import GaussianModel, rgb_to_sh
from tests.helpers.geometry import look_at_c2w

# The backend is the library's default ("auto": the native CPU kernel when built, else the
# reference). Tiny images: one intra-op thread is fastest (far faster on a busy, shared machine).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---------------------------------------------------------------------------------------- helpers
def _tiny_model(P=4, scale=0.01, opacity=0.5, sh_degree=1) -> GaussianModel:
    g = torch.Generator().manual_seed(1)
    K = (sh_degree + 1) ** 2 - 1
    logit = math.log(opacity / (1 - opacity))
    quat = torch.randn(P, 4, generator=g)
    return GaussianModel(
        means=torch.randn(P, 3, generator=g),
        sh_dc=torch.randn(P, 1, 3, generator=g),
        sh_rest=torch.randn(P, K, 3, generator=g) * 0.1,
        opacity_logit=torch.full((P, 1), logit),
        scale_log=torch.full((P, 3), math.log(scale)),
        quat=quat,
        sh_degree=sh_degree,
    )


def _state_with_moments(model, extent=1.0) -> GaussianTrainState:
    """A train state after one Adam step (so every parameter has non-zero Adam moments)."""
    st = GaussianTrainState(model, extent)
    loss = sum(st.get(n).sum() for n in PARAM_NAMES)
    loss.backward()
    st.step()
    st.zero_grad()
    return st


def _check_consistent(st: GaussianTrainState):
    P = st.num_gaussians
    for n in PARAM_NAMES:
        p = st.get(n)
        assert p.shape[0] == P
        assert st.optimizer.param_groups[PARAM_NAMES.index(n)]["params"][0] is p
        s = st.optimizer.state.get(p)
        if s:
            assert s["exp_avg"].shape == p.shape and s["exp_avg_sq"].shape == p.shape
    assert st.grad_accum.shape == (P,) and st.denom.shape == (P,) and st.max_radii2D.shape == (P,)


def _look_at_w2c(campos, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera of a camera at `campos` looking at `target` (OpenCV axes)."""
    return np.linalg.inv(look_at_c2w(campos, target, up))


def _ring_poses(n, radius=3.0, height=1.0):
    return [
        _look_at_w2c(
            (
                radius * math.cos(2 * math.pi * k / n),
                radius * math.sin(2 * math.pi * k / n),
                height * (1 if k % 2 else -0.5),
            )
        )
        for k in range(n)
    ]


def _gt_model() -> GaussianModel:
    """A small known scene: 40 coloured Gaussians in a ball of radius 0.6."""
    g = torch.Generator().manual_seed(7)
    P = 40
    d = torch.randn(P, 3, generator=g)
    means = d / d.norm(dim=1, keepdim=True) * torch.rand(P, 1, generator=g) * 0.6
    rgb = torch.rand(P, 3, generator=g)
    return GaussianModel(
        means=means,
        sh_dc=rgb_to_sh(rgb).view(P, 1, 3),
        sh_rest=torch.zeros(P, 3, 3),
        opacity_logit=torch.full((P, 1), 2.0),
        scale_log=torch.log(torch.rand(P, 3, generator=g) * 0.12 + 0.04),
        quat=torch.randn(P, 4, generator=g),
        sh_degree=1,
    )


def _render_views(model, poses, size=32, bg=(0.0, 0.0, 0.0)):
    from icomma_plugin.fit.state import GaussianTrainState as _S

    st = _S(model, 1.0)
    st.active_sh_degree = model.sh_degree
    intr = Intrinsics(size, size, size * 1.1, size * 1.1)
    views = []
    with torch.no_grad():
        for k, w2c in enumerate(poses):
            v = FitView(
                f"v{k}", torch.zeros(3, size, size), intr, torch.as_tensor(w2c, dtype=torch.float32)
            )
            out = render_state(st, v, torch.tensor(bg))
            views.append((v.name, out.color.clamp(0, 1), out.alpha.clamp(0, 1), intr, w2c))
    return views


def _fit_views(rendered):
    return [
        FitView(n, img, intr, torch.as_tensor(w2c, dtype=torch.float32))
        for n, img, _, intr, w2c in rendered
    ]


# ------------------------------------------------------------------------------ small functions
def test_ssim_identical_and_loss():
    a = torch.rand(3, 20, 24)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-5)
    assert photometric_loss(a, a).item() == pytest.approx(0.0, abs=1e-5)
    b = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    assert 0.0 < ssim(a, b).item() < 0.95
    assert psnr(a, a) == float("inf")
    assert psnr(torch.zeros(3, 4, 4), torch.full((3, 4, 4), 0.1)) == pytest.approx(20.0, abs=1e-4)


def _upstream_ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Upstream 3DGS's `ssim`: the 11x11 window as one 2D convolution a channel, zero padding 5."""
    x = torch.arange(11, dtype=a.dtype) - 5
    g = torch.exp(-(x ** 2) / (2 * 1.5 ** 2))
    g = g / g.sum()
    win = (g[:, None] * g[None, :]).expand(3, 1, 11, 11)

    def f(t):
        return torch.nn.functional.conv2d(t[None], win, padding=5, groups=3)[0]

    mu1, mu2 = f(a), f(b)
    s11, s22, s12 = f(a * a) - mu1 ** 2, f(b * b) - mu2 ** 2, f(a * b) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mu1 * mu2 + c1) * (2 * s12 + c2))
            / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))).mean()


def test_ssim_matches_upstream_window():
    g = torch.Generator().manual_seed(5)
    a = torch.rand(3, 17, 23, generator=g, dtype=torch.float64)
    b = (a + 0.3 * torch.rand(3, 17, 23, generator=g, dtype=torch.float64)).clamp(0, 1)
    want = _upstream_ssim(a, b).item()
    assert ssim(a, b).item() == pytest.approx(want, rel=1e-12)
    from icomma_plugin.fit.losses import ssim_value_and_grad

    assert ssim_value_and_grad(a, b)[0].item() == pytest.approx(want, rel=1e-12)


def test_expon_lr_endpoints():
    assert expon_lr(0, 1e-2, 1e-4, 100) == pytest.approx(1e-2)
    assert expon_lr(100, 1e-2, 1e-4, 100) == pytest.approx(1e-4)
    assert expon_lr(50, 1e-2, 1e-4, 100) == pytest.approx(1e-3)
    assert expon_lr(500, 1e-2, 1e-4, 100) == pytest.approx(1e-4)


def test_knn_scales_and_init():
    grid = np.stack(np.meshgrid(*[np.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    d2 = mean_knn_sq_dist(grid)
    assert np.allclose(d2[62], 1.0)  # an inner point: 3 nearest at distance 1
    m = model_from_points(grid, np.full_like(grid, 0.5), sh_degree=3, init_opacity=0.1)
    assert m.num_gaussians == 125 and m.sh_rest.shape == (125, 15, 3)
    assert torch.allclose(m.scale_log[62], torch.zeros(3), atol=1e-6)
    assert torch.allclose(m.opacities(), torch.full((125, 1), 0.1))
    assert torch.allclose(m.rotations(), torch.tensor([1.0, 0, 0, 0]).expand(125, 4))
    assert torch.allclose(m.sh_dc, torch.zeros(125, 1, 3), atol=1e-6)  # grey 0.5
    xyz, rgb = random_cube_points(1000, 1.3, seed=3)
    assert xyz.shape == (1000, 3) and np.abs(xyz).max() <= 1.3 and 0 <= rgb.min() and rgb.max() <= 1
    with pytest.raises(ValueError, match="xyz"):
        model_from_points(np.zeros((0, 3)), np.zeros((0, 3)))


# --------------------------------------------------------------------------- densification units
def test_densification_stats_only_visible():
    st = GaussianTrainState(_tiny_model(3), 1.0)
    # the unseen Gaussian's NaN must not reach its statistics
    g = torch.tensor([[3.0, 4.0, 100.0], [float("nan"), 0.0, 0.0], [0.0, 2.0, 0.0]])
    st.add_densification_stats(g, torch.tensor([2, 0, 5], dtype=torch.int32))
    st.add_densification_stats(g, torch.tensor([4, 0, 1], dtype=torch.int32))
    assert torch.allclose(st.grad_accum, torch.tensor([10.0, 0.0, 4.0]))  # norm of [:, :2] only
    assert torch.allclose(st.denom, torch.tensor([2.0, 0.0, 2.0]))
    assert torch.allclose(st.max_radii2D, torch.tensor([4.0, 0.0, 5.0]))
    assert torch.allclose(st.mean_grads(), torch.tensor([5.0, 0.0, 2.0]))  # 0/0 -> 0


def test_clone_small_gaussians():
    model = _tiny_model(4, scale=0.001)
    # percent_dense * extent = 0.01 > 0.001: all "small"
    st = _state_with_moments(model, extent=1.0)
    before = {n: st.get(n).detach().clone() for n in PARAM_NAMES}
    grads = torch.tensor([1e-3, 0.0, 5e-4, 1e-5])
    n = st.densify_and_clone(grads, 2e-4, 1.0)
    assert n == 2 and st.num_gaussians == 6
    _check_consistent(st)
    for name in PARAM_NAMES:
        p = st.get(name).detach()
        assert torch.equal(p[:4], before[name])
        assert torch.equal(p[4:], before[name][[0, 2]])  # identical copies
        s = st.optimizer.state[st.get(name)]
        assert (
            torch.count_nonzero(s["exp_avg"][4:]) == 0 and torch.count_nonzero(s["exp_avg"][:4]) > 0
        )
    # large Gaussians are not cloned
    st2 = _state_with_moments(_tiny_model(4, scale=0.5), extent=1.0)
    assert st2.densify_and_clone(grads, 2e-4, 1.0) == 0 and st2.num_gaussians == 4


def test_split_large_gaussians():
    model = _tiny_model(3, scale=0.5)
    st = _state_with_moments(model, extent=1.0)
    means0 = st.get("means").detach().clone()
    scales0 = st.scales().detach().clone()
    dc0 = st.get("sh_dc").detach().clone()
    grads = torch.tensor([1e-3, 1e-5, 1e-3])
    n = st.densify_and_split(grads, 2e-4, 1.0, N=2)
    assert n == 2 and st.num_gaussians == 3 - 2 + 4
    _check_consistent(st)
    assert torch.equal(st.get("means").detach()[0], means0[1])  # survivor first
    new_means = st.get("means").detach()[1:]
    # each new Gaussian is within a few (rotated) std of its parent, scale / (0.8 * N)
    parents = means0[[0, 2, 0, 2]]
    assert ((new_means - parents).norm(dim=1) < 4 * 0.5 * math.sqrt(3)).all()
    assert torch.allclose(st.scales().detach()[1:], scales0[[0, 2, 0, 2]] / 1.6, atol=1e-6)
    assert torch.allclose(st.get("sh_dc").detach()[1:], dc0[[0, 2, 0, 2]])
    new_state = st.optimizer.state[st.get("means")]
    assert torch.count_nonzero(new_state["exp_avg"][1:]) == 0
    # the optimizer still steps with the new tensors
    (st.get("means") ** 2).sum().backward()
    st.step()


def test_prune_and_full_densify_and_prune():
    model = _tiny_model(5, scale=0.05)
    model.opacity_logit[1] = -8.0  # opacity ~ 3e-4 < 0.005
    st = _state_with_moments(model, extent=1.0)
    keep_means = st.get("means").detach()[[0, 2, 3, 4]].clone()
    st.prune(torch.tensor([False, True, False, False, False]))
    assert st.num_gaussians == 4 and torch.equal(st.get("means").detach(), keep_means)
    _check_consistent(st)

    model = _tiny_model(5, scale=0.05)
    model.opacity_logit[1] = -8.0
    model.scale_log[3] = math.log(0.5)  # > 0.1 * extent: pruned when the size test is on
    st = _state_with_moments(model, extent=1.0)
    st.max_radii2D[4] = 50.0  # > max_screen_size
    d = st.densify_and_prune(2e-4, 0.005, 1.0, max_screen_size=20)
    assert d == {"cloned": 0, "split": 0, "pruned": 3, "total": 2}
    _check_consistent(st)
    assert torch.count_nonzero(st.grad_accum) == 0  # statistics reset


def test_densify_budget_caps_growth():
    st = _state_with_moments(_tiny_model(6, scale=0.001), extent=1.0)
    st.grad_accum = torch.tensor([1.0, 5.0, 3.0, 4.0, 2.0, 0.0]) * 1e-3
    st.denom = torch.ones(6)
    d = st.densify_and_prune(2e-4, 0.0, 1.0, None, max_gaussians=8)
    assert d["cloned"] == 2 and st.num_gaussians == 8
    # the two largest gradients (indices 1 and 3) were cloned
    assert torch.equal(st.get("means").detach()[6:], st.get("means").detach()[[1, 3]])


def test_reset_opacity():
    model = _tiny_model(3)
    model.opacity_logit[:, 0] = torch.tensor([3.0, -6.0, 0.0])
    st = _state_with_moments(model)
    op0 = st.opacities().detach().squeeze(1).clone()
    st.reset_opacity()
    op = st.opacities().detach().squeeze(1)
    assert torch.allclose(
        op, torch.stack([torch.tensor(0.01), op0[1], torch.tensor(0.01)]), atol=1e-6
    )
    assert op0[1] < 0.01
    s = st.optimizer.state[st.get("opacity_logit")]
    assert torch.count_nonzero(s["exp_avg"]) == 0 and torch.count_nonzero(s["exp_avg_sq"]) == 0
    _check_consistent(st)


# ------------------------------------------------------------------------------- end-to-end fit
def test_tiny_end_to_end_fit():
    gt = _gt_model()
    rendered = _render_views(gt, _ring_poses(8), size=32)
    views = _fit_views(rendered)
    train, test = views[:7], views[7:]
    xyz, rgb = random_cube_points(300, 0.8, seed=0)
    init = model_from_points(xyz, rgb, sh_degree=1)
    cfg = FitConfig.scaled_schedule(
        300, sh_degree=1, num_random_points=300, densify_grad_threshold=1e-4, max_gaussians=2000
    )
    trainer = Trainer(init, train, scene_extent=3.3, config=cfg, background=(0, 0, 0), test=test)
    p0 = trainer.evaluate(train)
    seen = []
    trainer.progress = lambda it, n, info: seen.append((it, info))
    res = trainer.run()
    p1 = trainer.evaluate(train)
    assert res.iterations == 300 and len(seen) == 30 and seen[-1][0] == 300
    assert {"loss", "psnr", "num_gaussians"} <= set(seen[-1][1])
    assert p1 > p0 + 8.0, (p0, p1)
    assert p1 > 24.0, p1
    assert res.test_psnr is not None and res.test_psnr > 18.0
    assert res.num_gaussians != 300  # densification / pruning happened
    assert set(res.timings) >= {"render", "backward", "adam", "densify"}


def _scanning_trainer(monkeypatch, every: int = 5):
    """A tiny fit whose NaN scans run every ``every`` steps; (trainer, list of validate flags)."""
    from icomma_plugin.fit import trainer as trainer_mod

    monkeypatch.setattr(trainer_mod, "_SCAN_EVERY", every)
    rendered = _render_views(_gt_model(), _ring_poses(4), size=24)
    xyz, rgb = random_cube_points(100, 0.8, seed=0)
    cfg = FitConfig.scaled_schedule(40, sh_degree=1, num_random_points=100)
    trainer = Trainer(model_from_points(xyz, rgb, sh_degree=1), _fit_views(rendered), 3.3, cfg,
                      background=(0, 0, 0))
    scans = []
    real = trainer_mod.rasterize_gaussians

    def counting(*a, validate=True, **k):
        scans.append(validate)
        return real(*a, validate=validate, **k)

    monkeypatch.setattr(trainer_mod, "rasterize_gaussians", counting)
    return trainer, scans


def test_steps_scan_for_nan_now_and_then_and_a_bad_gaussian_is_removed(monkeypatch, caplog):
    """The NaN scans (a host sync per tensor) run every ``_SCAN_EVERY`` steps.

    A Gaussian whose parameter goes bad between them is removed at the next scan, with a warning
    naming the parameter, and the fit goes on (a long fit is not lost to one bad gradient).
    """
    import logging

    trainer, scans = _scanning_trainer(monkeypatch)
    for _ in range(7):
        trainer.train_step()
    assert scans == [True, False, False, False, False, True, False]
    before = trainer.state.num_gaussians
    with torch.no_grad():
        trainer.state.get("opacity_logit")[5] = float("nan")
        trainer.state.get("means")[7, 1] = float("inf")
    with caplog.at_level(logging.WARNING, logger="icomma_plugin.fit.trainer"):
        for _ in range(5):  # the scan at step 11
            trainer.train_step()
    assert trainer.removed_non_finite == 2
    assert any("opacity_logit 1" in r.getMessage() and "means 1" in r.getMessage()
               for r in caplog.records), [r.getMessage() for r in caplog.records]
    bad, _ = trainer.state.non_finite()
    assert not bool(bad.any()) and trainer.state.num_gaussians <= before - 2 + 100  # (densify)
    res = trainer.run()
    assert res.removed_non_finite == 2 and res.iterations == 40


def test_a_fit_whose_gaussians_go_bad_by_the_many_stops_and_says_so(monkeypatch):
    """More than ``MAX_NON_FINITE_SHARE`` of the Gaussians at once: a diverged fit (raises)."""
    trainer, _ = _scanning_trainer(monkeypatch)
    for _ in range(6):
        trainer.train_step()
    n = trainer.state.num_gaussians // 20  # 5 %
    with torch.no_grad():
        trainer.state.get("scale_log")[:n] = float("nan")
    with pytest.raises(FloatingPointError, match=f"scale_log {n}.*lower the learning rates"):
        for _ in range(5):
            trainer.train_step()
    assert trainer.iteration == 11


def test_random_background_draws_a_colour_each_step_and_recomposites_only_alpha_views():
    """Random background: a photo is its own target, a view with alpha is re-composited.

    A photo (no alpha) is the target over any background; a view with alpha is re-composited over
    the step's colour, a new one each step (the capture recipe turns this on for photos).
    """
    gt = _gt_model()
    rendered = _render_views(gt, _ring_poses(2), size=24)
    (n0, img0, _, intr0, w0), (n1, img1, alpha1, intr1, w1) = rendered
    views = [FitView(n0, img0, intr0, torch.as_tensor(w0, dtype=torch.float32)),
             FitView(n1, img1, intr1, torch.as_tensor(w1, dtype=torch.float32), alpha=alpha1)]
    xyz, rgb = random_cube_points(100, 0.8, seed=0)
    cfg = FitConfig.scaled_schedule(20, sh_degree=1, random_background=True)
    trainer = Trainer(model_from_points(xyz, rgb, sh_degree=1), views, scene_extent=3.3,
                      config=cfg, background=(0, 0, 0))
    seen = []
    real = trainer._loss_and_grad

    def spy(index, color, target, valid):
        seen.append((index, target.clone()))
        return real(index, color, target, valid)

    trainer._loss_and_grad = spy
    for _ in range(6):
        trainer.train_step()
    assert {i for i, _ in seen} == {0, 1}
    for i, target in seen:
        if i == 0:
            assert torch.equal(target, img0)  # a photo is not touched
    # a view with alpha: target - image = (bg - black) (1 - alpha), a new colour every step
    colours = [((t - img1) / (1 - alpha1).clamp_min(1e-3))[:, alpha1[0] < 0.01].mean(-1)
               for i, t in seen if i == 1]
    assert len(colours) >= 2
    assert all(((c >= -1e-4) & (c <= 1 + 1e-4)).all() for c in colours)
    assert any((a - b).abs().max() > 1e-3 for a, b in zip(colours, colours[1:]))


def test_a_fit_is_repeatable_from_its_seed_alone():
    """Same config.seed, different global RNG states: the same Gaussians (random backgrounds on)."""
    rendered = _render_views(_gt_model(), _ring_poses(3), size=24)
    views = [FitView(n, img, intr, torch.as_tensor(w, dtype=torch.float32), alpha=alpha)
             for n, img, alpha, intr, w in rendered]
    xyz, rgb = random_cube_points(100, 0.8, seed=0)

    def fit(global_seed: int, seed: int) -> torch.Tensor:
        torch.manual_seed(global_seed)
        cfg = FitConfig.scaled_schedule(12, sh_degree=1, random_background=True, seed=seed)
        trainer = Trainer(model_from_points(xyz, rgb, sh_degree=1), views, scene_extent=3.3,
                          config=cfg, background=(0, 0, 0))
        for _ in range(12):
            trainer.train_step()
        return trainer.state.params["sh_dc"].detach().clone()

    first = fit(1, seed=0)
    assert torch.equal(first, fit(2, seed=0))
    assert not torch.equal(first, fit(1, seed=5))  # the seed is what decides


# --------------------------------------------------------------------------- dataset -> folder
def _write_blender_dataset(root: Path, rendered_train, rendered_test):
    from PIL import Image

    root.mkdir(parents=True, exist_ok=True)
    for split, items in (("train", rendered_train), ("test", rendered_test)):
        (root / split).mkdir(exist_ok=True)
        frames = []
        for name, img, alpha, intr, w2c in items:
            rgba = torch.cat([img, alpha], 0).permute(1, 2, 0).numpy()
            # straight (un-premultiplied) colour so that compositing over black reproduces `img`
            a = np.clip(rgba[..., 3:], 1e-6, 1)
            rgba[..., :3] = np.clip(rgba[..., :3] / a, 0, 1) * (rgba[..., 3:] > 0)
            Image.fromarray((rgba * 255 + 0.5).astype(np.uint8), "RGBA").save(
                root / split / f"{name}.png"
            )
            c2w = np.linalg.inv(w2c)
            c2w[:3, 1:3] *= -1  # OpenCV -> Blender axes
            frames.append({"file_path": f"./{split}/{name}", "transform_matrix": c2w.tolist()})
        fov = 2 * math.atan(intr.width / (2 * intr.fx))
        (root / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": fov, "frames": frames})
        )


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    rendered = _render_views(_gt_model(), _ring_poses(8), size=32)
    root = tmp_path_factory.mktemp("tiny_blender")
    _write_blender_dataset(root, rendered[:6], rendered[6:])
    return root


def test_fit_scene_writes_loadable_model_folder(tiny_dataset, tmp_path):
    from icomma_plugin.fit import fit_scene
    from icomma_plugin.io.model_folder import load_model_folder
    from icomma_plugin.render import render

    out = tmp_path / "model"
    cfg = FitConfig.scaled_schedule(60, sh_degree=1, num_random_points=200, save_iterations=(30,))
    calls = []
    res = fit_scene(
        tiny_dataset, out, cfg, white_background=False, progress=lambda *a: calls.append(a)
    )
    assert res.model_path == out.resolve() and calls
    for f in (
        "cfg_args",
        "cameras.json",
        "input.ply",
        "metrics.json",
        "point_cloud/iteration_30/point_cloud.ply",
        "point_cloud/iteration_60/point_cloud.ply",
    ):
        assert (out / f).is_file(), f
    assert not any(p.name.startswith(".model") for p in tmp_path.iterdir())  # no staging left
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["iterations"] == 60 and metrics["resolution"] == [32, 32]
    assert metrics["num_gaussians"] == res.fit.num_gaussians and metrics["test_views"] == 2
    assert math.isfinite(metrics["test_psnr"]) and metrics["seconds_train"] > 0

    folder = load_model_folder(out)
    assert folder.iteration == 60
    assert folder.cfg["source_path"] == str(tiny_dataset.resolve())
    assert folder.cfg["eval"] is True and folder.cfg["sh_degree"] == 1
    assert folder.cfg["white_background"] is False
    assert folder.cfg["principal_point"] == "dataset" and folder.principal_point == "dataset"
    names = [c.img_name for c in folder.cameras]
    assert names == ["v6", "v7", "v0", "v1", "v2", "v3", "v4", "v5"]  # test first, then train
    m = folder.model
    assert m.num_gaussians == res.fit.num_gaussians
    cam = folder.cameras[0]
    intr = Intrinsics(cam.width, cam.height, cam.fx, cam.fy)
    w2c = torch.as_tensor(cam.w2c, dtype=torch.float32)
    bg = torch.zeros(3)
    a = render(m, intr, w2c, bg).color
    b = render(res.fit.model, intr, w2c, bg).color
    assert torch.allclose(a, b, atol=1e-5)

    # never overwrites unless asked
    with pytest.raises(ValueError, match="already exists"):
        fit_scene(tiny_dataset, out, cfg)
    cfg2 = FitConfig.scaled_schedule(5, sh_degree=1, num_random_points=50)
    fit_scene(tiny_dataset, out, cfg2, overwrite=True)
    assert load_model_folder(out).iteration == 5
    assert not (out / "point_cloud" / "iteration_60").exists()


def test_bad_inputs(tmp_path, tiny_dataset):
    from icomma_plugin.fit import fit_scene

    with pytest.raises(ValueError, match="source_path"):
        fit_scene(tmp_path / "nope", tmp_path / "m", FitConfig(iterations=1))
    with pytest.raises(ValueError, match="resolution"):
        fit_scene(tiny_dataset, tmp_path / "m", FitConfig(iterations=1), resolution=0)
    with pytest.raises(ValueError, match="downscale"):
        fit_scene(
            tiny_dataset, tmp_path / "m", FitConfig(iterations=1), resolution=-1, downscale=-2.0
        )
    assert not (tmp_path / "m").exists()
    with pytest.raises(ValueError, match="iterations"):
        FitConfig(iterations=0)
    with pytest.raises(ValueError, match="sh_degree"):
        FitConfig(sh_degree=4)
    with pytest.raises(ValueError, match="principal_point must be 'dataset' or 'centre'"):
        FitConfig(principal_point="center")
    assert resolution_scale(-1, None, 400) == 1.0
    assert resolution_scale(2, None, 400) == 0.5
    assert resolution_scale(200, None, 400) == 0.5
    assert resolution_scale(None, 2.0, 400) == 0.5
    assert resolution_scale(-1, None, 3200) == 0.5
    with pytest.raises(ValueError, match="either"):
        resolution_scale(2, 2.0, 400)


def test_lego_split_and_resolution_smoke(lego_root):
    """The shared lego scene loads at 200x200 for fitting (no fit: that is tools/fit_scene.py)."""
    from icomma_plugin.fit.views import views_to_fit
    from icomma_plugin.io.datasets import read_dataset

    scene = read_dataset(lego_root, white_background=True)
    views = views_to_fit(scene.train[:2], 2, None, (1.0, 1.0, 1.0))
    assert views[0].image.shape == (3, 200, 200)
    assert views[0].intrinsics.fx == pytest.approx(0.5 * 555.555, rel=1e-3)
    assert views[0].image.max() <= 1.0 and views[0].image[:, 0, 0].min() > 0.99  # white corner


# ------------------------------------------------------------------------------ validity masks
def _border_mask(H, W, b=3):
    m = torch.zeros(1, H, W, dtype=torch.float64)
    m[:, b:H - b, b + 1:W - b] = 1.0
    return m


def test_masked_loss_gradient_matches_autograd_and_finite_differences():
    from icomma_plugin.fit.losses import photometric_loss_and_grad

    g = torch.Generator().manual_seed(3)
    H, W = 13, 15
    render = torch.rand(3, H, W, generator=g, dtype=torch.float64)
    gt = torch.rand(3, H, W, generator=g, dtype=torch.float64)
    mask = _border_mask(H, W)
    loss, grad = photometric_loss_and_grad(render, gt, 0.2, mask)
    r = render.clone().requires_grad_(True)
    ref = photometric_loss(r, gt, 0.2, mask=mask)
    ref.backward()
    assert loss.item() == pytest.approx(ref.item(), rel=1e-12)
    torch.testing.assert_close(grad, r.grad, rtol=1e-9, atol=1e-12)
    assert torch.count_nonzero(grad * (1 - mask)) == 0  # invalid pixels get no gradient
    # central differences on a few valid pixels (away from L1's kink)
    for c, y, x in ((0, 6, 7), (2, 3, 4), (1, 9, 11)):
        e = torch.zeros_like(render)
        e[c, y, x] = 1e-6
        fd = (photometric_loss(render + e, gt, 0.2, mask=mask)
              - photometric_loss(render - e, gt, 0.2, mask=mask)) / 2e-6
        assert grad[c, y, x].item() == pytest.approx(fd.item(), rel=1e-5, abs=1e-9)
    # content outside the mask does not matter, and an all-ones mask is no mask
    junk = gt.clone()
    junk[:, :3] = torch.rand(3, 3, W, generator=g, dtype=torch.float64)
    assert photometric_loss_and_grad(render, junk, 0.2, mask)[0].item() == pytest.approx(
        loss.item()
    )
    ones = torch.ones(1, H, W, dtype=torch.float64)
    assert photometric_loss_and_grad(render, gt, 0.2, ones)[0].item() == pytest.approx(
        photometric_loss_and_grad(render, gt, 0.2)[0].item(), rel=1e-12)
    assert ssim(render, gt, mask=ones).item() == pytest.approx(ssim(render, gt).item(), rel=1e-12)
    with pytest.raises(ValueError, match="mask"):
        photometric_loss_and_grad(render, gt, 0.2, mask[:, :5])


def test_psnr_on_valid_pixels_only():
    H, W = 20, 30
    gt = torch.full((3, H, W), 0.5)
    render = gt.clone()
    mask = torch.zeros(1, H, W)
    mask[:, 2:18, 3:27] = 1.0
    render[:, 2:18, 3:27] += 0.1  # MSE 0.01 on the valid pixels: 20 dB
    render[:, :2] = 1.0            # garbage where invalid (black borders would be the same)
    assert psnr(render, gt, mask) == pytest.approx(20.0, abs=1e-4)
    assert psnr(render, gt) < 19.0
    with pytest.raises(ValueError, match="no valid pixel"):
        psnr(render, gt, torch.zeros(1, H, W))


def test_fit_ignores_invalid_pixels():
    """A junk invalid border changes nothing: the fit and its evaluation use the valid pixels.

    Training on images whose invalid border is junk moves the Gaussians exactly as training on
    clean images with the same mask; the evaluation counts the valid pixels only.
    """
    rendered = _render_views(_gt_model(), _ring_poses(4), size=32)
    mask = _border_mask(32, 32, b=5).float()

    def views(junk: bool, masked: bool):
        out = []
        for n, img, _, intr, w2c in rendered:
            im = img.clone()
            if junk:
                im[:, :5] = 0.0  # like an undistortion border
                im[:, :, -5:] = 1.0
            out.append(FitView(n, im, intr, torch.as_tensor(w2c, dtype=torch.float32),
                               valid=mask if masked else None))
        return out

    def fit(train):
        xyz, rgb = random_cube_points(200, 0.8, seed=0)
        cfg = FitConfig.scaled_schedule(30, sh_degree=1)
        t = Trainer(model_from_points(xyz, rgb, sh_degree=1), train, 3.3, cfg, test=train)
        t.run()
        return t, t.state.get("means").detach().clone()

    t_clean, m_clean = fit(views(junk=False, masked=True))
    t_junk, m_junk = fit(views(junk=True, masked=True))
    _, m_unmasked = fit(views(junk=True, masked=False))
    assert torch.equal(m_clean, m_junk)
    assert not torch.equal(m_clean, m_unmasked)
    assert t_junk.evaluate() == pytest.approx(t_clean.evaluate(), abs=1e-9)
    with pytest.raises(ValueError, match="valid"):
        FitView("v", torch.zeros(3, 8, 8), Intrinsics(8, 8, 9.0, 9.0), torch.eye(4),
                valid=torch.zeros(1, 8, 6))


# ------------------------------------------------------------------ initialisation from views
def _plane_views(n=6, size=(48, 40)):
    """Pinhole views (OpenCV axes) of the textured plane z = 0 from about 3 units above it.

    Rendered analytically (ray-plane intersection).
    """
    W, H = size
    intr = Intrinsics(W, H, 40.0, 40.0)
    views = []
    for k in range(n):
        a = 2 * math.pi * k / n
        c = np.array([0.8 * math.cos(a), 0.8 * math.sin(a), 3.0])
        w2c = _look_at_w2c(c, target=(0.1 * math.cos(a), 0.0, 0.0), up=(0.0, 1.0, 0.0))
        c2w = np.linalg.inv(w2c)
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        d = np.stack([(u - intr.cx_px) / intr.fx, (v - intr.cy_px) / intr.fy, np.ones_like(u)], -1)
        d = d @ c2w[:3, :3].T
        t = -c[2] / d[..., 2]
        X = c + t[..., None] * d
        img = np.stack([_plane_texture(X[..., 0], X[..., 1], ch) for ch in range(3)], 0)
        views.append(FitView(f"p{k}", torch.as_tensor(img, dtype=torch.float32), intr,
                             torch.as_tensor(w2c, dtype=torch.float32)))
    return views


def _plane_texture(x, y, ch):
    return 0.5 + 0.35 * np.sin(9.0 * x + 2.0 * ch) * np.cos(7.0 * y - ch)


def test_plane_sweep_points_lie_on_the_photographed_surface():
    from icomma_plugin.fit.init import plane_sweep_points

    views = _plane_views()
    xyz, rgb = plane_sweep_points(views, (0.0, 0.0, 1.0), 3.5, n=600, seed=1)
    assert xyz.shape == (600, 3) and rgb.shape == (600, 3)
    on = np.abs(xyz[:, 2]) < 0.1
    assert on.mean() > 0.8, on.mean()  # the sweep finds the plane...
    want = np.stack([_plane_texture(xyz[on, 0], xyz[on, 1], c) for c in range(3)], 1)
    err = np.abs(rgb[on] - want)
    assert np.median(err) < 0.05       # ...and its colours
    # a random cloud in the same box is not on the plane
    rnd, _ = random_cube_points(600, 3.5, seed=1)
    assert (np.abs(rnd[:, 2] + 1.0) < 0.1).mean() < 0.1
    # a uniform image gives no depth: the points fill the box uniformly (grey)
    flat = [FitView(v.name, torch.full_like(v.image, 0.3), v.intrinsics, v.w2c) for v in views]
    fill, frgb = plane_sweep_points(flat, (0.0, 0.0, 1.0), 3.5, n=600, seed=1)
    assert fill.shape == (600, 3) and np.abs(fill - [0, 0, 1]).max() <= 3.5 + 1e-5
    assert np.all(frgb == 0.5) and (np.abs(fill[:, 2]) < 0.1).mean() < 0.1
    with pytest.raises(ValueError, match="2 posed images"):
        plane_sweep_points(views[:1], (0, 0, 0), 1.0, n=10)


def test_fit_scene_on_transforms_json_capture(tmp_path):
    """A single-file transforms.json capture with lens distortion fits.

    Masks reach the fit, the points come from the plane sweep, and train / test PSNR are reported.
    """
    from PIL import Image

    from icomma_plugin.fit import fit_scene
    from icomma_plugin.fit.views import views_to_fit
    from icomma_plugin.io.datasets import read_dataset

    rendered = _render_views(_gt_model(), _ring_poses(9), size=32)
    frames = []
    for name, img, _, intr, w2c in rendered:
        (tmp_path / "images").mkdir(exist_ok=True)
        arr = (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
        Image.fromarray(arr).save(tmp_path / "images" / f"{name}.png")
        c2w = np.linalg.inv(w2c)
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    frames.append({"file_path": "images/absent.png", "transform_matrix": np.eye(4).tolist()})
    intr = rendered[0][3]
    (tmp_path / "transforms.json").write_text(json.dumps({
        "fl_x": intr.fx, "fl_y": intr.fy, "cx": 16.0, "cy": 16.0, "w": 32, "h": 32, "k1": 0.08,
        "frames": frames}))
    scene = read_dataset(tmp_path)
    assert len(scene.train) == 7 and len(scene.test) == 2  # v0 and v8 held out
    fv = views_to_fit(scene.train, -1, None, (0.0, 0.0, 0.0))
    assert fv[0].valid is not None and 0.5 < float(fv[0].valid.mean()) < 1.0
    cfg = FitConfig.scaled_schedule(40, sh_degree=1, num_sweep_points=300)
    res = fit_scene(tmp_path, tmp_path / "model", cfg)
    m = res.metrics
    init = m["init"]
    assert init["source"] == "views" and init["points"] == 300 + init["far_field_points"]
    assert init["far_field_points"] > 1000 and init["far_field_radius"] > 3.0  # beyond the ring
    assert m["exposure"] is True and (tmp_path / "model" / "exposure.json").is_file()
    assert m["train_views"] == 7 and m["test_views"] == 2
    assert math.isfinite(m["train_psnr"]) and math.isfinite(m["test_psnr"])
    assert m["seconds_cpu"] > 0 and m["white_background"] is False
    # re-evaluating the written folder on its dataset gives the same figures
    from icomma_plugin.fit import evaluate_model_folder

    ev = evaluate_model_folder(tmp_path / "model")
    assert ev["test_psnr"] == pytest.approx(m["test_psnr"], abs=1e-3)
    assert ev["train_psnr"] == pytest.approx(m["train_psnr"], abs=1e-3)
    assert ev["train_psnr_exposure"] == pytest.approx(m["train_psnr_exposure"], abs=1e-3)
    assert ev["test_psnr_right_half_exposure"] == pytest.approx(
        m["test_psnr_right_half_exposure"], abs=1e-3)
    assert math.isfinite(m["test_psnr_neighbour_exposure"])
    assert ev["test_psnr_neighbour_exposure"] == pytest.approx(
        m["test_psnr_neighbour_exposure"], abs=1e-3)
    assert ev["resolution"] == [32, 32] and set(ev["per_view"]) >= {"v0", "v8"}


def test_resolution_as_target_width_warns_when_images_become_tiny(tmp_path, caplog):
    """Issue 16 bug 4: `-r 6` is upstream's target width (6 px), not a factor: say so."""
    from icomma_plugin.fit import fit_scene

    rendered = _render_views(_gt_model(), _ring_poses(4), size=128)
    _write_blender_dataset(tmp_path / "data", rendered[:3], rendered[3:])
    cfg = FitConfig.scaled_schedule(1, sh_degree=1, num_random_points=50)
    with caplog.at_level("WARNING"):
        res = fit_scene(tmp_path / "data", tmp_path / "m6", cfg, resolution=6)
    assert res.metrics["resolution"] == [6, 6]  # upstream's rule is kept
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("-r" in m and "6x6" in m and "--downscale 6" in m for m in warned), warned
    caplog.clear()
    with caplog.at_level("WARNING"):
        fit_scene(tmp_path / "data", tmp_path / "m2", cfg, resolution=2)  # a factor: 64x64
    assert not [r for r in caplog.records if "-r" in r.getMessage()]
