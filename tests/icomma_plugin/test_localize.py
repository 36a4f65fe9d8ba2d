"""icomma_plugin.localize, the paper's method: losses, gradient modes, schedule, stops, config.

Losses wiring, both gradient modes, the stage switch and its lr schedule, compare-alone steps,
the convergence stop, config validation.

A small textured plane (z = 0) seen by a 64x64 camera keeps every render cheap on the reference
backend. The `fake` matcher gets the exact plane-induced mapping query pixel -> render pixel.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.app.demo_scene import textured_plane_model
from icomma_plugin.pose.convert import look_at_c2w, perturb_pose
from icomma_plugin.localize import LocalizationResult, LocalizerConfig, Query, localize
from icomma_plugin.matchers import make_matcher
from icomma_plugin.pose.se3 import se3_log
from icomma_plugin.render import render


pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.fixture(scope="module")
def plane():
    model = textured_plane_model(n=40, size=2.0, seed=3)
    intr = Intrinsics.from_fov(64, 64, math.radians(60))
    gt_c2w = look_at_c2w((0.2, -1.1, 1.1), (0.0, 0.0, 0.0))
    with torch.no_grad():
        query = render(model, intr, torch.tensor(np.linalg.inv(gt_c2w), dtype=torch.float32),
                       torch.zeros(3)).color.clamp(0, 1)
    return model, intr, gt_c2w, query


def plane_mapping(intr: Intrinsics, query_c2w: np.ndarray, render_c2w: np.ndarray):
    """Query pixels -> render pixels through the plane z = 0 (exact correspondences)."""
    K = intr.K().numpy()
    Kinv = np.linalg.inv(K)
    render_w2c = np.linalg.inv(render_c2w)

    def mapping(k1: torch.Tensor) -> torch.Tensor:
        uv1 = np.concatenate([k1.numpy(), np.ones((len(k1), 1))], 1)
        d = (query_c2w[:3, :3] @ (Kinv @ uv1.T)).T  # world ray directions
        o = query_c2w[:3, 3]
        t = -o[2] / d[:, 2]
        X = o + t[:, None] * d
        Xc = (render_w2c[:3, :3] @ X.T).T + render_w2c[:3, 3]
        uv = (K @ (Xc / Xc[:, 2:3]).T).T[:, :2]
        uv[t <= 0] = np.nan
        return torch.from_numpy(uv)

    return mapping


def reprojection_gap(intr: Intrinsics, w2c: np.ndarray, gt_w2c: np.ndarray) -> float:
    """Mean image distance (px) between the projections of the plane's points under two poses."""
    g = np.linspace(-0.6, 0.6, 7)
    X = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    X = np.c_[X, np.zeros(len(X)), np.ones(len(X))]
    K = intr.K().numpy()

    def proj(T):
        Xc = (T @ X.T).T[:, :3]
        return (K @ (Xc / Xc[:, 2:3]).T).T[:, :2]

    return float(np.linalg.norm(proj(w2c) - proj(gt_w2c), axis=1).mean())


def pose_distance(w2c: np.ndarray, gt_w2c: np.ndarray) -> float:
    """Norm of the twist between two poses (rotation in rad, translation in world units)."""
    d = torch.as_tensor(gt_w2c @ np.linalg.inv(w2c), dtype=torch.float64)
    return float(se3_log(d).norm())


def test_config_defaults_are_the_papers():
    c = LocalizerConfig()
    assert c.lr == 0.05 and c.betas == (0.9, 0.999)
    assert c.lambda_match == 0.8 and c.switch_threshold == 1e-3
    assert c.lr_decay_base == 0.6 and c.lr_decay_steps == 50
    assert c.min_matches == 5 and c.confidence_threshold == 0.5
    assert c.max_iterations == 500
    assert math.isclose(c.stage2_lr(50), 0.05 * 0.6)


@pytest.mark.parametrize("kw", [
    {"lr": 0.0}, {"lambda_match": 1.5}, {"gradient_mode": "pixels"}, {"min_matches": -1},
    {"betas": (0.9,)}, {"max_iterations": 0}, {"image_scale": -1.0}, {"lr_decay_base": 0.0},
])
def test_config_rejects_bad_values(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        LocalizerConfig(**kw)


def test_config_from_dict():
    c = LocalizerConfig.from_dict({"lr": 1, "betas": [0.8, 0.99], "gradient_mode": "depth"})
    assert c.lr == 1.0 and c.betas == (0.8, 0.99) and c.gradient_mode == "depth"
    with pytest.raises(ValueError, match="unknown LocalizerConfig keys.*lrr"):
        LocalizerConfig.from_dict({"lrr": 0.1})
    assert LocalizerConfig.from_dict(LocalizerConfig().to_dict()) == LocalizerConfig()


@pytest.mark.parametrize("mode", ["image", "depth"])
def test_one_step_moves_toward_truth(plane, mode):
    model, intr, gt_c2w, query = plane
    init_c2w = perturb_pose(gt_c2w, 6.0, 0.05, generator=np.random.default_rng(1), pivot="origin")
    matcher = make_matcher("fake", mapping=plane_mapping(intr, gt_c2w, init_c2w), grid_step=6)
    # Matching term alone (lambda = 1) and a small lr: the step follows the matching gradient.
    cfg = LocalizerConfig(lambda_match=1.0, lr=0.005, max_iterations=1, gradient_mode=mode,
                          switch_threshold=0.0, converge_patience=0)
    gt_w2c = np.linalg.inv(gt_c2w)
    res = localize(model, Query(query, intr), matcher=matcher, config=cfg, init_c2w=init_c2w,
                   gt_c2w=gt_c2w)
    assert res.iterations == 1
    rec = res.trace[0]
    assert rec["stage"] == 1 and rec["matches_used"] >= 20 and rec["loss_match"] > 0
    # Closer in the image (what the matching term measures) and closer in se(3).
    gap0 = reprojection_gap(intr, np.linalg.inv(init_c2w), gt_w2c)
    gap1 = reprojection_gap(intr, res.w2c, gt_w2c)
    assert gap1 < 0.9 * gap0, (gap0, gap1)
    assert pose_distance(res.w2c, gt_w2c) < pose_distance(np.linalg.inv(init_c2w), gt_w2c)


def test_losses_wiring_and_switch_schedule(plane):
    model, intr, gt_c2w, query = plane
    init_c2w = perturb_pose(gt_c2w, 2.0, 0.0, generator=np.random.default_rng(2), pivot="origin")
    # Identity correspondences: in depth mode L_match is 0 at the current pose, below any threshold.
    matcher = make_matcher("fake", grid_step=8)
    cfg = LocalizerConfig(
        max_iterations=6, switch_threshold=1.0, converge_patience=0, gradient_mode="depth"
    )
    res = localize(model, Query(query, intr), matcher=matcher, config=cfg, init_c2w=init_c2w)
    t0 = res.trace[0]
    # L = (1 - lambda) L_compare + lambda L_match in stage 1.
    assert t0["stage"] == 1 and t0["loss_match"] is not None
    assert math.isclose(t0["loss"], 0.2 * t0["loss_compare"] + 0.8 * t0["loss_match"], rel_tol=1e-5)
    assert t0["lr"] == 0.05
    # L_match < threshold at iteration 0 -> stage 2 from iteration 1, compare alone, decaying lr.
    assert res.details["switch_iteration"] == 1
    for r in res.trace[1:]:
        t = r["iteration"] - res.details["switch_iteration"] + 1
        assert r["stage"] == 2 and r["loss_match"] is None and r["matches"] == 0
        assert math.isclose(r["loss"], r["loss_compare"], rel_tol=1e-6)
        assert math.isclose(r["lr"], 0.05 * 0.6 ** (t / 50), rel_tol=1e-12)


def test_no_switch_above_threshold(plane):
    model, intr, gt_c2w, query = plane
    init_c2w = perturb_pose(gt_c2w, 8.0, 0.0, generator=np.random.default_rng(2), pivot="origin")
    matcher = make_matcher("fake", grid_step=8, noise=2.0)  # never exact: L_match > 0
    cfg = LocalizerConfig(
        max_iterations=3, switch_threshold=1e-9, converge_patience=0, gradient_mode="depth"
    )
    res = localize(model, Query(query, intr), matcher=matcher, config=cfg, init_c2w=init_c2w)
    assert res.details["switch_iteration"] is None
    assert all(r["stage"] == 1 and r["lr"] == 0.05 for r in res.trace)


@pytest.mark.parametrize("mode", ["image", "depth"])
def test_too_few_matches_compare_alone(plane, mode):
    model, intr, gt_c2w, query = plane
    init_c2w = perturb_pose(gt_c2w, 3.0, 0.0, generator=np.random.default_rng(4), pivot="origin")
    k = torch.tensor([[20.0, 20.0], [40.0, 30.0], [30.0, 44.0]])
    matcher = make_matcher("fake", kpts0=k, kpts1=k)  # 3 matches < min_matches = 5
    cfg = LocalizerConfig(max_iterations=2, converge_patience=0, gradient_mode=mode)
    res = localize(model, Query(query, intr), matcher=matcher, config=cfg, init_c2w=init_c2w)
    for r in res.trace:
        assert r["stage"] == 1 and r["matches"] == 3 and r["matches_used"] == 0
        assert r["loss_match"] is None and r["loss"] == r["loss_compare"]  # weight 1, as iComMa
    assert res.details["match_counts"]["compare_alone_steps"] == 2
    assert res.details["switch_iteration"] is None


def test_low_confidence_matches_dropped(plane):
    model, intr, gt_c2w, query = plane
    matcher = make_matcher("fake", grid_step=8, confidence=0.3)
    cfg = LocalizerConfig(max_iterations=1, converge_patience=0, gradient_mode="depth")
    res = localize(model, Query(query, intr), matcher=matcher, config=cfg, init_c2w=gt_c2w)
    assert res.trace[0]["matches"] > 5 and res.trace[0]["matches_used"] == 0


def test_convergence_stop(plane):
    model, intr, gt_c2w, query = plane
    # Starting at the optimum of the photometric loss: Adam barely moves, the stop fires.
    cfg = LocalizerConfig(use_matching=False, max_iterations=60, converge_patience=5,
                          converge_rot_deg=0.5, converge_trans_rel=0.05, lr=1e-4)
    calls = []
    res = localize(model, Query(query, intr), config=cfg, init_c2w=gt_c2w, gt_c2w=gt_c2w,
                   progress=calls.append)
    assert res.stop_reason == "converged"
    assert res.iterations == 5 and len(calls) == 5 and len(res.trace) == 5
    assert res.details["switch_iteration"] == 0  # compare-only: stage 2 from the start, lr decaying
    assert math.isclose(res.trace[0]["lr"], 1e-4 * 0.6 ** (1 / 50))
    assert res.rot_err_deg < 0.1


def test_max_iterations_stop_and_json(plane):
    model, intr, gt_c2w, query = plane
    init_c2w = perturb_pose(gt_c2w, 3.0, 0.0, generator=np.random.default_rng(5), pivot="origin")
    cfg = LocalizerConfig(use_matching=False, max_iterations=2, converge_patience=0)
    res = localize(model, Query(query, intr), matcher=make_matcher("none"), config=cfg,
                   init_c2w=init_c2w, gt_c2w=gt_c2w)
    assert isinstance(res, LocalizationResult)
    assert res.stop_reason == "max_iterations" and res.iterations == 2
    assert math.isclose(res.init_rot_err_deg, 3.0, abs_tol=1e-6)
    j = res.to_json()
    assert np.allclose(np.asarray(j["c2w"]), res.c2w) and np.allclose(j["init_c2w"], init_c2w)
    assert np.allclose(res.c2w @ res.w2c, np.eye(4), atol=1e-9)
    assert len(j["trace"]) == 2 and j["config"]["lr"] == 0.05
    for key in ("loss", "loss_compare", "lr", "stage", "matches", "rot_err_deg", "trans_err"):
        assert key in j["trace"][0]


def test_pose_update_is_left_perturbation_of_w2c(plane):
    """The trace's twist reproduces what was rendered: w2c = se3_exp(xi) @ w2c_0, not w2c_0 @ ...

    The render at the pose rebuilt from the recorded twist gives the comparing loss recorded at
    that iteration; the right perturbation gives another.
    """
    from icomma_plugin.losses import compare_loss
    from icomma_plugin.pose.se3 import se3_exp

    model, intr, gt_c2w, query = plane
    init_c2w = perturb_pose(gt_c2w, 3.0, 0.02, generator=np.random.default_rng(6), pivot="origin")
    cfg = LocalizerConfig(use_matching=False, max_iterations=3, converge_patience=0)
    res = localize(model, Query(query, intr), config=cfg, init_c2w=init_c2w)
    assert res.trace[0]["xi"] == [0.0] * 6
    xi = torch.tensor(res.trace[2]["xi"], dtype=torch.float64)
    assert float(xi.norm()) > 1e-4
    w2c0 = torch.as_tensor(np.linalg.inv(init_c2w))

    def loss_at(w2c):
        with torch.no_grad():
            img = render(model, intr, w2c.float(), torch.zeros(3)).color
        return float(compare_loss(img, query, None))

    left, right = loss_at(se3_exp(xi) @ w2c0), loss_at(w2c0 @ se3_exp(xi))
    assert math.isclose(left, res.trace[2]["loss_compare"], rel_tol=1e-4)
    assert not math.isclose(right, res.trace[2]["loss_compare"], rel_tol=1e-3)


def test_image_mode_needs_gradient_matcher(plane):
    model, intr, gt_c2w, query = plane

    class NoGrad:
        name = "nograd"
        supports_image_gradient = False

    with pytest.raises(ValueError, match="gradient_mode='depth'"):
        localize(model, Query(query, intr), matcher=NoGrad(), config=LocalizerConfig(),
                 init_c2w=gt_c2w)


def test_bad_inputs(plane):
    model, intr, gt_c2w, query = plane
    with pytest.raises(ValueError, match="intrinsics size"):
        Query(query[:, :32], intr)
    with pytest.raises(ValueError, match="init_c2w"):
        localize(model, Query(query, intr), config=LocalizerConfig(), init_c2w=np.eye(3))
    bad = gt_c2w.copy()
    bad[:3, :3] *= 2
    with pytest.raises(ValueError, match="init_c2w.*rigid"):
        localize(model, Query(query, intr), config=LocalizerConfig(), init_c2w=bad)
    with pytest.raises(ValueError, match="query_alpha"):
        Query(query, intr, alpha=torch.ones(1, 8, 8))
    with pytest.raises(ValueError, match="model_side"):
        localize(model, Query(query, intr), config=LocalizerConfig(), init_c2w=gt_c2w,
                 model_side="64")
    with pytest.raises(ValueError, match="intrinsics must be an Intrinsics"):
        Query(query, {"fx": 1.0})
    with pytest.raises(ValueError, match="query must be a Query"):
        localize(model, query, config=LocalizerConfig(), init_c2w=gt_c2w)
    with pytest.raises(TypeError):  # poses are keywords: an old positional w2c cannot slip in
        localize(model, Query(query, intr), None, None, np.linalg.inv(gt_c2w))


def test_image_scale(plane):
    model, intr, gt_c2w, query = plane
    cfg = LocalizerConfig(
        use_matching=False, max_iterations=1, image_scale=0.5, converge_patience=0
    )
    res = localize(model, Query(query, intr), config=cfg, init_c2w=gt_c2w)
    assert res.iterations == 1 and res.trace[0]["loss_compare"] < 0.05
