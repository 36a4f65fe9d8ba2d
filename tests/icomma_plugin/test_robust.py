"""The default localizer's stages, each on its own, and end to end on the demo scene.

The stages: PnP, geometric rounds, photometric refinement, candidates, verdict; end to end from a
90 degree start and from no start.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.localization.geometry import lift_keypoints, project, solve_pnp
from icomma_plugin.localization.state import LocalizationState
from icomma_plugin.localization.types import Query, Stage
from icomma_plugin.localization.verify import VerdictConfig, decide, score_observation
from icomma_plugin.pose.convert import look_at_c2w, perturb_pose, rotation_error_deg



@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo scene at 100x100 (model, query, intrinsics, gt, ring cameras)."""
    from icomma_plugin.app.demo_scene import build_demo_scene
    from icomma_plugin.io.cameras_json import read_cameras_json

    scene = build_demo_scene(
        tmp_path_factory.mktemp("demo") / "scene", seed=0, width=100, height=100
    )
    cams = [e.c2w for e in read_cameras_json(scene.path / "cameras.json")]
    return scene, scene.load_model(), scene.load_query(), cams


def _state(demo, matcher=None, query=None):
    scene, model, q, _ = demo
    return LocalizationState(
        model,
        Query(q if query is None else query, scene.intrinsics),
        torch.zeros(3),
        matcher=matcher,
        gt_c2w=scene.gt_c2w,
    )


def _refined_error(demo, cfg, query=None):
    """Rotation error [deg] (and the outcome) of a refinement from 0.5 deg off the truth."""
    from icomma_plugin.localization.refine import refine_photometric

    scene = demo[0]
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.5, 0.005, 2, pivot="camera"))
    out = refine_photometric(_state(demo, query=query), start, cfg, scene_depth=4.0)
    return float(rotation_error_deg(np.linalg.inv(out.w2c), scene.gt_c2w)), out


def _assert_matches_central_differences(grad, st, w2c, mask, **evaluate_kwargs):
    """``grad`` (the refinement's pose gradient at ``w2c``) against central differences.

    Of ``refine._evaluate``'s loss with ``evaluate_kwargs``, step 1e-3 per twist component.
    """
    from icomma_plugin.localization.refine import _evaluate
    from icomma_plugin.pose.se3 import se3_exp

    h, fd = 1e-3, torch.zeros(6, dtype=torch.float64)
    for k in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[k] = h
        val = [_evaluate(st, (se3_exp(sign * e) @ torch.as_tensor(w2c)).numpy(), 1.0, mask, None,
                         want_grad=False, **evaluate_kwargs)[0]
               for sign in (1.0, -1.0)]
        fd[k] = (val[0] - val[1]) / (2 * h)
    cos = float(grad @ fd / (grad.norm() * fd.norm()))
    assert cos > 0.99, (grad, fd)
    assert 0.9 < float(grad.norm() / fd.norm()) < 1.1, (grad, fd)


# ------------------------------------------------------------------------------------------- PnP


def test_pnp_recovers_a_known_pose_with_half_outliers():
    rng = np.random.default_rng(3)
    intr = Intrinsics(320, 240, 300.0, 300.0, 158.0, 121.5)
    c2w = look_at_c2w([2.0, -3.0, 1.5], [0.1, 0.0, 0.2])
    w2c = np.linalg.inv(c2w)
    X = rng.uniform(-1, 1, (400, 3))
    uv, z = project(X, w2c, intr)
    assert (z > 0).all()
    uv = uv + rng.normal(0, 0.3, uv.shape)
    outlier = np.arange(400) % 2 == 0
    uv[outlier] = rng.uniform([0, 0], [320, 240], (int(outlier.sum()), 2))
    res = solve_pnp(X, uv, intr, threshold_px=2.0)
    assert res is not None
    assert float(rotation_error_deg(res.w2c, w2c)) < 0.1
    assert np.linalg.norm(np.linalg.inv(res.w2c)[:3, 3] - c2w[:3, 3]) < 0.01
    # the inliers are the true correspondences
    assert (res.inliers & outlier).sum() <= 2 and (res.inliers & ~outlier).sum() >= 190


def test_pnp_gives_up_on_pure_noise():
    rng = np.random.default_rng(0)
    intr = Intrinsics(100, 100, 90.0, 90.0)
    assert solve_pnp(rng.uniform(-1, 1, (40, 3)), rng.uniform(0, 100, (40, 2)), intr, 1.0,
                     min_inliers=20) is None
    assert solve_pnp(np.zeros((3, 3)), np.zeros((3, 2)), intr, 1.0) is None  # too few points


def test_median_depth_of_the_shown_pixels():
    from icomma_plugin.localization.geometry import median_depth

    depth = torch.tensor([[[1.0, 2.0, 3.0, 4.0, 50.0]]])
    alpha = torch.tensor([[[0.9, 0.9, 0.9, 0.9, 0.1]]])
    assert median_depth(depth, alpha) == 2.5  # numpy's median of the four shown
    assert median_depth(depth, torch.zeros_like(alpha)) == 1.0  # nothing shown


@pytest.mark.parametrize("shape", [(1, 1), (2, 9), (7, 5), (40, 33)])
def test_depth_edges_are_those_of_a_3x3_max_and_min_pool(shape):
    """The separable shifted min and max: the same pixels as max_pool2d, borders included."""
    import torch.nn.functional as F

    from icomma_plugin.localization.geometry import depth_edges

    g = torch.Generator().manual_seed(5)
    depth = 2.0 + 0.05 * torch.rand((1,) + shape, generator=g, dtype=torch.float64)
    depth[..., : shape[0] // 2, : shape[1] // 3] = 0.0  # empty pixels: edges around them
    hi = F.max_pool2d(depth[None], 3, stride=1, padding=1)[0]
    lo = -F.max_pool2d(-depth[None], 3, stride=1, padding=1)[0]
    expected = (hi - lo) > 0.05 * depth.clamp_min(1e-12)
    got = depth_edges(depth, 0.05)
    assert got.shape == depth.shape and torch.equal(got, expected)
    if min(shape) > 4:
        assert got.any() and not got.all()


@pytest.mark.parametrize("shape", [(1, 1), (2, 9), (7, 5), (40, 33)])
def test_depth_edges_about_points_are_the_whole_maps_where_a_sample_reads(shape):
    """The depth edges ``lift_keypoints`` computes about its keypoints alone.

    The whole map's values on each point's nearest pixel and neighbours, so a bilinear sample at
    the points reads the same (integer, half-pixel and border positions included).
    """
    from icomma_plugin.localization.geometry import _depth_edges_at, depth_edges, sample_bilinear

    g = torch.Generator().manual_seed(6)
    H, W = shape
    depth = 2.0 + 0.05 * torch.rand((1,) + shape, generator=g, dtype=torch.float64)
    depth[..., H // 3:, W // 2:] += 1.0
    depth[..., : H // 2, : W // 3] = 0.0
    size = torch.tensor([W - 1, H - 1], dtype=torch.float64)
    xy = torch.rand((200, 2), generator=g, dtype=torch.float64) * size
    xy[:40] = torch.round(xy[:40])
    xy[40:60] = torch.floor(xy[40:60]) + 0.5
    xy[60:70, 0], xy[70:80, 1] = 0.0, H - 1.0
    whole = depth_edges(depth, 0.05).to(torch.float64)
    near = _depth_edges_at(depth, xy, 0.05)
    assert near.shape == whole.shape
    c = torch.round(xy).long()
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            x, y = c[:, 0] + dx, c[:, 1] + dy
            inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            assert torch.equal(near[0, y[inside], x[inside]], whole[0, y[inside], x[inside]])
    assert torch.equal(sample_bilinear(near, xy)[:, 0] > 0, sample_bilinear(whole, xy)[:, 0] > 0)


def test_lift_keypoints_inverts_the_projection(demo):
    scene, model, _, _ = demo
    st = _state(demo)
    w2c = np.linalg.inv(scene.gt_c2w)
    out = st.render(w2c)
    ys, xs = torch.nonzero(out.alpha[0] > 0.99, as_tuple=True)
    k = torch.stack([xs, ys], -1)[::37].double()
    pts, keep = lift_keypoints(
        k,
        out.depth,
        out.alpha,
        scene.intrinsics,
        torch.as_tensor(scene.gt_c2w),
        max_depth_jump=0.05,
    )
    uv, _ = project(pts.numpy(), w2c, scene.intrinsics)
    assert keep.sum() > 10 and np.abs(uv - k[keep].numpy()).max() < 1e-6


# ------------------------------------------------------------------------------- stages alone


def test_a_worse_geometric_proposal_is_rejected_and_the_pose_kept(demo, xfeat, monkeypatch):
    """The geometric stage never takes a proposal whose own render scores worse."""
    from icomma_plugin.localization import geometric

    scene, _, _, _ = demo
    st = _state(demo, xfeat)
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 1.0, 0.01, 0, pivot="camera"))
    wrong = np.linalg.inv(perturb_pose(scene.gt_c2w, 35.0, 0.3, 1, pivot="camera"))

    class Bad:
        w2c, num_inliers, inliers, median_error_px = wrong, 50, np.ones(50, bool), 0.1

    monkeypatch.setattr(geometric, "pnp_from_observation", lambda *a, **k: Bad())
    out = geometric.run_geometric(st, start, geometric.GeometricConfig(max_rounds=3))
    assert np.array_equal(out.w2c, start)
    recs = [r for r in st.trace if r.stage == Stage.GEOMETRIC]
    assert [r.accepted for r in recs] == [True, False]


def _scripted_rounds(monkeypatch, counts, proposals):
    """Script the geometric stage: no render is matched.

    Its renders score ``counts`` (agreeing matches) in turn, and their PnP proposes
    ``proposals`` ((w2c, inliers) pairs) in turn.
    """
    from icomma_plugin.localization import geometric
    from icomma_plugin.localization.verify import PoseScore

    counts, proposals = iter(counts), iter(proposals)
    monkeypatch.setattr(geometric, "score_observation",
                        lambda *a, **k: PoseScore(400, next(counts), 1.0, 0.6, 0.8, 1.0, 0.1))

    def propose(*a, **k):
        class P:
            (w2c, num_inliers), inliers, median_error_px = next(proposals), None, 0.5
        return P()

    monkeypatch.setattr(geometric, "pnp_from_observation", propose)


@pytest.mark.parametrize("patience", [0, 1, 2])
def test_a_dip_in_the_score_is_crossed_within_the_patience(demo, xfeat, monkeypatch, patience):
    """Proposals scoring below the best go on from their own PnP, ``patience`` in a row at most.

    The scores of goldcape's IMG_5937: 244 agreeing matches, then 210 and 200 on the way, then
    327 at the right pose; the stage keeps the best-scored pose it saw.
    """
    from icomma_plugin.localization import geometric

    scene, _, _, _ = demo
    poses = [np.linalg.inv(perturb_pose(scene.gt_c2w, d, 0.01 * d, i, pivot="camera"))
             for i, d in enumerate((1.4, 0.9, 0.5, 0.05))]
    # each round's render proposes the next pose; the last proposal moves the pose no more
    _scripted_rounds(monkeypatch, [244, 210, 200, 327, 330],
                     zip(poses[1:] + [poses[-1]], [242, 245, 227, 280, 281]))
    st = _state(demo, xfeat)
    out = geometric.run_geometric(st, poses[0], geometric.GeometricConfig(patience=patience))
    accepted = [r.accepted for r in st.trace if r.stage == Stage.GEOMETRIC]
    if patience == 2:
        assert accepted == [True, False, False, True] and out.converged
        assert np.array_equal(out.w2c, poses[3]) and out.score.inliers == 327
        assert out.pnp_inliers == [242, 280]  # the accepted rounds' (the dips' are not)
    else:
        assert accepted == [True] + [False] * (patience + 1) and not out.converged
        assert np.array_equal(out.w2c, poses[0]) and out.score.inliers == 244
        assert out.pnp_inliers == [242]  # the best pose's proposal stays the last
    with pytest.raises(ValueError, match="GeometricConfig.patience"):
        geometric.GeometricConfig(patience=-1)


@pytest.mark.parametrize("tie, count, ends_there", [(0.05, 310, True), (0.05, 300, False),
                                                     (None, 310, False)])
def test_a_fixed_point_of_pnp_within_the_tie_ends_the_stage(demo, xfeat, monkeypatch, tie,
                                                            count, ends_there):
    """A render below the best whose own proposal barely moves it is taken within the tie.

    goldcape's IMG_5953: 322 agreeing matches 0.33 deg off, whose proposal moves 0.27 deg; that
    render agrees with 310 and its proposal stays (a fixed point of PnP).
    """
    from icomma_plugin.localization import geometric

    scene, _, _, _ = demo
    far = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.33, 0.003, 0, pivot="camera"))
    near = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.07, 0.0005, 1, pivot="camera"))
    stay = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.06, 0.0005, 1, pivot="camera"))
    _scripted_rounds(monkeypatch, [322, count], [(near, 276), (stay, 281)])
    st = _state(demo, xfeat)
    cfg = geometric.GeometricConfig(fixed_point_tie=tie)
    out = geometric.run_geometric(st, far, cfg)
    assert [r.accepted for r in st.trace if r.stage == Stage.GEOMETRIC] == [True, False]
    if ends_there:
        assert np.array_equal(out.w2c, stay) and out.converged and out.score.inliers == count
        assert out.pnp_inliers == [276, 281]
    else:
        assert np.array_equal(out.w2c, far) and not out.converged and out.score.inliers == 322
        assert out.pnp_inliers == [276]
    with pytest.raises(ValueError, match="GeometricConfig.fixed_point_tie"):
        geometric.GeometricConfig(fixed_point_tie=1.0)


@pytest.mark.parametrize("join_deg, shift, joined", [(5.0, 0.0, True), (1.0, 0.0, False),
                                                    (5.0, 1.0, False), (None, 0.0, False)])
def test_a_stage_that_leads_to_the_pose_it_may_join_stops_there(demo, xfeat, monkeypatch,
                                                                join_deg, shift, joined):
    """A rival hypothesis whose proposal lands near the best pose stops (``join``).

    The proposal 2 deg from the pose to join: within 5 deg it joins after the first round
    (unless its centre is elsewhere: a repeating scene's twin); within 1 deg it goes on.
    """
    from icomma_plugin.localization import geometric

    scene, _, _, _ = demo
    best = np.linalg.inv(scene.gt_c2w)
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 25.0, 0.1, 0, pivot="camera"))
    near = np.linalg.inv(perturb_pose(scene.gt_c2w, 2.0, 0.0, 1, pivot="camera"))
    near[:3, 3] += shift * np.asarray(near[:3, :3])[:, 0]  # its centre moved sideways
    stay = near.copy()
    _scripted_rounds(monkeypatch, [150, 300, 301], [(near, 140), (stay, 290), (stay, 290)])
    st = _state(demo, xfeat)
    join = None if join_deg is None else (best, join_deg)
    out = geometric.run_geometric(st, start, geometric.GeometricConfig(max_rounds=3), join=join)
    assert out.joined == joined
    if joined:
        assert out.rounds == 1 and np.array_equal(out.w2c, start) and out.score.inliers == 150
    else:
        assert out.rounds == 2 and out.converged and out.score.inliers == 300


def test_a_hypothesis_that_joined_is_neither_the_best_nor_a_rival():
    """``_Search`` keeps its best and ``_rival`` looks past a hypothesis that joined it."""
    from icomma_plugin.localization import robust
    from icomma_plugin.localization.geometric import GeometricOutcome
    from icomma_plugin.localization.verify import PoseScore

    def outcome(w2c, inliers, joined=False):
        score = PoseScore(inliers + 10, inliers, 0.3, 0.3, 0.5, 0.9, 0.05)
        return GeometricOutcome(w2c, None, score, 1, False, inliers, 0.9, [inliers], joined)

    cfg = robust.RobustConfig()
    best = outcome(np.eye(4), 200)
    far = perturb_pose(np.eye(4), 30.0, 0.0, 0, pivot="camera")
    assert robust._rival([("a", best), ("b", outcome(far, 190))], best, cfg) is not None
    assert robust._rival([("a", best), ("b", outcome(far, 190, True))], best, cfg) is None

    search = robust._Search(None, cfg, 1.0)
    search.best = best

    class Index:
        source = {3: "r_3"}

        def start_w2c(self, idx, turns):
            return far

    import unittest.mock as mock

    with mock.patch.object(robust, "run_geometric", lambda *a, **k: outcome(far, 250, True)):
        search._run_candidate(Index(), 3, 0, 2, " (rival)", join=(best.w2c, 5.0))
    assert search.best is best and search.hyps[-1][1].joined
    with mock.patch.object(robust, "run_geometric", lambda *a, **k: outcome(far, 250)):
        search._run_candidate(Index(), 3, 0, 3)
    assert search.best is search.hyps[-1][1]


@pytest.mark.parametrize("converged, rounds, joins", [(True, 3, True), (True, 8, False),
                                                     (False, 3, False)])
def test_a_rival_may_join_only_a_best_pose_that_settled(monkeypatch, converged, rounds, joins):
    """The rival's rounds stop near the best pose only if that converged before its last round.

    A best that needed all its rounds may not sit at its basin's fixed point (goldcape's
    IMG_5913): the rival then runs to its end and is taken if it scores better.
    """
    from icomma_plugin.localization import robust
    from icomma_plugin.localization.geometric import GeometricOutcome
    from icomma_plugin.localization.verify import PoseScore

    cfg = robust.RobustConfig()
    score = PoseScore(250, 240, 0.3, 0.3, 0.5, 0.9, 0.05)
    search = robust._Search(None, cfg, 1.0)
    search.best = GeometricOutcome(np.eye(4), None, score, rounds, converged, 200, 0.9, [200])
    far = perturb_pose(np.eye(4), 30.0, 0.0, 0, pivot="camera")

    class Index:
        source, features, last_counts = ["a", "b"], [object(), object()], [100, 95]

        def start_w2c(self, idx, turns):
            return np.eye(4) if idx == 0 else far

    asked = {}

    def fake(state, w2c, cfg_, scale, hypothesis=None, join=None):
        asked["join"] = join
        return GeometricOutcome(w2c, None, score, 1, False, 0, 0.9, [], join is not None)

    monkeypatch.setattr(robust, "run_geometric", fake)
    search._run_rival(Index(), [(0, 0), (1, 0)], {0})
    assert (asked["join"] is not None) == joins
    if joins:
        assert asked["join"][1] == robust.RIVAL_JOIN_SHARE * cfg.candidates.rival_deg


def test_a_proposal_within_the_tie_wins_on_its_mean_displacement(demo, xfeat, monkeypatch):
    """Near the answer the agreeing counts differ by noise: the mean displacement decides."""
    from icomma_plugin.localization import geometric
    from icomma_plugin.localization.verify import PoseScore

    scene, _, _, _ = demo
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 2.0, 0.01, 0, pivot="camera"))
    near = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.1, 0.001, 1, pivot="camera"))
    scores = None  # per run below: the start agrees with 185 matches at 0.34 px, the proposal
    # with 179 (3 % fewer) at 0.28 px
    monkeypatch.setattr(geometric, "score_observation", lambda *a, **k: next(scores))

    class Near:
        w2c, num_inliers, inliers, median_error_px = near, 150, np.ones(150, bool), 0.3

    monkeypatch.setattr(geometric, "pnp_from_observation", lambda *a, **k: Near())
    for tie, taken in ((0.05, True), (0.02, False)):
        scores = iter([PoseScore(200, 185, 0.3, 0.34, 0.8, 0.9, 0.05),
                       PoseScore(200, 179, 0.2, 0.28, 0.8, 0.9, 0.05)])
        st = _state(demo, xfeat)
        cfg = geometric.GeometricConfig(max_rounds=2, accept_tie=tie)
        out = geometric.run_geometric(st, start, cfg)
        recs = [r for r in st.trace if r.stage == Stage.GEOMETRIC]
        assert [r.accepted for r in recs] == [True, taken]
        assert np.array_equal(out.w2c, near if taken else start)
    with pytest.raises(ValueError, match="GeometricConfig.accept_tie"):
        geometric.GeometricConfig(accept_tie=1.0)


def test_refinement_never_increases_the_loss_and_a_rejected_step_keeps_the_pose(demo):
    from icomma_plugin.localization.refine import RefineConfig, refine_photometric

    scene, _, _, _ = demo
    st = _state(demo)
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.5, 0.005, 2, pivot="camera"))
    cfg = RefineConfig(scales=(1.0,), blur=(0.0,), iterations=(6,))
    out = refine_photometric(st, start, cfg, scene_depth=4.0)
    accepted = [r for r in st.trace if r.accepted]
    losses = [r.loss for r in accepted]
    assert losses == sorted(losses, reverse=True)
    assert out.loss_end <= out.loss_start
    assert float(rotation_error_deg(np.linalg.inv(out.w2c), scene.gt_c2w)) < 0.1

    # At the optimum (the query is the render at the truth) no step lowers the loss: every step
    # is rejected and the pose is returned exactly as given.
    gt_w2c = np.linalg.inv(scene.gt_c2w)
    st2 = _state(demo, query=st.render(gt_w2c).color.detach().clamp(0, 1))
    out2 = refine_photometric(
        st2, gt_w2c, RefineConfig(scales=(1.0,), blur=(0.0,), iterations=(3,)), scene_depth=4.0
    )
    assert [r.accepted for r in st2.trace] == [False] * len(st2.trace) and len(st2.trace) == 3
    assert np.array_equal(out2.w2c, gt_w2c)


def test_the_last_step_of_a_level_takes_no_backward_pass_and_the_same_pose(demo, monkeypatch):
    """Its gradient would serve no further step: one backward pass fewer, the same result."""
    import icomma_plugin.localization.refine as refine
    from icomma_plugin.localization.refine import RefineConfig, refine_photometric

    scene, _, _, _ = demo
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.5, 0.005, 2, pivot="camera"))
    # a level that ends on its own count (extra steps would need the last step's gradient)
    cfg = RefineConfig(scales=(0.5, 1.0), blur=(1.0, 0.0), iterations=(2, 3), extra_iterations=0)
    evaluate = refine._evaluate

    def run(always_grad: bool):
        st, calls = _state(demo), []

        def counted(*args, **kwargs):
            if always_grad:
                kwargs["want_grad"] = True
            loss, grad, out, mask = evaluate(*args, **kwargs)
            calls.append(grad is not None)
            return loss, grad, out, mask

        monkeypatch.setattr(refine, "_evaluate", counted)
        return refine_photometric(st, start, cfg, scene_depth=4.0), calls

    fewer, calls = run(always_grad=False)
    every, calls_every = run(always_grad=True)
    assert np.array_equal(fewer.w2c, every.w2c) and fewer.loss_end == every.loss_end
    assert fewer.accepted == every.accepted and fewer.iterations == every.iterations
    assert sum(calls) < sum(calls_every) and fewer.accepted >= 2  # the levels' last steps


def test_finite_difference_hessian_agrees_with_the_motion_field_model(demo):
    """The two Gauss-Newton Hessians describe the same curvature (cheap model: 15-30 % short)."""
    from icomma_plugin.localization.refine import _hessian_and_jacobian, RefineConfig
    from icomma_plugin.localization.state import Observation
    from icomma_plugin.localization.verify import coverage_mask

    scene, _, _, _ = demo
    st = _state(demo)
    w2c = np.linalg.inv(scene.gt_c2w)
    out = st.render(w2c)
    mask = coverage_mask(Observation(w2c, 1.0, out.color, out.depth, out.alpha), st)
    q = st.query_at(1.0).rgb
    h_fd, _ = _hessian_and_jacobian(
        st, RefineConfig(hessian="finite_difference"), w2c, 1.0, out, mask, scene.intrinsics, 0.0,
        q, None,
    )
    h_mf, _ = _hessian_and_jacobian(
        st, RefineConfig(hessian="motion_field"), w2c, 1.0, out, mask, scene.intrinsics, 0.0, q,
        None,
    )
    cos = float((h_fd * h_mf).sum() / (h_fd.norm() * h_mf.norm()))
    assert cos > 0.9
    assert 0.3 < float(torch.trace(h_mf) / torch.trace(h_fd)) < 1.2


def test_exposure_fit_recovers_a_known_gain_and_offset_over_the_mask():
    from icomma_plugin.localization.refine import exposure_fit

    g = torch.Generator().manual_seed(0)
    render = torch.rand(3, 20, 30, generator=g, dtype=torch.float64)
    a_true = torch.tensor([0.7, 1.0, 1.4], dtype=torch.float64).view(3, 1, 1)
    b_true = torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64).view(3, 1, 1)
    query = a_true * render + b_true
    mask = torch.zeros(1, 20, 30, dtype=torch.float64)
    mask[:, :, :15] = 1.0
    query[:, :, 15:] = torch.rand(3, 20, 15, generator=g, dtype=torch.float64)  # not in the mask
    a, b = exposure_fit(render, query, mask, (0.5, 2.0))
    assert torch.allclose(a, a_true, atol=1e-9) and torch.allclose(b, b_true, atol=1e-9)

    # A gain beyond the range is clamped, and the offset then fits the means at that gain.
    a, b = exposure_fit(render, 3.0 * render, torch.ones(1, 20, 30, dtype=torch.float64),
                        (0.5, 2.0))
    assert torch.allclose(a, torch.full_like(a, 2.0))
    assert torch.allclose(b.flatten(), (3.0 * render - 2.0 * render).mean((1, 2)), atol=1e-12)
    # Nothing in the mask: the identity.
    a, b = exposure_fit(render, query, torch.zeros(1, 20, 30, dtype=torch.float64), (0.5, 2.0))
    assert torch.equal(a, torch.ones_like(a)) and torch.equal(b, torch.zeros_like(b))


def test_the_exposure_profiled_gauss_newton_matrix_is_that_of_the_projected_jacobian():
    """The 6x6 moments' closed form equals projecting each channel's Jacobian off (render, 1)."""
    from icomma_plugin.localization.refine import _gauss_newton

    g = torch.Generator().manual_seed(3)
    J = torch.randn(3, 6, 12, 17, generator=g, dtype=torch.float64)
    w = torch.rand(1, 12, 17, generator=g, dtype=torch.float64) * (
        torch.rand(1, 12, 17, generator=g) > 0.3)
    base = torch.rand(3, 12, 17, generator=g)
    gains = torch.tensor([0.8, 1.0, 1.3])
    expected = torch.zeros(6, 6, dtype=torch.float64)
    for c in range(3):
        Jc, wc = J[c].reshape(6, -1), w.reshape(-1)
        basis = torch.stack([torch.ones_like(wc), base[c].double().reshape(-1)], 1)  # [P, 2]
        coef = torch.linalg.solve(basis.T @ (basis * wc[:, None]), basis.T @ (Jc * wc).T)
        Jp = (Jc - (basis @ coef).T) * gains[c]
        expected += (Jp * wc) @ Jp.T
    expected *= 2.0 / (3 * 50.0)
    got = _gauss_newton(J, w, (gains, base), norm=50.0)
    assert torch.allclose(got, expected, rtol=1e-10, atol=1e-12), (got - expected).abs().max()
    plain = 2.0 * torch.einsum("cip,cjp->ij", (J * w).reshape(3, 6, -1),
                               J.reshape(3, 6, -1)) / (3 * float(w.sum()))
    assert torch.allclose(_gauss_newton(J, w), plain, rtol=1e-12)


@pytest.mark.parametrize("block", [50, 1 << 16])
def test_the_gauss_newton_matrix_of_a_float32_jacobian_in_blocks_is_the_float64_one(
        block, monkeypatch):
    """Moments summed over pixel blocks, from a float32 Jacobian: the float64 matrix to ~1e-6."""
    from icomma_plugin.localization import refine

    g = torch.Generator().manual_seed(4)
    J = torch.randn(3, 6, 40, 30, generator=g, dtype=torch.float64)
    w = (torch.rand(1, 40, 30, generator=g) > 0.2).double()
    base = 0.4 + 0.3 * torch.rand(3, 40, 30, generator=g)
    gains = torch.tensor([0.9, 1.0, 1.2], dtype=torch.float64)
    whole = {ex: refine._gauss_newton(J, w, (gains, base) if ex else None, 7.0)
             for ex in (False, True)}
    monkeypatch.setattr(refine, "_GN_BLOCK", block)  # 24 blocks of 50 pixels, or one
    for ex in (False, True):
        exposure = (gains, base) if ex else None
        in_blocks = refine._gauss_newton(J, w, exposure, 7.0)
        assert torch.allclose(in_blocks, whole[ex], rtol=1e-12, atol=1e-14)
        f32 = refine._gauss_newton(J.float(), w, exposure, 7.0)
        assert f32.dtype == torch.float64
        assert (f32 - whole[ex]).abs().max() < 1e-5 * whole[ex].abs().max()


def test_a_bad_exposure_setting_is_one_error_naming_it():
    from icomma_plugin.localization.refine import RefineConfig
    from icomma_plugin.localization.robust import RobustConfig

    with pytest.raises(ValueError, match=r"RefineConfig.exposure must be one of .*got 'auto'"):
        RefineConfig(exposure="auto")
    for gain in ((2.0, 3.0), (0.0, 2.0), (0.5,), (1.5, 0.5)):
        with pytest.raises(ValueError, match="RefineConfig.exposure_gain must be"):
            RefineConfig(exposure_gain=gain)
    # the tools' YAML lists become tuples, and the range is None when nothing is fitted
    cfg = RobustConfig.from_dict({"refine": {"exposure_gain": [0.8, 1.25]}}).refine
    assert cfg.exposure_gain == (0.8, 1.25) and cfg.fitted_gain_range == (0.8, 1.25)
    assert RefineConfig(exposure="none").fitted_gain_range is None


def test_the_exposure_profiled_gradient_matches_finite_differences(demo):
    """The exposure-profiled loss's gradient is exact (checked by central differences).

    With the exposure fitted at each pose the loss is ``min_{a,b} |a I + b - Q|^2``; the gradient
    at the fitted ``a, b`` is its derivative (envelope theorem).
    """
    from icomma_plugin.localization.refine import _evaluate

    scene, _, _, _ = demo
    gt_w2c = np.linalg.inv(scene.gt_c2w)
    clean = _state(demo).render(gt_w2c).color.detach().clamp(0, 1)
    gains = torch.tensor([0.6, 0.8, 1.2]).view(3, 1, 1)
    st = _state(demo, query=(gains * clean + 0.05).clamp(0, 1))
    w2c = np.linalg.inv(perturb_pose(scene.gt_c2w, 1.0, 0.01, 4, pivot="camera"))
    rng = (0.5, 2.0)
    _, _, _, mask = _evaluate(st, w2c, 1.0, None, None, exposure_gain=rng)
    _, grad, _, _ = _evaluate(st, w2c, 1.0, mask, None, exposure_gain=rng)
    _assert_matches_central_differences(grad, st, w2c, mask, exposure_gain=rng)


def test_the_exposure_keeps_a_tinted_photo_from_pulling_the_pose(demo):
    """A photo darker and tinted against the model: the exposure-fitted refinement ends nearer.

    Nearer the truth than the plain comparison, from the same start.
    """
    from icomma_plugin.localization.refine import RefineConfig

    scene, _, _, _ = demo
    gt_w2c = np.linalg.inv(scene.gt_c2w)
    clean = _state(demo).render(gt_w2c).color.detach().clamp(0, 1)
    gains = torch.tensor([0.55, 0.75, 1.1]).view(3, 1, 1)
    tinted = (gains * clean + torch.tensor([0.08, 0.02, -0.03]).view(3, 1, 1)).clamp(0, 1)
    errors = {mode: _refined_error(demo, RefineConfig(iterations=(8,), exposure=mode), tinted)[0]
              for mode in ("none", "affine")}
    assert errors["affine"] < 0.05, errors
    assert errors["affine"] < 0.5 * errors["none"], errors


def test_the_cauchy_loss_gradient_matches_finite_differences(demo):
    """The robust (Cauchy) comparison's pose gradient is exact, the exposure fitted too.

    The loss's scale ``c2`` is set at the first evaluation and then fixed, as in a level.
    """
    from icomma_plugin.localization.refine import _Cauchy, _evaluate

    scene, _, _, _ = demo
    gt_w2c = np.linalg.inv(scene.gt_c2w)
    clean = _state(demo).render(gt_w2c).color.detach().clamp(0, 1)
    st = _state(demo, query=(0.8 * clean + 0.05).clamp(0, 1))
    w2c = np.linalg.inv(perturb_pose(scene.gt_c2w, 1.0, 0.01, 4, pivot="camera"))
    rng, robust = (0.5, 2.0), _Cauchy(1.0)
    _, _, _, mask = _evaluate(st, w2c, 1.0, None, None, exposure_gain=rng, robust=robust)
    c2 = robust.c2
    assert c2 is not None and c2 > 0
    loss, grad, _, _ = _evaluate(st, w2c, 1.0, mask, None, exposure_gain=rng, robust=robust)
    assert robust.c2 == c2  # fixed once set
    # below the plain mean squared difference: large residuals count less
    plain = _evaluate(st, w2c, 1.0, mask, None, exposure_gain=rng, want_grad=False)[0]
    assert 0 < loss < plain
    _assert_matches_central_differences(grad, st, w2c, mask, exposure_gain=rng, robust=robust)


def test_the_cauchy_loss_keeps_an_occluder_from_pulling_the_pose(demo):
    """A photo with a patch the model cannot explain: the robust refinement ends nearer.

    The patch (a fifth of the image, of a colour the scene does not have) pulls the plain
    comparison; the Cauchy loss counts its pixels logarithmically.
    """
    from icomma_plugin.localization.refine import RefineConfig

    scene, _, _, _ = demo
    gt_w2c = np.linalg.inv(scene.gt_c2w)
    photo = _state(demo).render(gt_w2c).color.detach().clamp(0, 1).clone()
    H, W = photo.shape[1:]
    photo[:, : H // 2, : int(0.4 * W)] = torch.tensor([1.0, 0.0, 1.0]).view(3, 1, 1)
    errors = {mode: _refined_error(demo, RefineConfig(iterations=(8,), robust=mode), photo)[0]
              for mode in ("none", "cauchy")}
    assert errors["cauchy"] < 0.07, errors
    assert errors["cauchy"] < 0.5 * errors["none"], errors


def test_the_cauchy_loss_converges_on_a_clean_image(demo):
    """From 0.5 deg off the demo scene's own render, the robust refinement reaches the truth.

    Its Gauss-Newton matrix is reweighted at every accepted step: with the weights of the
    level's first (misaligned) render kept, it stalled after one step at 0.16-0.25 deg.
    """
    from icomma_plugin.localization.refine import RefineConfig

    for exposure in ("none", "affine"):
        cfg = RefineConfig(iterations=(6,), robust="cauchy", exposure=exposure)
        err, out = _refined_error(demo, cfg)
        assert err < 0.02, exposure
        assert out.accepted >= 3 and out.loss_end < out.loss_start


def test_a_bad_robust_setting_is_one_error_naming_it():
    from icomma_plugin.localization.refine import RefineConfig

    with pytest.raises(ValueError, match=r"RefineConfig.robust must be one of .*got 'huber'"):
        RefineConfig(robust="huber")
    with pytest.raises(ValueError, match="RefineConfig.robust_scale"):
        RefineConfig(robust_scale=0.0)


def test_candidates_rank_the_nearest_camera_first(demo, xfeat, tmp_path):
    from icomma_plugin.localization.candidates import CandidateConfig
    from icomma_plugin.localization.localizer import Localizer

    scene, model, q, cams = demo
    loc = Localizer(model, xfeat, cameras=cams, cache_dir=tmp_path)
    index = loc.candidate_index(scene.intrinsics)
    st = _state(demo, xfeat)
    order = [i for i, _ in index.rank(st, CandidateConfig())]
    angles = [float(rotation_error_deg(c, scene.gt_c2w)) for c in index.c2w]
    dists = [np.linalg.norm(c[:3, 3] - scene.gt_c2w[:3, 3]) for c in index.c2w]
    # the best-ranked view is among the 5 closest (by viewing direction and position)
    closeness = np.argsort(np.asarray(angles) / 10.0 + np.asarray(dists))
    assert order[0] in closeness[:5]
    # left out, the best one is never ranked
    assert order[0] not in [i for i, _ in index.rank(st, CandidateConfig(), exclude={order[0]})]
    other = LocalizationState(model, Query(torch.zeros(3, 64, 32), Intrinsics(32, 64, 60.0, 60.0)),
                              torch.zeros(3), matcher=xfeat)
    with pytest.raises(ValueError, match="another aspect ratio"):
        index.rank(other, CandidateConfig())


@pytest.mark.parametrize("k", [1, 2, 3])
def test_rolled_w2c_renders_the_view_turned_like_rot90(demo, k):
    """The camera of a photo that matches a view after rot90(photo, k) is rolled_w2c(view, k)."""
    from icomma_plugin.localization.candidates import rolled_w2c

    scene, _, _, _ = demo
    st = _state(demo)
    w2c = np.linalg.inv(scene.gt_c2w)
    view = st.render(w2c).color
    photo = st.render(rolled_w2c(w2c, k)).color  # a square image with its centre at (W-1)/2
    assert float((torch.rot90(photo, k, dims=(1, 2)) - view).abs().mean()) < 0.01
    assert float((torch.rot90(photo, -k, dims=(1, 2)) - view).abs().mean()) > 0.02 or k == 2


def test_a_photo_taken_sideways_is_found_without_a_start(demo, xfeat):
    """No start, a camera rolled 90 degrees: the best-ranked start is a camera turned alike."""
    from icomma_plugin.localization.candidates import rolled_w2c
    from icomma_plugin.localize import localize

    scene, model, _, cams = demo
    gt_w2c = rolled_w2c(np.linalg.inv(scene.gt_c2w), 1)
    photo = _state(demo).render(gt_w2c).color.clamp(0, 1)
    res = localize(model, Query(photo, scene.intrinsics), matcher=xfeat,
                   gt_c2w=np.linalg.inv(gt_w2c), cameras=cams, cache_dir=False)
    assert res.rot_err_deg < 0.1 and res.verdict.status == "ok", res.verdict.reason
    hyps = res.details["hypotheses"]
    assert hyps[0]["start"].endswith("turned 90 deg"), hyps


# ------------------------------------------------------------------------------------ verdict


def test_verdict_is_failed_for_an_empty_render(demo, xfeat):
    scene, _, _, _ = demo
    st = _state(demo, xfeat)
    away = scene.gt_c2w.copy()
    # turned around: looks away from the scene
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    obs = st.observe(np.linalg.inv(away))
    v = decide(score_observation(obs, st, 2.0), VerdictConfig())
    assert v.status == "failed" and "sees almost none of the scene" in v.reason


def test_verdict_is_failed_or_uncertain_for_a_wrong_pose_and_ok_for_the_truth(demo, xfeat):
    scene, _, _, _ = demo
    st = _state(demo, xfeat)
    wrong = perturb_pose(scene.gt_c2w, 25.0, 0.3, 5, pivot=scene.scene_centre)
    v_wrong = decide(score_observation(st.observe(np.linalg.inv(wrong)), st, 2.0), VerdictConfig())
    v_right = decide(
        score_observation(st.observe(np.linalg.inv(scene.gt_c2w)), st, 2.0),
        VerdictConfig(),
        converged=True,
    )
    assert v_wrong.status in ("failed", "uncertain"), v_wrong
    assert v_right.status == "ok", v_right
    assert v_right.signals["inliers"] >= 30 and "inlier_ratio" in v_right.signals


def _good_score():
    from icomma_plugin.localization.verify import PoseScore

    return PoseScore(matches=300, inliers=280, median_px=0.5, mean_px=0.5, spread=0.5,
                     coverage=0.6, photometric_rmse=0.05)


@pytest.mark.parametrize("focal, status", [
    ({"scale": 1.07, "rms_px": 0.8, "rms_px_given": 1.1}, "uncertain"),  # off, and explains
    ({"scale": 0.93, "rms_px": 0.8, "rms_px_given": 1.1}, "uncertain"),
    ({"scale": 1.02, "rms_px": 0.5, "rms_px_given": 1.1}, "ok"),  # within the tolerance
    ({"scale": 1.07, "rms_px": 1.05, "rms_px_given": 1.1}, "ok"),  # explains little more
    (None, "ok"),  # not measured (too few matches, or another method)
    ({"scale": None, "rms_px": 0.8, "rms_px_given": 1.1}, "ok"),  # unreadable: not a verdict
])
def test_the_intrinsics_check_makes_a_pose_uncertain_only_when_another_focal_explains_it(
        focal, status):
    v = decide(_good_score(), VerdictConfig(), converged=True, extra={"focal": focal})
    assert v.status == status, v.reason
    if status == "uncertain":
        assert f"focal length {focal['scale']:.3f}x" in v.reason and "refine.focal" in v.reason
        assert v.signals["focal"] == focal
    # off: never
    off = decide(_good_score(), VerdictConfig(ok_focal_scale=None), converged=True,
                 extra={"focal": focal})
    assert off.status == "ok"


def test_the_intrinsics_check_says_when_the_retry_did_not_pass():
    focal = {"scale": 1.07, "rms_px": 0.8, "rms_px_given": 1.1}
    v = decide(_good_score(), VerdictConfig(), converged=True,
               extra={"focal": focal, "focal_retry": "not kept"})
    assert v.status == "uncertain" and v.signals["focal_retry"] == "not kept"
    assert "did not pass either" in v.reason and "refine.focal" not in v.reason


def test_the_intrinsics_check_is_kept_by_a_calibration_and_redecided_from_signals():
    """A recorded row's verdict decided again (calibration) still sees the focal signal."""
    from icomma_plugin.localization.calibration import redecide

    v = decide(_good_score(), VerdictConfig(), converged=True,
               extra={"focal": {"scale": 1.07, "rms_px": 0.8, "rms_px_given": 1.1}})
    again = redecide(v.to_json()["signals"], VerdictConfig(ok_inliers=10))
    assert again.status == "uncertain" and "focal length" in again.reason


@pytest.mark.parametrize("kwargs, message", [
    ({"ok_focal_scale": -0.1}, "ok_focal_scale"), ({"ok_focal_gain": 0.0}, "ok_focal_gain"),
    ({"ok_focal_gain": 1.5}, "ok_focal_gain"), ({"ok_focal_scale": "x"}, "ok_focal_scale"),
])
def test_a_bad_intrinsics_check_setting_names_it(kwargs, message):
    with pytest.raises(ValueError, match=message):
        VerdictConfig(**kwargs)


@pytest.fixture(scope="module")
def demo200(tmp_path_factory):
    """The demo scene at 200x200: a 4 % focal error moves its edges by 4 px."""
    from icomma_plugin.app.demo_scene import build_demo_scene
    from icomma_plugin.io.cameras_json import read_cameras_json

    scene = build_demo_scene(tmp_path_factory.mktemp("demo200") / "scene", seed=0,
                             width=200, height=200)
    cams = [e.c2w for e in read_cameras_json(scene.path / "cameras.json")]
    return scene, scene.load_model(), scene.load_query(), cams


def test_a_pose_found_with_a_wrong_focal_length_is_uncertain_or_found_with_it_free(demo200, xfeat):
    """Given 8 % too short a focal length, the distance makes up for it: not ``ok``.

    With the check's retry (the default) the focal length is estimated and the pose is right.
    """
    import dataclasses

    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localize import localize

    scene, model, q, cams = demo200
    i = scene.intrinsics
    init = perturb_pose(scene.gt_c2w, 10.0, 0.05, 7, pivot="camera")
    given = Intrinsics(i.width, i.height, i.fx * 0.92, i.fy * 0.92, i.cx, i.cy)
    res = {}
    for name, intr, retry in (("right", i, True), ("held", given, False), ("retried", given, True)):
        method = dataclasses.replace(RobustConfig(), focal_retry=retry)
        res[name] = localize(model, Query(q, intr), matcher=xfeat, init_c2w=init,
                             gt_c2w=scene.gt_c2w, cameras=cams, cache_dir=False, config=method)
    right, held, retried = res["right"], res["held"], res["retried"]
    assert right.verdict.status == "ok", right.verdict.reason
    assert right.verdict.signals["focal"]["scale"] == pytest.approx(1.0, abs=0.01)
    assert "focal_retry" not in right.details and "focal_scale" not in right.details
    # the distance took up the focal length: a wrong pose by the benchmark's measure
    assert held.trans_err > 3 * right.trans_err + 0.05 * scene.scene_scale
    assert held.verdict.status == "uncertain", held.verdict.reason
    assert "focal length" in held.verdict.reason
    # the matches' refit finds the focal length (sub-pixel render keypoints: whole pixels left
    # a quarter of the error, 1.062) and explains them far better with it
    focal = held.verdict.signals["focal"]
    assert focal["scale"] == pytest.approx(1 / 0.92, abs=0.01)
    assert focal["rms_px"] < 0.5 * focal["rms_px_given"]
    assert held.details["focal_retry"] == "off"
    # the retry estimates the focal length and finds the pose
    assert retried.details["focal_retry"] == "kept", retried.verdict.reason
    first_loss, retried_loss = retried.details["focal_retry_loss"]
    assert retried_loss < first_loss  # the photo agrees better with the focal length found
    assert retried.details["focal_scale"] == pytest.approx(1 / 0.92, abs=0.01)
    assert retried.intrinsics.fx == pytest.approx(i.fx, rel=0.01)
    assert retried.rot_err_deg < 0.2
    assert retried.trans_err < 2 * right.trans_err + 0.005 * scene.scene_scale
    assert retried.verdict.status == "ok", retried.verdict.reason


def test_a_retry_that_compares_no_better_with_the_photo_is_not_kept(demo200, xfeat,
                                                                   monkeypatch):
    """The retry's pose must also compare with the photo better than the first pose.

    A refit that trades the focal length against the distance (bird's training photos) asks
    for another focal length without one being better; its retry is then not kept.
    """
    import dataclasses

    from icomma_plugin.localization import robust
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localize import localize

    real = robust.refine_photometric

    def no_better_with_the_focal_free(state, start, cfg, **kw):
        out = real(state, start, cfg, **kw)
        return dataclasses.replace(out, loss_end=1.0) if cfg.focal else out

    monkeypatch.setattr(robust, "refine_photometric", no_better_with_the_focal_free)
    scene, model, q, cams = demo200
    i = scene.intrinsics
    init = perturb_pose(scene.gt_c2w, 10.0, 0.05, 7, pivot="camera")
    given = Intrinsics(i.width, i.height, i.fx * 0.92, i.fy * 0.92, i.cx, i.cy)
    res = localize(model, Query(q, given), matcher=xfeat, init_c2w=init, gt_c2w=scene.gt_c2w,
                   cameras=cams, cache_dir=False, config=RobustConfig())
    assert res.details["focal_retry"] == "not kept"
    first, retried = res.details["focal_retry_loss"]
    assert retried == 1.0 and 0 < first < 1.0
    assert "focal_scale" not in res.details
    assert res.verdict.status == "uncertain" and "did not pass either" in res.verdict.reason


def test_empty_start_is_reported_with_what_to_do(demo, xfeat):
    """A start that looks away from the scene: relocalized from the candidates, and said so."""
    from icomma_plugin.localize import localize

    scene, model, q, cams = demo
    away = scene.gt_c2w.copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    res = localize(model, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=away,
                   gt_c2w=scene.gt_c2w, cameras=cams, cache_dir=False)
    assert res.verdict.signals["start_render_empty"] is True
    assert "start pose was empty" in res.verdict.reason
    assert res.rot_err_deg < 1.0 and res.verdict.status in ("ok", "uncertain")


# ------------------------------------------------------------------------------- end to end


@pytest.mark.parametrize("start", ["90deg", "none"])
def test_demo_end_to_end_from_90_degrees_and_from_no_start(demo, xfeat, start):
    from icomma_plugin.localize import localize

    scene, model, q, cams = demo
    init = None
    if start == "90deg":
        init = perturb_pose(scene.gt_c2w, 90.0, 0.1, 11, pivot=scene.scene_centre)
    res = localize(model, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                   gt_c2w=scene.gt_c2w, cameras=cams, cache_dir=False)
    assert res.rot_err_deg < 0.1, res.verdict
    assert res.trans_err < 0.01 * scene.scene_scale
    assert res.verdict.status == "ok", res.verdict.reason
    assert res.method == "robust" and len(res.details["hypotheses"]) >= 1
    assert set(res.stage_seconds) >= {"render", "matcher", "pnp", "other", "total"}
    j = res.to_json()
    first = "geometric" if init is not None else "candidates"
    assert j["status"] == "ok" and j["trace"][0]["stage_name"] == first


def test_default_method_needs_a_matcher_and_the_paper_needs_a_start(demo):
    from icomma_plugin.localize import LocalizerConfig, localize

    scene, model, q, _ = demo
    with pytest.raises(ValueError, match="needs a matcher"):
        localize(model, Query(q, scene.intrinsics), init_c2w=scene.gt_c2w)
    with pytest.raises(ValueError, match="needs a start pose"):
        localize(model, Query(q, scene.intrinsics), config=LocalizerConfig())


def test_features_of_the_query_are_reused_and_match_like_match(demo, xfeat):
    """extract + match_features gives the same matches as match() (the query is detected once)."""
    _, _, q, _ = demo
    a = xfeat.match(q, q)
    b = xfeat.match(q, q, features1=xfeat.extract(q))
    assert len(a) == len(b) > 50 and torch.equal(a.kpts0, b.kpts0) and torch.equal(a.kpts1, b.kpts1)
    with pytest.raises(ValueError, match="features1"):
        xfeat.match(q, q[:, :64, :64].contiguous(), features1=xfeat.extract(q))


def test_stage_seconds_are_exclusive_and_add_up(demo, monkeypatch):
    """Nested timers count once each (a fake clock: no timing in tests)."""
    from icomma_plugin.localization import state as state_mod

    clock = [100.0]
    monkeypatch.setattr(state_mod.time, "perf_counter", lambda: clock[0])
    st = _state(demo)
    with st.timed("verify"):
        clock[0] += 2.0
        with st.timed("render"):
            clock[0] += 3.0
        clock[0] += 1.0
    clock[0] += 0.5
    s = st.stage_seconds()
    assert (s["verify"], s["render"], s["other"], s["total"]) == (3.0, 3.0, 0.5, 6.5)


def test_renders_above_one_reach_the_matcher_clamped(demo, xfeat):
    """Both methods match renders of a model whose colours overshoot [0, 1] (bright SH colours).

    It stopped the paper's method with "image0 must hold values in [0, 1]"; both methods now clamp
    before matching, and the matcher finds matches on those renders.
    """
    from icomma_plugin.localize import LocalizerConfig, localize

    scene, model, q, cams = demo
    bright = model.to(dtype=torch.float32)
    bright.sh_dc = bright.sh_dc * 1.0 + 2.5  # colours well above 1 once the SH is evaluated
    st = _state(demo)
    st.model = bright
    assert float(st.render(np.linalg.inv(scene.gt_c2w)).color.max()) > 1.3
    init = perturb_pose(scene.gt_c2w, 5.0, 0.05, 4, pivot=scene.scene_centre)
    paper = localize(bright, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                     config=LocalizerConfig(max_iterations=2, converge_patience=0))
    assert paper.iterations == 2 and max(r.matches for r in paper.trace) > 0
    default = localize(bright, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                       cameras=cams, cache_dir=False)
    geometric = [r for r in default.trace if r.stage == Stage.GEOMETRIC]
    assert geometric and max(r.matches for r in geometric) > 0


def test_a_photo_sharper_than_the_model_is_worked_at_the_model_resolution(demo, xfeat):
    from icomma_plugin.localize import localize
    from icomma_plugin.localization.types import resize_image

    scene, model, q, cams = demo
    big = resize_image(q, 200, 200).clamp(0, 1)
    intr = scene.intrinsics.scaled(2.0)
    init = perturb_pose(scene.gt_c2w, 10.0, 0.05, 8, pivot=scene.scene_centre)
    res = localize(model, Query(big, intr), matcher=xfeat, init_c2w=init, gt_c2w=scene.gt_c2w,
                   cameras=cams, model_side=100, cache_dir=False)
    scales = {r.scale for r in res.trace if r.stage == Stage.GEOMETRIC}
    assert scales == {0.5} and res.config["work_side"] == 100
    assert res.rot_err_deg < 0.5 and res.verdict.status == "ok"


def test_above_the_model_resolution_poses_are_judged_in_the_model_pixels():
    from icomma_plugin.camera import Intrinsics
    from icomma_plugin.localization.refine import RefineConfig
    from icomma_plugin.localization.robust import RobustConfig

    intr = Intrinsics(800, 600, 700.0, 700.0)
    cfg = RobustConfig(work_side=800)
    at = cfg.at_model_side(intr, 200)  # 4x the model's side: its pixels are 4 of ours
    v = at.verdict
    assert (v.inlier_px, v.ok_median_px, v.ok_mean_px) == pytest.approx((8.0, 4.0, 3.2))
    assert at.geometric.inlier_px == 8.0 and at.rollback_median_px == 2.0
    # counts, shares and everything else stay; the caller's config is untouched
    assert at.verdict.ok_inliers == cfg.verdict.ok_inliers and at.verdict.ok_ratio == 0.5
    assert at.geometric.ransac_px == cfg.geometric.ransac_px and at.work_side == 800
    assert cfg.verdict.inlier_px == 2.0 and cfg.geometric.inlier_px == 2.0
    # the refinement compares in the model's pixels (its levels / 4), unless told not to
    assert at.refine.scales == (0.25,) and cfg.refine.scales == (1.0,)
    assert at.refine.iterations == cfg.refine.iterations and at.refine.blur == cfg.refine.blur
    off = RobustConfig(work_side=800, refine_model_side=False).at_model_side(intr, 200)
    assert off.refine == cfg.refine and off.verdict == at.verdict
    two = RobustConfig(work_side=800, refine=RefineConfig(scales=(0.5, 1.0), blur=(1.0, 0.0),
                                                          iterations=(2, 3)))
    assert two.at_model_side(intr, 200).refine.scales == (0.125, 0.25)
    with pytest.raises(ValueError, match="refine_model_side"):
        RobustConfig(refine_model_side="yes")
    # at or below the model's side nothing changes; without a work side it works at the model's
    assert RobustConfig(work_side=200).at_model_side(intr, 200) == RobustConfig(work_side=200)
    assert RobustConfig(work_side=100).at_model_side(intr, 200) == RobustConfig(work_side=100)
    assert RobustConfig().at_model_side(intr, 200) == RobustConfig(work_side=200)
    assert RobustConfig(work_side=800).at_model_side(intr, None) == cfg


def test_above_the_model_resolution_the_refinement_compares_in_the_model_pixels(demo, xfeat):
    """Worked at 2x the model's side: the refinement renders at the model's side.

    That is scale 0.5 of the query; the geometric stage and the verification stay at the working
    side.
    """
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localization.types import resize_image
    from icomma_plugin.localize import localize

    scene, model, q, _ = demo
    big = resize_image(q, 200, 200).clamp(0, 1)
    intr = scene.intrinsics.scaled(2.0)
    init = perturb_pose(scene.gt_c2w, 5.0, 0.02, 8, pivot=scene.scene_centre)
    runs = {}
    for at_model in (True, False):
        cfg = RobustConfig(work_side=200, use_candidates=False, refine_model_side=at_model)
        res = localize(model, Query(big, intr), matcher=xfeat, config=cfg, init_c2w=init,
                       gt_c2w=scene.gt_c2w, model_side=100)
        scales = {stage: {r.scale for r in res.trace if r.stage == stage}
                  for stage in (Stage.GEOMETRIC, Stage.REFINE, Stage.VERIFY)}
        assert scales[Stage.GEOMETRIC] == {1.0} and scales[Stage.VERIFY] == {1.0}
        assert scales[Stage.REFINE] == ({0.5} if at_model else {1.0})
        runs[at_model] = res
    # The query is the 100-px photo enlarged: compared at 200 px the pose drifted 0.55-0.65 deg
    # (4 starts); in the model's pixels it ends 0.10 deg off (0.28-0.46 after the PnP).
    assert runs[True].rot_err_deg < 0.25 < runs[False].rot_err_deg
    assert runs[True].verdict.status == "ok", runs[True].verdict.reason
    assert list(runs[True].config["refine"]["scales"]) == [1.0]  # as given: it runs the same


def test_a_wrong_pose_is_not_ok_in_the_model_pixels_and_the_truth_is(demo, xfeat):
    """Worked at 2x the model's side: the scaled thresholds still tell a 1-degree error."""
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localization.types import resize_image

    scene, model, q, _ = demo
    big = resize_image(q, 200, 200).clamp(0, 1)
    intr = scene.intrinsics.scaled(2.0)
    cfg = RobustConfig(work_side=200).at_model_side(intr, 100)
    st = LocalizationState(model, Query(big, intr), torch.zeros(3), matcher=xfeat)
    px = cfg.geometric.inlier_px

    def verdict(c2w):
        return decide(score_observation(st.observe(np.linalg.inv(c2w)), st, px), cfg.verdict,
                      converged=True)

    for deg, seed in ((1.0, 3), (3.0, 5)):  # turned about the camera: the view moves by ~deg * fx
        wrong = verdict(perturb_pose(scene.gt_c2w, deg, 0.0, seed))
        assert wrong.status != "ok", (deg, wrong.reason)
    right = verdict(scene.gt_c2w)
    assert right.status == "ok", right.reason


def test_a_result_records_the_config_that_runs_the_same_again(demo, xfeat):
    """Above the model's side the result's config holds the thresholds as given, not scaled.

    Copied into a new run it is scaled there once more, the same way: the same pose and verdict.
    """
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localization.types import resize_image
    from icomma_plugin.localize import localize

    scene, model, q, _ = demo
    big = resize_image(q, 200, 200).clamp(0, 1)
    intr = scene.intrinsics.scaled(2.0)
    init = perturb_pose(scene.gt_c2w, 5.0, 0.02, 8, pivot=scene.scene_centre)
    cfg = RobustConfig(work_side=200, use_candidates=False)
    first = localize(model, Query(big, intr), matcher=xfeat, config=cfg, init_c2w=init,
                     gt_c2w=scene.gt_c2w, model_side=100)
    assert first.config["verdict"] == RobustConfig().to_dict()["verdict"]
    assert first.config["geometric"]["inlier_px"] == cfg.geometric.inlier_px
    assert first.config["rollback_median_px"] == cfg.rollback_median_px
    again = localize(model, Query(big, intr), matcher=xfeat,
                     config=RobustConfig.from_dict(first.config), init_c2w=init,
                     gt_c2w=scene.gt_c2w, model_side=100)
    assert again.config == first.config and again.verdict.status == first.verdict.status
    np.testing.assert_allclose(again.c2w, first.c2w, atol=1e-9)
    # without a work side the model's is recorded
    res = localize(model, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                   config=RobustConfig(use_candidates=False), model_side=100)
    assert res.config["work_side"] == 100


def test_the_paper_method_too_works_at_the_model_resolution(demo, xfeat):
    from icomma_plugin.localize import LocalizerConfig, localize
    from icomma_plugin.localization.types import resize_image

    scene, model, q, _ = demo
    big = resize_image(q, 200, 200).clamp(0, 1)
    intr = scene.intrinsics.scaled(2.0)
    init = perturb_pose(scene.gt_c2w, 5.0, 0.02, 8, pivot=scene.scene_centre)
    cfg = LocalizerConfig(max_iterations=3)
    res = localize(model, Query(big, intr), matcher=xfeat, config=cfg, init_c2w=init,
                   gt_c2w=scene.gt_c2w, model_side=100)
    assert res.config["image_scale"] == 0.5 and cfg.image_scale == 1.0  # the caller's is untouched
    # an explicit working scale is kept
    res = localize(model, Query(big, intr), matcher=xfeat, init_c2w=init, model_side=100,
                   config=LocalizerConfig(max_iterations=2, image_scale=0.25))
    assert res.config["image_scale"] == 0.25


# ------------------------------------------------------------------------------ the cheap mode
def test_mutual_nn_matches_an_image_to_itself_keypoint_for_keypoint(demo, xfeat):
    from icomma_plugin.matchers import mutual_nn, mutual_nn_count

    _, _, q, _ = demo
    f = xfeat.extract(q)
    m = mutual_nn(f, f, 0.82)
    assert len(m) == len(f) > 50 and mutual_nn_count(f, f, 0.82) == len(m)
    assert torch.equal(m.kpts0, m.kpts1) and float(m.confidence.min()) > 0.99
    shifted = xfeat.extract(torch.roll(q, 3, dims=2))
    assert len(mutual_nn(f, shifted, 0.999)) < len(mutual_nn(f, shifted, 0.82))


def test_the_cheap_mode_matches_by_mutual_nn_and_judges_on_the_geometric_render(
        demo, xfeat, monkeypatch):
    """Tracking's fast config: no LightGlue pass, and one render-and-match fewer a pose."""
    import dataclasses

    from icomma_plugin.localization.refine import RefineConfig
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localize import localize

    scene, model, q, _ = demo
    init = perturb_pose(scene.gt_c2w, 0.5, 0.002, 3, pivot=scene.scene_centre)
    calls = {"glue": 0, "mnn": 0}
    glue, mnn = xfeat._match_features, xfeat.match_mutual_nn

    def count(name, fn):
        def wrapped(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(xfeat, "_match_features", count("glue", glue))
    monkeypatch.setattr(xfeat, "match_mutual_nn", count("mnn", mnn))
    cheap = RobustConfig(use_candidates=False, mutual_nn=0.82, verify_geometric=True,
                         refine=RefineConfig(iterations=(0,)))
    runs = {}
    for verify_geometric in (True, False):
        calls.update(glue=0, mnn=0)
        cfg = dataclasses.replace(cheap, verify_geometric=verify_geometric,
                                  verify_near=verify_geometric)
        res = localize(model, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                       gt_c2w=scene.gt_c2w, config=cfg, cache_dir=False)
        assert calls["glue"] == 0, "the cheap mode ran LightGlue"
        assert res.verdict.status == "ok" and res.rot_err_deg < 0.2, res.verdict.reason
        rounds = res.details["hypotheses"][0]["rounds"]
        runs[verify_geometric] = (res, calls["mnn"], rounds)
    (res_g, n_g, rounds_g), (res_f, n_f, rounds_f) = runs[True], runs[False]
    assert res_g.details["verified_on"] == "geometric" and res_f.details["verified_on"] == "final"
    assert rounds_g == rounds_f and n_g == rounds_g and n_f == rounds_f + 1
    np.testing.assert_allclose(res_g.c2w, res_f.c2w)  # the verdict's render moves no pose


def test_mutual_nn_is_checked_and_needs_a_matcher_with_descriptors(demo):
    from icomma_plugin.app.tracking import TrackingConfig
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.matchers import make_matcher

    for bad in (0.0, 1.0, 2, "high"):
        with pytest.raises(ValueError, match="mutual_nn"):
            RobustConfig(mutual_nn=bad)
    loftr_like = type("Dense", (), {"name": "dense", "supports_features": False})()
    assert "mutual_nn" in RobustConfig(mutual_nn=0.8).needs(loftr_like)
    assert RobustConfig().needs(loftr_like) is None
    fast = TrackingConfig().fast_method(RobustConfig(), 200, make_matcher("xfeat"))
    assert fast.mutual_nn == 0.82 and fast.verify_geometric and not fast.use_candidates
    assert fast.geometric.subpixel_iterations == 0 and RobustConfig().geometric.subpixel_iterations
    with pytest.raises(ValueError, match="fast_subpixel_iterations"):
        TrackingConfig(fast_subpixel_iterations=-1)
    assert TrackingConfig().fast_method(RobustConfig(), 200, loftr_like).mutual_nn is None
    assert TrackingConfig(fast_mutual_nn=None).fast_method(
        RobustConfig(), 200, make_matcher("xfeat")).mutual_nn is None


# ----------------------------------------------------------- the cheap mode's patch search
def test_patch_search_finds_a_known_sub_pixel_shift_and_marks_its_matches_sub_pixel():
    import torch.nn.functional as F

    from icomma_plugin.matchers import patch_search

    torch.manual_seed(0)
    query = F.avg_pool2d(torch.rand(1, 3, 120, 120), 5, 1, 2)[0]  # smooth random texture
    shift = torch.tensor([1.3, -0.6])  # the render shows the query moved by this
    ys, xs = torch.meshgrid(torch.arange(120.0), torch.arange(120.0), indexing="ij")
    grid = torch.stack([(xs - shift[0]) / 59.5 - 1, (ys - shift[1]) / 59.5 - 1], -1)
    render = F.grid_sample(query[None], grid[None], align_corners=True,
                           padding_mode="border")[0]
    k1 = torch.stack(torch.meshgrid(torch.arange(20.0, 100.0, 8), torch.arange(20.0, 100.0, 8),
                                    indexing="xy"), -1).reshape(-1, 2)
    m = patch_search(render, query, k1, window=3, min_ncc=0.8)
    assert m.subpixel and len(m) > 0.9 * len(k1)
    err = (m.kpts0 - m.kpts1 - shift).norm(dim=-1)
    assert float(err.median()) < 0.1 and float(err.max()) < 0.3, err  # integer search alone: 0.5
    assert m.select(m.confidence > 0.9).subpixel and m.to(dtype=torch.float64).subpixel
    assert not m.select(torch.arange(0)).kpts0.shape[0]
    # a render further off than the window: the right displacement is out of its reach
    far = torch.roll(render, 7, dims=2)
    m_far = patch_search(far, query, k1, window=3, min_ncc=0.8)
    assert len(m_far) == 0 or float((m_far.kpts0 - m_far.kpts1).norm(dim=-1).median()) > 1.5
    for bad in ({"window": 0}, {"min_ncc": 2.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            patch_search(render, query, k1, **bad)


def test_patch_search_margin_drops_keypoints_on_a_flat_surface():
    """Flat patches stay put and "agree" with any render: the margin drops them.

    On the textured half the NCC peak stands out and its keypoints are kept.
    """
    import torch.nn.functional as F

    from icomma_plugin.matchers import patch_search
    from icomma_plugin.matchers.refine import peak_margin, refine_render_keypoints

    torch.manual_seed(1)
    query = F.avg_pool2d(torch.rand(1, 3, 120, 120), 5, 1, 2)[0]
    ramp = torch.linspace(0.2, 0.8, 120).view(1, 1, 120)
    query[:, :, 60:] = ramp[..., 60:] + 0.002 * query[:, :, 60:]  # right half: a soft ramp
    render = torch.roll(query, 1, dims=2)  # the render shows it moved by 1 px
    k1 = torch.stack(torch.meshgrid(torch.arange(15.0, 106.0, 10),
                                    torch.arange(15.0, 106.0, 10), indexing="xy"), -1
                     ).reshape(-1, 2)
    textured, flat = k1[:, 0] < 50, k1[:, 0] > 70  # (patches of the columns between see both)
    _, _, margin = refine_render_keypoints(render, query, k1.clone(), k1, window=2,
                                           iterations=0, return_score=True, return_margin=True)
    assert float(margin[textured].min()) > 0.07 and float(margin[flat].max()) < 0.01, margin
    kept = patch_search(render, query, k1, window=2, min_ncc=0.5, min_margin=0.05)
    x = kept.kpts1[:, 0]
    assert int((x < 50).sum()) == int(textured.sum()) and not bool((x > 70).any())
    assert float((kept.kpts0 - kept.kpts1 - torch.tensor([1.0, 0.0])).norm(dim=-1).max()) < 0.2
    assert len(patch_search(render, query, k1, window=2, min_ncc=0.5)) > len(kept)
    # the margin itself: the best score less the best one 2 px or more away
    disp = torch.tensor([[-2.0, 0.0], [-1.0, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    ncc = torch.tensor([[0.1, 0.6, 0.9, 0.5, 0.3], [0.85, 0.2, 0.9, 0.89, 0.1]])
    torch.testing.assert_close(peak_margin(ncc, disp, ncc.argmax(-1)),
                               torch.tensor([0.6, 0.05]))
    with pytest.raises(ValueError, match="min_margin"):
        patch_search(render, query, k1, min_margin=-0.1)


def _cheap_mode_calls(demo, xfeat, monkeypatch, start_deg, seed):
    """The cheap mode with the patch search from ``start_deg`` off: (result, calls made)."""
    import icomma_plugin.matchers.refine as refine_mod
    from icomma_plugin.app.tracking import TrackingConfig
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localize import localize

    scene, model, q, _ = demo
    init = perturb_pose(scene.gt_c2w, start_deg, 0.0, seed, pivot="camera")
    calls = {"extract": 0, "mnn": 0, "pnp_subpixel": 0}

    def count(name, fn):
        def wrapped(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(xfeat, "extract", count("extract", xfeat.extract))
    monkeypatch.setattr(xfeat, "match_mutual_nn", count("mnn", xfeat.match_mutual_nn))
    # the PnP's sub-pixel step imports it from the module when it runs (the patch search holds
    # its own reference): counted here are the PnP's calls alone
    monkeypatch.setattr(refine_mod, "refine_render_keypoints",
                        count("pnp_subpixel", refine_mod.refine_render_keypoints))
    cheap = TrackingConfig(fast_patch_search=2).fast_method(RobustConfig(), 100, xfeat)
    assert cheap.patch_search == 2
    res = localize(model, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                   gt_c2w=scene.gt_c2w, config=cheap, cache_dir=False)
    return res, calls


def test_the_cheap_mode_near_the_pose_extracts_the_query_alone(demo, xfeat, monkeypatch):
    """A prediction a fraction of a degree off: no render features, no second sub-pixel step."""
    res, calls = _cheap_mode_calls(demo, xfeat, monkeypatch, 0.3, 4)
    assert res.verdict.status == "ok" and res.rot_err_deg < 0.1, (res.rot_err_deg,
                                                                  res.verdict.reason)
    assert calls == {"extract": 1, "mnn": 0, "pnp_subpixel": 0}, calls
    assert res.details["patch_search"]["fell_back"] == 0 < res.details["patch_search"]["matched"]


def test_the_cheap_mode_far_from_the_pose_matches_by_descriptors(demo, xfeat, monkeypatch):
    """A render further off than the window is matched by descriptors, and no wrong pose is ok."""
    res, calls = _cheap_mode_calls(demo, xfeat, monkeypatch, 6.0, 5)
    assert calls["mnn"] >= 1 and calls["extract"] >= 2, calls
    assert res.details["patch_search"]["fell_back"] >= 1
    assert res.verdict.status != "ok" or res.rot_err_deg < 0.3, (res.rot_err_deg,
                                                                   res.verdict.reason)


def test_patch_search_is_checked_and_needs_a_matcher_with_keypoints(demo, xfeat):
    from icomma_plugin.app.tracking import TrackingConfig
    from icomma_plugin.localization.robust import RobustConfig

    for bad in (0, -2, 1.5, "wide"):
        with pytest.raises(ValueError, match="patch_search"):
            RobustConfig(patch_search=bad)
    with pytest.raises(ValueError, match="patch_search_ncc"):
        RobustConfig(patch_search_ncc=1.5)
    with pytest.raises(ValueError, match="fast_patch_search"):
        TrackingConfig(fast_patch_search=0)
    with pytest.raises(ValueError, match="patch_search_margin"):
        RobustConfig(patch_search_margin=-0.5)
    with pytest.raises(ValueError, match="fast_patch_margin"):
        TrackingConfig(fast_patch_margin="sharp")
    assert TrackingConfig(fast_patch_search=2, fast_patch_margin=0.1).fast_method(
        RobustConfig(), 200, xfeat).patch_search_margin == 0.1
    loftr_like = type("Dense", (), {"name": "dense", "supports_features": False})()
    assert "patch_search" in RobustConfig(patch_search=3).needs(loftr_like)
    assert TrackingConfig(fast_patch_search=2).fast_method(
        RobustConfig(), 200, loftr_like).patch_search is None
    # off by default: on photo collections and soft models it falls back more than it serves
    assert TrackingConfig().fast_method(RobustConfig(), 200, xfeat).patch_search is None
    assert TrackingConfig(fast_patch_search=None).fast_method(
        RobustConfig(), 200, xfeat).patch_search is None


# ------------------------------------------------------------------------------ the focal length


def _jacobian_1deg_off(demo, cfg, seed: int, focal_scale: float = 1.0, rng=(0.5, 2.0)):
    """The demo 1 deg off its truth: (state, w2c, backward gradient, render, mask, Jacobian).

    Of the exposure-profiled loss (gain range ``rng``), the focal length scaled by
    ``focal_scale``; the Jacobian by ``cfg``'s forward differences.
    """
    from icomma_plugin.localization.refine import _evaluate, _fd_jacobian

    st = _state(demo)
    st.focal_scale = focal_scale
    w2c = np.linalg.inv(perturb_pose(demo[0].gt_c2w, 1.0, 0.01, seed, pivot="camera"))
    _, grad, out, mask = _evaluate(st, w2c, 1.0, None, None, exposure_gain=rng)
    jac = _fd_jacobian(st, cfg, w2c, 1.0, out, mask, 0.0, torch.ones(3, dtype=torch.float64),
                       st.query_at(1.0).rgb, own_render=False)
    return st, w2c, grad, out, mask, jac


def test_the_focal_gradient_matches_finite_differences_of_the_loss(demo):
    """The Gauss-Newton gradient along the focal length's log against central differences.

    Of the exposure-profiled loss, at a pose 1 deg off and a focal length 3 % off the query's.
    """
    from icomma_plugin.localization.refine import RefineConfig, _evaluate, _jacobian_gradient

    rng = (0.5, 2.0)
    st, w2c, _, out, mask, jac = _jacobian_1deg_off(demo, RefineConfig(focal=True), 4, 1.03, rng)
    assert jac.J.shape[1] == 7 and st.focal_scale == 1.03  # the column's render is undone
    whole = _jacobian_gradient(jac, out.color, rng)
    g = float(_jacobian_gradient(jac, out.color, rng, first=6)[0])  # the refinement's call
    assert g == pytest.approx(float(whole[6]), rel=1e-6)  # the focal column alone, as in all 7
    h, val = 1e-3, []
    for sign in (1.0, -1.0):
        st.focal_scale = 1.03 * np.exp(sign * h)
        val.append(_evaluate(st, w2c, 1.0, mask, None, want_grad=False, exposure_gain=rng)[0])
    fd = (val[0] - val[1]) / (2 * h)
    assert abs(fd) > 1e-5 and g == pytest.approx(fd, rel=0.1), (g, fd)


def test_the_pose_gradient_against_central_differences_of_the_loss(demo):
    """The backward pass's and the Jacobian's pose gradients against the loss's differences.

    The forward-difference Jacobian's (a step of 1e-4) is within 5 % of them at its own render;
    the rasterizer's backward pass within 8 %: it leaves out where the Gaussians' footprints are
    cut off, which the loss's differences see (gaussian_renderer_pose/DESIGN.md, "Gradients").
    """
    from icomma_plugin.localization.refine import RefineConfig, _evaluate, _jacobian_gradient
    from icomma_plugin.pose import se3_exp

    rng = (0.5, 2.0)
    st, w2c, grad, out, mask, jac = _jacobian_1deg_off(demo, RefineConfig(fd_step=1e-4), 5)
    g = _jacobian_gradient(jac, out.color, rng)
    assert g.shape == (6,) and g.dtype == torch.float64
    h, central = 3e-4, torch.zeros(6, dtype=torch.float64)
    for k in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[k] = h
        val = [_evaluate(st, (se3_exp(s * e) @ torch.as_tensor(w2c)).numpy(), 1.0, mask, None,
                         want_grad=False, exposure_gain=rng)[0] for s in (1.0, -1.0)]
        central[k] = (val[0] - val[1]) / (2 * h)
    assert float((g - central).norm() / central.norm()) < 0.05, (g, central)
    assert float((grad - central).norm() / central.norm()) < 0.08, (grad, central)


def test_with_the_focal_length_free_a_wrong_one_is_corrected(demo):
    """A query whose given focal length is 4 % short: the pose is off with it fixed, not free."""
    from icomma_plugin.localization.refine import RefineConfig, refine_photometric

    scene, _, q, _ = demo
    i = scene.intrinsics
    wrong = Query(q, Intrinsics(i.width, i.height, i.fx * 0.96, i.fy * 0.96, i.cx, i.cy))
    start = np.linalg.inv(perturb_pose(scene.gt_c2w, 0.5, 0.005, 2, pivot="camera"))
    errors = {}
    for focal in (False, True):
        st = LocalizationState(scene.load_model(), wrong, torch.zeros(3), gt_c2w=scene.gt_c2w)
        out = refine_photometric(st, start, RefineConfig(focal=focal), scene_depth=4.0)
        errors[focal] = float(rotation_error_deg(np.linalg.inv(out.w2c), scene.gt_c2w))
        if focal:
            assert out.focal_scale == pytest.approx(1 / 0.96, abs=0.01)
            assert st.intrinsics_at(1.0).fx == pytest.approx(i.fx * 0.96 * out.focal_scale)
        else:
            assert out.focal_scale == 1.0
    assert errors[True] < 0.1 and errors[True] < 0.5 * errors[False], errors


def test_a_bad_focal_setting_is_one_error_naming_it():
    from icomma_plugin.localization.refine import RefineConfig

    with pytest.raises(ValueError, match="RefineConfig.focal needs"):
        RefineConfig(focal=True, hessian="motion_field")
    with pytest.raises(ValueError, match="RefineConfig.focal needs"):
        RefineConfig(focal=True, robust="cauchy")
    with pytest.raises(ValueError, match="RefineConfig.focal must be"):
        RefineConfig(focal="yes")


def test_the_matches_reprojection_recovers_a_known_focal_length():
    """``fit_pose_and_focal``: points seen at a known pose by a camera 5 % longer than given."""
    from icomma_plugin.localization.geometry import fit_pose_and_focal, project

    rng = np.random.default_rng(3)
    X = rng.uniform(-1.0, 1.0, (300, 3)) * [1.0, 1.0, 0.8]
    truth_c2w = look_at_c2w(np.array([0.3, -3.5, 1.0]), np.zeros(3))
    given = Intrinsics(200, 150, 180.0, 180.0)
    true_intr = Intrinsics(200, 150, 189.0, 189.0)
    x, _ = project(X, np.linalg.inv(truth_c2w), true_intr)
    x = x + rng.normal(0.0, 0.2, x.shape)
    start = np.linalg.inv(perturb_pose(truth_c2w, 0.5, 0.02, 5, pivot="camera"))
    free = fit_pose_and_focal(X, x, start, given, threshold_px=50.0)
    assert free.focal_scale == pytest.approx(1.05, abs=0.005) and free.median_px < 0.5
    assert free.rms_px < 0.5
    assert rotation_error_deg(np.linalg.inv(free.w2c), truth_c2w) < 0.05
    # the pose alone makes up for the focal length only in part, with a wrong distance
    fixed = fit_pose_and_focal(X, x, start, given, 50.0, max_log_focal=0.0)
    assert fixed.focal_scale == 1.0 and fixed.median_px > 1.3 * free.median_px
    assert fixed.rms_px > 1.3 * free.rms_px
    w2c_fixed = fixed.w2c
    distance = np.linalg.norm(truth_c2w[:3, 3])
    assert np.linalg.norm(np.linalg.inv(w2c_fixed)[:3, 3] - truth_c2w[:3, 3]) > 0.03 * distance
    assert fit_pose_and_focal(X[:5], x[:5], start, given, 50.0) is None  # too few


def test_the_focal_fit_ends_where_the_reprojection_error_is_stationary():
    """Finite differences of the cost the fit minimises vanish at its result (Jacobian check)."""
    import torch

    from icomma_plugin.localization.geometry import fit_pose_and_focal, project
    from icomma_plugin.pose.se3 import se3_exp

    rng = np.random.default_rng(4)
    X = rng.uniform(-1.0, 1.0, (200, 3))
    truth_c2w = look_at_c2w(np.array([-1.0, -3.0, 1.5]), np.zeros(3))
    given = Intrinsics(160, 120, 150.0, 150.0)
    x, _ = project(X, np.linalg.inv(truth_c2w), given.with_focal_scale(0.96))
    x = x + rng.normal(0.0, 0.3, x.shape)
    start = np.linalg.inv(perturb_pose(truth_c2w, 1.0, 0.05, 8, pivot="camera"))

    def cost(w2c, p):  # a camera-frame twist and a log focal step from (w2c, scale)
        T = se3_exp(torch.as_tensor(p[:6], dtype=torch.float64)).numpy() @ w2c
        return float(((project(X, T, given.with_focal_scale(s * np.exp(p[6])))[0] - x) ** 2).sum())

    def grad(w2c):
        g = np.empty(7)
        for k in range(7):
            e = np.zeros(7)
            e[k] = 1e-6
            g[k] = (cost(w2c, e) - cost(w2c, -e)) / 2e-6
        return g

    s = 1.0
    g_start = grad(start)
    fit = fit_pose_and_focal(X, x, start, given, threshold_px=1e3)
    s = fit.focal_scale
    g_end = grad(fit.w2c)
    assert np.abs(g_end).max() < 1e-4 * np.abs(g_start).max(), (g_start, g_end)
    assert fit.focal_scale == pytest.approx(0.96, abs=0.005)


def _near_runs(demo, xfeat, monkeypatch, configs, refine_move_deg=0.0):
    """Localize the demo from 20 deg off with each config: [(result, LightGlue calls)].

    ``refine_move_deg``: the refinement's pose turned by that much more (about the camera).
    """
    from icomma_plugin.localization import robust
    from icomma_plugin.localize import localize

    scene, model, q, cams = demo
    init = perturb_pose(scene.gt_c2w, 20.0, 0.05, 5, pivot="camera")
    calls = {"glue": 0}
    glue = xfeat._match_features

    def counted(*a, **k):
        calls["glue"] += 1
        return glue(*a, **k)

    monkeypatch.setattr(xfeat, "_match_features", counted)
    if refine_move_deg:
        refine = robust.refine_photometric

        def moved(*a, **k):
            import dataclasses

            out = refine(*a, **k)
            c2w = perturb_pose(np.linalg.inv(out.w2c), refine_move_deg, 0.0, 1, pivot="camera")
            return dataclasses.replace(out, w2c=np.linalg.inv(c2w), observation=None)

        monkeypatch.setattr(robust, "refine_photometric", moved)
    runs = []
    for cfg in configs:
        calls["glue"] = 0
        res = localize(model, Query(q, scene.intrinsics), matcher=xfeat, init_c2w=init,
                       gt_c2w=scene.gt_c2w, cameras=cams, cache_dir=False, config=cfg)
        runs.append((res, calls["glue"]))
    return runs


def test_a_refined_pose_near_an_ok_geometric_render_is_judged_on_it(demo, xfeat, monkeypatch):
    """``verify_near``: one matcher call fewer, the same pose and verdict, the same signals."""
    from icomma_plugin.localization.robust import RobustConfig

    (near, n_near), (final, n_final) = _near_runs(
        demo, xfeat, monkeypatch, [RobustConfig(), RobustConfig(verify_near=False)])
    assert near.details["verified_on"] == "geometric"
    assert final.details["verified_on"] == "final"
    assert n_near == n_final - 1  # the matcher's call at the returned pose
    np.testing.assert_array_equal(near.c2w, final.c2w)  # the verdict's render moves no pose
    assert near.verdict.status == final.verdict.status == "ok", near.verdict.reason
    assert near.rot_err_deg < 0.1
    # judged on the geometric stage's best render: its score is the one the verdict reads
    best = max(near.details["hypotheses"], key=lambda h: h["score"]["inliers"])
    assert near.verdict.signals["inliers"] == best["score"]["inliers"]
    verify = [r for r in near.trace if r["stage_name"] == "verify"]
    assert len(verify) == 1 and verify[0]["accepted"] and verify[0]["inliers"] == best["score"][
        "inliers"]


def test_a_refinement_that_moved_past_the_stop_gets_its_own_render_and_match(
        demo, xfeat, monkeypatch):
    """Moved further than ``geometric.stop_rot_deg`` from that render: checked as before."""
    from icomma_plugin.localization.robust import RobustConfig

    cfg = RobustConfig()
    (res, n), = _near_runs(demo, xfeat, monkeypatch, [cfg],
                           refine_move_deg=2 * cfg.geometric.stop_rot_deg)
    assert res.details["verified_on"] == "final"
    # the turned pose is checked by its own render, so the roll-back can see it
    verify = [r for r in res.trace if r["stage_name"] == "verify"]
    assert len(verify) == 1 and verify[0]["inliers"] != res.details["hypotheses"][0]["score"][
        "inliers"] or res.details["rolled_back"]


def test_a_geometric_render_not_ok_alone_decides_no_verdict(demo, xfeat, monkeypatch):
    """A render whose score alone is not ``ok`` (here: a mean displacement asked below any)."""
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localization.verify import VerdictConfig

    strict = RobustConfig(verdict=VerdictConfig(ok_mean_px=1e-6, ok_median_px=1e-6))
    (res, _), = _near_runs(demo, xfeat, monkeypatch, [strict])
    assert res.details["verified_on"] == "final"
    assert res.verdict.status == "uncertain"


def test_a_pose_moved_by_the_focal_fit_is_judged_on_its_own_render(demo200, xfeat):
    """``verify_geometric`` with no refinement step: the geometric render is reused if its pose.

    Not when the matches' focal fit moved the pose and the focal length off that render's.
    """
    from icomma_plugin.localization.refine import RefineConfig
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localize import localize

    scene, model, q, cams = demo200
    i = scene.intrinsics
    init = perturb_pose(scene.gt_c2w, 10.0, 0.05, 7, pivot="camera")
    wrong = Intrinsics(i.width, i.height, i.fx * 0.92, i.fy * 0.92, i.cx, i.cy)
    res = {}
    for name, intr in (("right", i), ("wrong", wrong)):
        cfg = RobustConfig(verify_geometric=True, focal_retry=False,
                           refine=RefineConfig(focal=True, iterations=(0,)))
        res[name] = localize(model, Query(q, intr), matcher=xfeat, init_c2w=init,
                             gt_c2w=scene.gt_c2w, cameras=cams, cache_dir=False, config=cfg)
    right, moved = res["right"], res["wrong"]
    assert right.details["refine_iterations"] == 0 and right.details["focal_scale"] == 1.0
    assert right.details["verified_on"] == "geometric"  # the fit was not taken: reused
    assert moved.details["focal_scale"] > 1.03  # the matches' fit was taken
    assert moved.details["verified_on"] == "final", moved.details
    # judged at the fitted focal length: its matches ask for the rest of the way to the truth
    found = moved.verdict.signals["focal"]["scale"] * moved.details["focal_scale"]
    assert found == pytest.approx(1 / 0.92, abs=0.02)


def test_a_localization_with_the_focal_length_free_finds_it(demo, xfeat):
    """The demo query given 4 % too short a focal length, localized from 10 deg off."""
    from icomma_plugin.localization.refine import RefineConfig
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localize import localize

    scene, model, q, cams = demo
    i = scene.intrinsics
    wrong = Intrinsics(i.width, i.height, i.fx * 0.96, i.fy * 0.96, i.cx, i.cy)
    init = perturb_pose(scene.gt_c2w, 10.0, 0.05, 7, pivot="camera")
    res = {}
    for focal in (False, True):
        res[focal] = localize(model, Query(q, wrong), matcher=xfeat, init_c2w=init,
                              gt_c2w=scene.gt_c2w, cameras=cams, cache_dir=False,
                              config=RobustConfig(refine=RefineConfig(focal=focal),
                                                  focal_retry=False))
    free = res[True]
    assert free.details["focal_scale"] == pytest.approx(1 / 0.96, abs=0.01)
    assert free.intrinsics.fx == pytest.approx(i.fx, rel=0.01)
    assert "focal_scale" not in res[False].details and res[False].intrinsics == wrong
    assert free.rot_err_deg < 0.1 and free.rot_err_deg < 0.5 * res[False].rot_err_deg, \
        (free.rot_err_deg, res[False].rot_err_deg)
