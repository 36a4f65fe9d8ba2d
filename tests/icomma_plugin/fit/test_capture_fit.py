"""Fitting photographed captures (issue 18).

Exposure, far field, initial points, coarse-to-fine, distance-scaled thresholds, the grid.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.fit import (
    ExposureState,
    FitConfig,
    FitView,
    GaussianTrainState,
    Trainer,
    far_field_points,
    fit_affine_colour,
    initial_points,
    model_from_points,
    write_grid,
)
from icomma_plugin.fit.evaluate import photo_psnrs
from icomma_plugin.fit.exposure import NeighbourExposure, apply_affine_colour
from icomma_plugin.fit.init import fibonacci_sphere
from icomma_plugin.fit.losses import photometric_loss
from icomma_plugin.gaussians import GaussianModel, rgb_to_sh
from tests.helpers.geometry import look_at_c2w
from tests.helpers.images import write_png

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _ring_w2c(n, radius=3.0):
    return [np.linalg.inv(look_at_c2w((radius * math.cos(2 * math.pi * k / n),
                                       radius * math.sin(2 * math.pi * k / n), 0.4)))
            for k in range(n)]


def _view(name, image, w2c, size):
    intr = Intrinsics(size, size, size * 1.1, size * 1.1)
    return FitView(name, image, intr, torch.as_tensor(w2c, dtype=torch.float32))


# ------------------------------------------------------------------------------------ exposure
def test_exposure_backward_matches_autograd():
    torch.manual_seed(0)
    st = ExposureState(3, dtype=torch.float64)
    with torch.no_grad():
        st.params.add_(0.1 * torch.randn_like(st.params))
    img = torch.rand(3, 9, 7, dtype=torch.float64, requires_grad=True)
    gt = torch.rand(3, 9, 7, dtype=torch.float64)
    E = st.params.detach()[1].clone().requires_grad_(True)
    loss = photometric_loss(apply_affine_colour(E, img), gt, 0.2)
    loss.backward()
    shown = st.apply(1, img.detach())
    shown.requires_grad_(True)
    photometric_loss(shown, gt, 0.2).backward()
    d_img = st.backward(1, img.detach(), shown.grad)
    torch.testing.assert_close(d_img, img.grad)
    torch.testing.assert_close(st.params.grad[1], E.grad)
    assert float(st.params.grad[0].abs().sum()) == 0.0 and float(st.params.grad[2].abs().sum()) == 0


def test_exposure_gradient_finite_differences():
    torch.manual_seed(1)
    st = ExposureState(1, dtype=torch.float64)
    img = torch.rand(3, 5, 6, dtype=torch.float64)
    gt = torch.rand(3, 5, 6, dtype=torch.float64)

    def f(E):  # a smooth loss: L2 through the transform
        return 0.5 * ((apply_affine_colour(E, img) - gt) ** 2).sum()

    E0 = st.params.detach()[0].clone()
    shown = st.apply(0, img)
    st.backward(0, img, shown - gt)
    eps = 1e-6
    for c, k in ((0, 0), (1, 2), (2, 3), (0, 3)):
        Ep, Em = E0.clone(), E0.clone()
        Ep[c, k] += eps
        Em[c, k] -= eps
        fd = (f(Ep) - f(Em)) / (2 * eps)
        assert float(st.params.grad[0, c, k]) == pytest.approx(float(fd), rel=1e-6, abs=1e-8)


def test_exposure_recentre_and_json():
    st = ExposureState(2)
    with torch.no_grad():
        st.params[0, 0, 0] = 1.4
        st.params[1, 0, 0] = 1.0
        st.params[0, 1, 3] = 0.2
    st.recentre()
    torch.testing.assert_close(st.params.detach().mean(0), torch.eye(3, 4))
    d = st.to_json(["a", "b"])
    assert set(d) == {"a", "b"} and np.array(d["a"]).shape == (3, 4)
    assert d["a"][0][0] == pytest.approx(1.2) and d["b"][0][0] == pytest.approx(0.8)
    with pytest.raises(ValueError, match="names"):
        st.to_json(["a"])
    with pytest.raises(ValueError, match="num_views"):
        ExposureState(0)


def _visit(st, index, seed):
    """A gradient for photo ``index``'s transform, as a training step that shows it."""
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(3, 4, 5, generator=g, dtype=torch.float64)
    st.backward(index, img, torch.rand(3, 4, 5, generator=g, dtype=torch.float64) - 0.5)


@pytest.mark.parametrize("sparse", [False, True])
def test_exposure_sparse_adam_moves_only_the_photos_it_saw(sparse):
    """Between its visits a photo's transform stays put with ``sparse`` (the recentring aside).

    Upstream's dense Adam moves it on its last gradient's momentum at every step.
    """
    st = ExposureState(3, lr_init=1e-2, lr_final=1e-2, dtype=torch.float64, sparse=sparse)
    _visit(st, 0, 0)
    st.step(0)
    first = st.params.detach().clone()
    # a first Adam step moves every element with a gradient by the learning rate; recentring
    # moves all three photos alike, by a third of it
    torch.testing.assert_close((first[0] - first[1]).abs(), torch.full((3, 4), 1e-2,
                                                                        dtype=torch.float64))
    torch.testing.assert_close(first[1], first[2])
    for it in range(1, 6):  # five steps that show photo 1 alone
        _visit(st, 1, it)
        st.step(it)
    now = st.params.detach()
    shift = (now[2] - first[2])  # photo 2 was never seen: the recentring's shift alone
    moved0 = float((now[0] - first[0] - shift).abs().max())
    if sparse:
        assert moved0 < 1e-12  # photo 0 stayed where its one visit left it
    else:
        assert moved0 > 2e-2  # momentum carried it on, by more than two learning rates
    assert float((now[1] - first[1] - shift).abs().max()) > 1e-2  # photo 1 moved


def test_exposure_sparse_is_checked():
    with pytest.raises(ValueError, match="sparse"):
        ExposureState(2, sparse="yes")
    with pytest.raises(ValueError, match="exposure_sparse"):
        FitConfig(exposure_sparse=1)


def test_fit_affine_colour_recovers_a_transform():
    g = torch.Generator().manual_seed(2)
    render = torch.rand(3, 20, 30, generator=g, dtype=torch.float64)
    E = torch.tensor([[0.9, 0.05, 0.0, 0.03], [0.0, 1.1, 0.02, -0.02], [0.01, 0.0, 0.8, 0.05]],
                     dtype=torch.float64)
    photo = apply_affine_colour(E, render)
    mask = torch.zeros(1, 20, 30, dtype=torch.float64)
    mask[..., :15] = 1
    torch.testing.assert_close(fit_affine_colour(render, photo, mask), E, atol=2e-3, rtol=0)
    # the protocol: fitted on the left half, measured on the right half
    view = FitView("v", photo.float(), Intrinsics(30, 20, 30.0, 30.0), torch.eye(4))
    p = photo_psnrs(render.float(), view)
    assert p["right_exposure"] > p["right"] + 10 and p["right_exposure"] > 38


def test_neighbour_exposure_follows_the_nearest_photos():
    """A camera's predicted exposure is its neighbours': exactly a photo's own at its camera."""
    w2cs = _ring_w2c(8)
    mats = [torch.eye(3, 4, dtype=torch.float64) * (0.6 + 0.1 * k) for k in range(8)]
    for E in mats:
        E[:, 3] = 0.01
    at2 = NeighbourExposure(w2cs, mats, k=1)(w2cs[2])
    torch.testing.assert_close(at2, mats[2])
    # a camera between photos 3 and 4 gets a gain between theirs, from them and one more
    between = np.linalg.inv(look_at_c2w((3.0 * math.cos(2 * math.pi * 3.5 / 8),
                                         3.0 * math.sin(2 * math.pi * 3.5 / 8), 0.4)))
    g = float(NeighbourExposure(w2cs, mats)(between)[0, 0])
    assert 0.85 < g < 1.05 and abs(g - 0.95) < 0.05
    # every photo at most: the mean of all, weighted
    assert 0.6 < float(NeighbourExposure(w2cs, mats, k=100)(between)[0, 0]) < 1.3
    with pytest.raises(ValueError, match="k"):
        NeighbourExposure(w2cs, mats, k=0)
    with pytest.raises(ValueError, match="one length"):
        NeighbourExposure(w2cs, mats[:3])
    with pytest.raises(ValueError, match=r"\[3, 4\]"):
        NeighbourExposure(w2cs, [torch.eye(3)] * 8)
    with pytest.raises(ValueError, match=r"w2cs\[0\].*rigid"):
        NeighbourExposure([2.0 * np.eye(4)] + w2cs[1:], mats)


# ----------------------------------------------------------------------------------- far field
def test_fibonacci_sphere_is_even():
    d = fibonacci_sphere(2000)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.abs(d.mean(0)).max() < 0.01
    with pytest.raises(ValueError, match="n"):
        fibonacci_sphere(0)


def test_far_field_points_take_the_colour_they_are_seen_with():
    """Shell points take the colour of the pixels they land on.

    Views whose upper half is blue sky and lower half green ground: shell points above the
    horizon get blue, below it green; directions no camera sees are dropped.
    """
    size = 24
    views = []
    for k, w2c in enumerate(_ring_w2c(8)):
        img = torch.zeros(3, size, size)
        img[2, : size // 2] = 1.0   # the top half of the image: world up (z) is image up
        img[1, size // 2:] = 1.0
        views.append(_view(f"v{k}", img, w2c, size))
    xyz, rgb = far_field_points(views, (0, 0, 0), 30.0, 3000)
    assert 0 < len(xyz) < 3000
    np.testing.assert_allclose(np.linalg.norm(xyz, axis=1), 30.0, rtol=1e-5)
    up, down = xyz[:, 2] > 3.0, xyz[:, 2] < -8.0  # the cameras look 7.6 degrees down
    assert up.any() and down.any()
    assert (rgb[up, 2] > 0.9).mean() > 0.95 and (rgb[down, 1] > 0.9).mean() > 0.95
    with pytest.raises(ValueError, match="radius"):
        far_field_points(views, (0, 0, 0), -1.0, 10)


# ---------------------------------------------------------------------------- initial points
def _write_llff(root, n=8, size=24, with_points=False):
    """An LLFF folder of a textured photo set (no alpha), optionally with COLMAP points."""
    from tests.helpers.colmap import write_colmap_bin

    rows = []
    rng = np.random.default_rng(0)
    for k in range(n):
        c2w = np.linalg.inv(_ring_w2c(n)[k])
        llff = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3],
                         [size, size, size * 1.1]], 1)
        rows.append(np.concatenate([llff.ravel(), [1.0, 6.0]]))
        write_png(root / "images" / f"{k:03d}.png",
                  (rng.random((size, size, 3)) * 255).astype(np.uint8))
    np.save(root / "poses_bounds.npy", np.array(rows))
    if with_points:
        pts = [(i + 1, rng.normal(size=3) * 0.3, (200, 10, 10), 0.5, []) for i in range(50)]
        write_colmap_bin(root / "sparse" / "0", [(1, "SIMPLE_PINHOLE", size, size,
                                                  [size * 1.1, size / 2, size / 2])], [], pts)


def test_initial_points_by_capture(tmp_path):
    from icomma_plugin.fit.scene import views_to_fit
    from icomma_plugin.io.datasets import read_dataset

    cfg = FitConfig(num_sweep_points=200, far_field_points=500)
    _write_llff(tmp_path / "plain")
    scene = read_dataset(tmp_path / "plain", kind="llff")
    train = views_to_fit(scene.train, -1, None, (0.0, 0.0, 0.0))
    cloud = initial_points(scene, train, cfg)
    assert cloud.source == "views" and 0 < cloud.far_points <= 500
    assert len(cloud.xyz) == 200 + cloud.far_points
    # the shell lies at the 90th percentile of the LLFF far bounds (6), beyond the cameras (3)
    far = np.linalg.norm(cloud.xyz[-cloud.far_points:] - np.asarray(cloud.centre), axis=1)
    np.testing.assert_allclose(far, 6.0, rtol=1e-5)
    cloud = initial_points(scene, train, FitConfig(num_sweep_points=200, far_field_points=0))
    assert cloud.far_points == 0 and len(cloud.xyz) == 200

    _write_llff(tmp_path / "points", with_points=True)
    scene = read_dataset(tmp_path / "points", kind="llff")
    cloud = initial_points(scene, train, cfg)
    assert cloud.source == "dataset" and len(cloud.xyz) == 50 + cloud.far_points
    np.testing.assert_allclose(cloud.rgb[0], [200 / 255, 10 / 255, 10 / 255], atol=1e-6)


def test_object_render_keeps_the_random_cube(tmp_path):
    """A Blender layout with alpha (a synthetic object) keeps upstream's cube.

    The same layout of photos without alpha gets the plane sweep and a far field.
    """
    from icomma_plugin.fit.scene import views_to_fit
    from icomma_plugin.io.datasets import read_dataset

    size = 16
    for alpha, name in ((True, "synthetic"), (False, "photos")):
        root = tmp_path / name
        frames = []
        for k, w2c in enumerate(_ring_w2c(6)):
            c2w = np.linalg.inv(w2c)
            c2w[:3, 1:3] *= -1
            arr = np.random.default_rng(k).integers(0, 255, (size, size, 4 if alpha else 3))
            write_png(root / "train" / f"r_{k}.png", arr.astype(np.uint8))
            frames.append({"file_path": f"./train/r_{k}", "transform_matrix": c2w.tolist()})
        (root / "transforms_train.json").write_text(json.dumps(
            {"camera_angle_x": 2 * math.atan(1 / 2.2), "frames": frames}))
        scene = read_dataset(root, white_background=True)
        train = views_to_fit(scene.train, -1, None, (1.0, 1.0, 1.0))
        cloud = initial_points(scene, train, FitConfig(num_random_points=100,
                                                        num_sweep_points=100))
        if alpha:
            assert cloud.source == "random" and cloud.far_points == 0 and len(cloud.xyz) == 100
        else:
            assert cloud.source == "views" and cloud.far_points > 0


# ------------------------------------------------------------------ densification thresholds
def test_distance_scaled_thresholds_keep_far_large_gaussians():
    """A wall Gaussian 20 extents away, 0.5 extent wide, survives the world-size prune.

    Upstream's rule prunes it; the threshold growing with the distance keeps it. A near one that
    large is pruned either way.
    """
    model = GaussianModel(
        means=torch.tensor([[20.0, 0, 0], [0.5, 0, 0]]),
        sh_dc=torch.zeros(2, 1, 3), sh_rest=torch.zeros(2, 0, 3),
        opacity_logit=torch.full((2, 1), 2.0), scale_log=torch.log(torch.full((2, 3), 0.5)),
        quat=torch.tensor([[1.0, 0, 0, 0]] * 2), sh_degree=0)
    for centre, kept in ((None, 0), (torch.zeros(3), 1)):
        st = GaussianTrainState(model, 1.0)
        st.densify_and_prune(1.0, 0.005, 1.0, max_screen_size=1e9, centre=centre)
        assert st.num_gaussians == kept
        if kept:
            assert float(st.get("means").detach()[0, 0]) == 20.0
    st = GaussianTrainState(model, 1.0)
    torch.testing.assert_close(st.size_factor(torch.zeros(3), 1.0), torch.tensor([20.0, 1.0]))


# ------------------------------------------------------------------------------ coarse to fine
def test_downsampled_view_and_schedule():
    img = torch.rand(3, 64, 96)
    valid = torch.ones(1, 64, 96)
    valid[..., :3] = 0
    v = FitView("v", img, Intrinsics(96, 64, 100.0, 90.0, 47.0, 31.5), torch.eye(4), valid=valid)
    h = v.downsampled(2)
    assert tuple(h.image.shape) == (3, 32, 48) and h.intrinsics.fx == pytest.approx(50.0)
    assert h.intrinsics.cx == pytest.approx((47.0 + 0.5) / 2 - 0.5)
    torch.testing.assert_close(h.image[:, 5, 7], img[:, 10:12, 14:16].mean((1, 2)))
    assert float(h.valid[0, 0, 1]) == 0.0 and float(h.valid[0, 0, 2]) == 1.0  # pixels 2-3 of 0-5
    assert v.downsampled(1) is v
    model = model_from_points(np.random.default_rng(0).normal(size=(20, 3)) * 0.2,
                              np.full((20, 3), 0.5), sh_degree=0)
    cfg = FitConfig(iterations=100, sh_degree=0, coarse_to_fine=(0.1, 0.3))
    big = FitView("b", torch.rand(3, 128, 160), Intrinsics(160, 128, 99.0, 99.0), torch.eye(4))
    tr = Trainer(model, [big], 3.0, cfg)
    assert [tr.downsample_factor(i) for i in (1, 10, 11, 30, 31, 100)] == [4, 4, 2, 2, 1, 1]
    tr = Trainer(model, [v], 3.0, cfg)
    assert tr.downsample_factor(1) == 2  # 64 / 4 < 32: the next finer level
    small = FitView("s", torch.rand(3, 40, 40), Intrinsics(40, 40, 40.0, 40.0), torch.eye(4))
    tr = Trainer(model, [small], 3.0, cfg)
    assert tr.downsample_factor(1) == 1  # 40 / 2 < 32: full size
    with pytest.raises(ValueError, match="coarse_to_fine"):
        FitConfig(coarse_to_fine=(0.5, 0.2))


# ------------------------------------------------------------------------ exposure in the fit
def _scene_model():
    g = torch.Generator().manual_seed(3)
    P = 60
    d = torch.randn(P, 3, generator=g)
    return GaussianModel(
        means=d / d.norm(dim=1, keepdim=True) * torch.rand(P, 1, generator=g) * 0.6,
        sh_dc=rgb_to_sh(torch.rand(P, 3, generator=g) * 0.6 + 0.2).view(P, 1, 3),
        sh_rest=torch.zeros(P, 0, 3), opacity_logit=torch.full((P, 1), 3.0),
        scale_log=torch.log(torch.rand(P, 3, generator=g) * 0.1 + 0.08),
        quat=torch.randn(P, 4, generator=g), sh_degree=0)


def test_fit_with_exposure_explains_photos_of_changing_exposure():
    """Photos of one scene with a different gain per photo.

    With per-photo exposure the fit explains them (train PSNR through the exposures) far better
    than without, and the fitted gains follow the photos'.
    """
    from icomma_plugin.fit import render_state

    gt = GaussianTrainState(_scene_model(), 1.0)
    size = 32
    views = []
    with torch.no_grad():
        for k, w2c in enumerate(_ring_w2c(8)):
            v = _view(f"v{k}", torch.zeros(3, size, size), w2c, size)
            gain = 0.6 + 0.1 * k
            img = (render_state(gt, v, torch.zeros(3)).color * gain).clamp(0, 1)
            views.append(_view(v.name, img, w2c, size))
    init = _scene_model()
    with torch.no_grad():
        init.sh_dc.add_(0.3 * torch.randn_like(init.sh_dc))
    # a held-out photo between photos 1 and 2, exposed between them (the mean photo's gain is
    # 0.95, which the scene's own colours take)
    between = np.linalg.inv(look_at_c2w((3.0 * math.cos(2 * math.pi * 1.5 / 8),
                                         3.0 * math.sin(2 * math.pi * 1.5 / 8), 0.4)))
    with torch.no_grad():
        v = _view("held_out", torch.zeros(3, size, size), between, size)
        held_out = _view(v.name, (render_state(gt, v, torch.zeros(3)).color * 0.75).clamp(0, 1),
                         between, size)
    psnr = {}
    for exposure in (False, True):
        cfg = FitConfig.scaled_schedule(300, sh_degree=0, densify_until_iter=0)
        tr = Trainer(init, views, 3.0, cfg, exposure=exposure)
        tr.run()
        torch.set_grad_enabled(False)
        if exposure:
            gains = torch.stack([tr.exposure.matrix(i)[:3, :3].diagonal().mean()
                                 for i in range(len(views))])
            assert float(torch.corrcoef(torch.stack([gains, torch.arange(8.0)]))[0, 1]) > 0.95
            shown = [tr.exposure.apply(i, render_state(tr.state, v, tr.background).color)
                     for i, v in enumerate(views)]
            # the held-out photo through its neighbours' exposures, never having seen it
            predict = NeighbourExposure([v.w2c for v in views],
                                        [tr.exposure.matrix(i) for i in range(len(views))])
            p = photo_psnrs(render_state(tr.state, held_out, tr.background).color, held_out,
                            predicted=predict(held_out.w2c))
            assert p["neighbour_exposure"] > p["full"] + 3.0, p
        else:
            shown = [render_state(tr.state, v, tr.background).color for v in views]
        psnr[exposure] = float(np.mean([-10 * math.log10(float(((s.clamp(0, 1) - v.image) ** 2)
                                                               .mean())) for s, v in
                                        zip(shown, views)]))
        torch.set_grad_enabled(True)
    assert psnr[True] > psnr[False] + 5.0, psnr


# ---------------------------------------------------------------------------------- the grid
def test_write_grid(tmp_path):
    import cv2

    v = FitView("v", torch.rand(3, 40, 30), Intrinsics(30, 40, 30.0, 30.0), torch.eye(4))
    path = write_grid(tmp_path / "g" / "grid.png", [(v, v.image), (v, torch.zeros(3, 40, 30))])
    im = cv2.imread(str(path))
    assert im.shape == (80, 90, 3)
    assert np.abs(im[:40, 30:60].astype(int) - im[:40, :30]).max() <= 1  # render == photo
    with pytest.raises(ValueError, match="pairs"):
        write_grid(tmp_path / "x.png", [])


def test_initial_scales_bounded_by_their_angle_from_the_cameras():
    from icomma_plugin.fit.init import init_scale_limits

    xyz = np.array([[10.0, 0, 0], [1.0, 0, 0], [1.0, 0.05, 0], [1.0, 0, 0.05], [30.0, 5, 0]])
    lim = init_scale_limits(xyz, np.zeros((1, 3)), 0.01)
    np.testing.assert_allclose(lim[:2], [0.1, 0.01])
    free = model_from_points(xyz, np.full((5, 3), 0.5), sh_degree=0)
    held = model_from_points(xyz, np.full((5, 3), 0.5), sh_degree=0, max_scale=lim)
    s_free, s_held = free.scale_log.exp()[:, 0], held.scale_log.exp()[:, 0]
    assert float(s_free[0]) > 0.5 and float(s_held[0]) == pytest.approx(0.1, rel=1e-5)
    torch.testing.assert_close(s_held, torch.minimum(s_free, torch.as_tensor(lim).float()))
    with pytest.raises(ValueError, match="max_scale"):
        model_from_points(xyz, np.full((5, 3), 0.5), max_scale=lim[:3])
    with pytest.raises(ValueError, match="angle"):
        init_scale_limits(xyz, np.zeros((1, 3)), 0.0)
