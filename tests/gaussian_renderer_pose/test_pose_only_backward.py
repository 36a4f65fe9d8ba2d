"""Native backward when only the camera needs a gradient (a localizer's fixed scene).

When no Gaussian tensor requires grad, `_native.py` calls the backward op with
`compute_gaussian_grads=False` and the kernel skips the work that only the Gaussians' gradients
need. The camera gradient must be the same bits as with every gradient requested, agree with the
reference, and match central finite differences; the op returns None for the Gaussians then, and
the same grad_bg. Skips cleanly when the extension is not built.
"""
from __future__ import annotations

from typing import Dict

import pytest
import torch

from gaussian_renderer_pose import _backend
from gaussian_renderer_pose.camera import camera_matrices
from gaussian_renderer_pose.reference import rasterize_gaussians_reference
from tests.helpers.scenes import make_scene, se3_exp
from tests.gaussian_renderer_pose.test_native_misc import assert_pose_grad_matches_fd
from tests.gaussian_renderer_pose.test_native_vs_reference import GAUSSIAN_INPUTS, assert_grad_close

_OK, _WHY = _backend.native_status("cpu")
pytestmark = pytest.mark.skipif(not _OK, reason=f"native CPU backend not built: {_WHY}")

CAMERA = ("viewmatrix", "projmatrix", "campos", "xi")
DEVICES = ["cpu"] + (["cuda"] if _backend.native_status("cuda")[0] else [])

# Every variant of the per-tile backward (which slots the camera needs: the opacity with
# antialiasing, the colour with SH of degree > 0) and of the per-Gaussian chain.
CASES = {
    "sh3": dict(num_gaussians=150, sh_degree=3, seed=101),
    "sh0": dict(num_gaussians=150, sh_degree=0, seed=102),
    "sh1_aa_odd": dict(num_gaussians=150, sh_degree=1, antialiasing=True, height=97, width=131,
                       seed=103),
    "precomp_colors": dict(num_gaussians=150, colors="precomp", seed=104),
    "precomp_cov_scale_mod": dict(num_gaussians=150, covariance="precomp", scale_modifier=0.7,
                                  seed=105),
    "precomp_both_aa": dict(num_gaussians=150, colors="precomp", covariance="precomp",
                            antialiasing=True, seed=106),
    "off_centre_pp_aa": dict(num_gaussians=120, cx=30.0, cy=20.0, antialiasing=True, seed=107),
    "many": dict(num_gaussians=4000, height=48, width=64, sh_degree=3, seed=108),
}


def _native():
    from gaussian_renderer_pose._native import rasterize_gaussians_native

    return rasterize_gaussians_native


def _ops():
    from gaussian_renderer_pose import _ops

    return _ops


def _render_grads(fn, scene, *, gaussians: bool, cot_seed: int = 1):
    """Forward + backward of sum(out * cot) -> (outputs, grads by name).

    The pose twist xi requires grad, and the Gaussian tensors too when `gaussians`.
    """
    leaves = {name: None if getattr(scene, name) is None else
              getattr(scene, name).detach().clone().requires_grad_(gaussians)
              for name in GAUSSIAN_INPUTS}
    xi = torch.zeros(6, dtype=torch.float64, device=scene.w2c.device, requires_grad=True)
    w2c = (se3_exp(xi) @ scene.w2c.detach().double()).float()
    cam = camera_matrices(w2c, scene.fx, scene.fy, scene.width, scene.height, scene.cx, scene.cy)
    mats = {"viewmatrix": cam.viewmatrix, "projmatrix": cam.projmatrix, "campos": cam.campos}
    for t in mats.values():
        t.retain_grad()
    out = fn(
        *(leaves[n] for n in GAUSSIAN_INPUTS), mats["viewmatrix"], mats["projmatrix"],
        mats["campos"], image_height=scene.height, image_width=scene.width, tanfovx=cam.tanfovx,
        tanfovy=cam.tanfovy, scale_modifier=scene.scale_modifier, sh_degree=scene.sh_degree,
        prefiltered=False, antialiasing=scene.antialiasing,
    )
    g = torch.Generator().manual_seed(cot_seed)
    loss = sum((o * torch.randn(o.shape, generator=g).to(o.device)).sum()
               for i, o in enumerate(out) if i != 1)
    loss.backward()
    grads: Dict[str, torch.Tensor] = {k: mats[k].grad for k in mats}
    grads["xi"] = xi.grad
    if gaussians:
        grads.update({k: v.grad for k, v in leaves.items() if v is not None})
    return [o.detach() for o in out], grads


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("case", list(CASES))
def test_pose_gradient_is_the_same_bits_without_gaussian_gradients(case, device):
    scene = make_scene(**CASES[case]).to(device)
    out_all, g_all = _render_grads(_native(), scene, gaussians=True)
    out_pose, g_pose = _render_grads(_native(), scene, gaussians=False)
    for a, b in zip(out_all, out_pose):
        assert torch.equal(a, b)
    assert g_all["means3D"] is not None and "means3D" not in g_pose
    for name in ("viewmatrix", "xi"):  # (campos gets 0 where the colour ignores the camera)
        assert float(g_pose[name].abs().max()) > 0, name
    for name in CAMERA:
        assert torch.equal(g_all[name], g_pose[name]), (
            f"{name}: pose-only {g_pose[name].tolist()} != with Gaussian grads "
            f"{g_all[name].tolist()}")


@pytest.mark.parametrize("case", list(CASES))
def test_pose_only_gradient_matches_reference(case):
    scene = make_scene(**CASES[case])
    _, g_ref = _render_grads(rasterize_gaussians_reference, scene, gaussians=False)
    _, g_nat = _render_grads(_native(), scene, gaussians=False)
    for name in ("viewmatrix", "projmatrix", "campos"):
        assert_grad_close(name, g_ref[name], g_nat[name])
    assert_grad_close("xi", g_ref["xi"], g_nat["xi"], rel=1e-3, cos=0.99999)


@pytest.mark.parametrize("gaussians", [False, True], ids=["pose_only", "full"])
def test_backward_is_deterministic_and_thread_independent(gaussians):
    # both backward paths: pose-only (camera gradients alone) and full (every Gaussian's too)
    scene = make_scene(2000, height=64, width=80, sh_degree=3, seed=109)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        _, g1 = _render_grads(_native(), scene, gaussians=gaussians)
        _, g1b = _render_grads(_native(), scene, gaussians=gaussians)
        torch.set_num_threads(max(2, old))
        _, g2 = _render_grads(_native(), scene, gaussians=gaussians)
    finally:
        torch.set_num_threads(old)
    assert set(g1) > set(CAMERA) if gaussians else set(g1) == set(CAMERA)
    for name in g1:
        assert torch.equal(g1[name], g1b[name]), f"{name} differs between runs"
        assert torch.equal(g1[name], g2[name]), f"{name} depends on the thread count"


@pytest.mark.parametrize("colors,covariance", [("precomp", "scale_rot"), ("sh", "precomp"),
                                               ("precomp", "precomp")])
def test_pose_only_gradient_matches_finite_differences(colors, covariance):
    # Complements test_native_misc's SH-3 case (tensors that do not require grad: the pose-only
    # path) with precomputed colours (the colour slots are then never accumulated) and cov3D.
    # (The scene of that test: with other seeds a Gaussian near a cut-off can make float32 FD
    # depend on the step by several %, in the old kernel as well.)
    scene = make_scene(20, height=48, width=64, sh_degree=3, seed=41, colors=colors,
                       covariance=covariance, frac_behind=0.0, frac_offscreen=0.0,
                       frac_cluster=0.0, scale_range=(0.3, 0.8), opacity_range=(0.6, 0.95))
    assert_pose_grad_matches_fd(scene, cot_seed=6)


def _op_call(scene, camera: bool, gaussians: bool):
    """rasterize_backward of the raw op for `scene` (random image cotangents)."""
    ops = _ops()
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    tensors = [None if t is None else t.detach().contiguous() for t in (
        scene.means3D, scene.opacities, scene.shs, scene.colors_precomp, scene.scales,
        scene.rotations, scene.cov3D_precomp, scene.bg, cam.viewmatrix, cam.projmatrix,
        cam.campos)]
    settings = (scene.height, scene.width, cam.tanfovx, cam.tanfovy, scene.scale_modifier,
                scene.sh_degree, False, scene.antialiasing, None)
    outs = ops.rasterize_forward(*tensors, *settings)
    g = torch.Generator().manual_seed(2)
    H, W = scene.height, scene.width
    cots = [torch.randn(s, generator=g) for s in ((3, H, W), (1, H, W), (1, H, W), (1, H, W))]
    return ops.rasterize_backward(*tensors, *settings, *outs[4:], *cots, camera, gaussians)


@pytest.mark.parametrize("case", ["sh3", "precomp_both_aa"])
def test_op_returns_no_gaussian_gradients_when_not_asked(case):
    scene = make_scene(**CASES[case])
    full = _op_call(scene, True, True)
    pose = _op_call(scene, True, False)
    neither = _op_call(scene, False, False)
    assert all(t is None for t in pose[:8]) and all(t is None for t in neither[:8])
    assert neither[9] is None and neither[10] is None and neither[11] is None
    assert full[0] is not None and full[2] is not None
    for i in (8, 9, 10, 11):  # grad_bg and the camera
        assert torch.equal(full[i], pose[i])
    assert torch.equal(full[8], neither[8])


def test_native_asks_for_gaussian_gradients_only_when_a_gaussian_requires_grad(monkeypatch):
    ops = _ops()
    flags = []
    real = ops.rasterize_backward

    def spy(*args):
        flags.append(args[-2:])  # compute_camera_grad, compute_gaussian_grads
        return real(*args)

    monkeypatch.setattr(ops, "rasterize_backward", spy)
    scene = make_scene(60, sh_degree=2, seed=111)
    _render_grads(_native(), scene, gaussians=False)
    _render_grads(_native(), scene, gaussians=True)
    assert flags == [(True, False), (True, True)]
