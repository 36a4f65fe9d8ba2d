"""Native CPU backend: determinism, pose gradient, errors, empty input, mark_visible.

Pose gradient vs finite differences, no camera work when not requested, TORCH_CHECK errors,
P = 0 and empty image regions.
"""
from __future__ import annotations

import pytest
import torch

from gaussian_renderer_pose.camera import camera_matrices
from tests.helpers.scenes import make_scene, se3_exp
from tests.gaussian_renderer_pose.test_native_vs_reference import compare, run_backend

pytestmark = pytest.mark.usefixtures("native_backend")


def _native():
    from gaussian_renderer_pose._native import rasterize_gaussians_native

    return rasterize_gaussians_native


def _ops():
    from gaussian_renderer_pose import _ops

    return _ops


def _direct_args(scene):
    """Leading args of the grp ops for a scene (float32, contiguous).

    The tensors, and the settings up to sh_degree (prefiltered and antialiasing follow).
    """
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    tensors = [scene.means3D, scene.opacities, scene.shs, scene.colors_precomp, scene.scales,
               scene.rotations, scene.cov3D_precomp, scene.bg, cam.viewmatrix.contiguous(),
               cam.projmatrix.contiguous(), cam.campos.contiguous()]
    settings = [scene.height, scene.width, cam.tanfovx, cam.tanfovy, scene.scale_modifier,
                scene.sh_degree]
    return tensors, settings


# ------------------------------------------------------------------------------------------------
def test_backward_is_bitwise_deterministic():
    scene = make_scene(3000, height=64, width=80, sh_degree=3, antialiasing=True, seed=31)
    out1, g1 = run_backend(_native(), scene, pose=True)
    out2, g2 = run_backend(_native(), scene, pose=True)
    for a, b in zip(out1, out2):
        assert torch.equal(a, b)
    for name in g1:
        assert torch.equal(g1[name], g2[name]), f"{name} differs between runs"


# ------------------------------------------------------------------------------------------------
def _pose_loss(scene, xi, cots):
    """sum(out * cot) of the native render at w2c = exp(xi) w2c0 (accumulated in float64)."""
    w2c = (se3_exp(xi) @ scene.w2c.double()).float()
    cam = camera_matrices(w2c, scene.fx, scene.fy, scene.width, scene.height)
    out = _native()(
        scene.means3D, None, scene.opacities, scene.shs, scene.colors_precomp, scene.scales,
        scene.rotations, scene.cov3D_precomp, scene.bg, cam.viewmatrix, cam.projmatrix, cam.campos,
        image_height=scene.height, image_width=scene.width, tanfovx=cam.tanfovx,
        tanfovy=cam.tanfovy, scale_modifier=scene.scale_modifier, sh_degree=scene.sh_degree,
        prefiltered=False, antialiasing=scene.antialiasing,
    )
    color, _r, invdepth, depth_acc, alpha = out
    loss = torch.zeros((), dtype=torch.float64)
    for o, c in zip((color, invdepth, depth_acc, alpha), cots):
        loss = loss + (o.double() * c).sum()
    return loss


@pytest.mark.parametrize("antialiasing", [False, True])
def test_pose_gradient_matches_finite_differences(antialiasing):
    # Few, large, smooth Gaussians well inside the frustum: FD in float32 stays meaningful.
    # (The alpha cut-off and tile-rect truncation make the forward piecewise; with these settings
    # their jumps are negligible next to the smooth part.)
    scene = make_scene(20, height=48, width=64, sh_degree=3, seed=41, antialiasing=antialiasing,
                       frac_behind=0.0, frac_offscreen=0.0, frac_cluster=0.0,
                       scale_range=(0.3, 0.8), opacity_range=(0.6, 0.95))
    assert_pose_grad_matches_fd(scene, cot_seed=5)


def assert_pose_grad_matches_fd(scene, cot_seed: int, eps: float = 1e-3):
    """The native pose gradient of sum(out * cot) (random cotangents) vs central FD in xi."""
    g = torch.Generator().manual_seed(cot_seed)
    h, w = scene.height, scene.width
    cots = [torch.rand(s, generator=g, dtype=torch.float64) for s in
            ((3, h, w), (1, h, w), (1, h, w), (1, h, w))]
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    _pose_loss(scene, xi, cots).backward()
    grad = xi.grad.clone()
    fd = torch.zeros(6, dtype=torch.float64)
    with torch.no_grad():
        for i in range(6):
            d = torch.zeros(6, dtype=torch.float64)
            d[i] = eps
            fd[i] = (_pose_loss(scene, d, cots) - _pose_loss(scene, -d, cots)) / (2 * eps)
    err = (grad - fd).abs()
    tol = 5e-2 * fd.abs() + 1e-2 * fd.abs().max()
    assert bool((err <= tol).all()), f"pose gradient {grad.tolist()} vs central FD {fd.tolist()}"
    assert float(torch.nn.functional.cosine_similarity(grad, fd, dim=0)) > 0.999


# ------------------------------------------------------------------------------------------------
def test_no_camera_gradient_when_not_requested():
    scene = make_scene(300, sh_degree=3, seed=51)
    out_p, g_p = run_backend(_native(), scene, pose=True)
    out_n, g_n = run_backend(_native(), scene, pose=False)
    for a, b in zip(out_p, out_n):
        assert torch.equal(a, b)
    for name in g_n:
        assert torch.equal(g_p[name], g_n[name]), f"{name} depends on whether a pose grad was asked"
    # The C++ backward returns no camera gradient at all when not asked (nothing computed).
    tensors, settings = _direct_args(scene)
    ops = _ops()
    outs = ops.rasterize_forward(*tensors, *settings, False, False, None)
    H, W = scene.height, scene.width
    state = outs[4:]  # radii and the saved state
    grads = ops.rasterize_backward(*tensors, *settings, False, False, None, *state,
                                   torch.ones(3, H, W), torch.zeros(1, H, W),
                                   torch.zeros(1, H, W), torch.zeros(1, H, W), False, True)
    assert grads[9] is None and grads[10] is None and grads[11] is None
    grads_cam = ops.rasterize_backward(*tensors, *settings, False, False, None, *state,
                                       torch.ones(3, H, W), torch.zeros(1, H, W),
                                       torch.zeros(1, H, W), torch.zeros(1, H, W), True, True)
    assert all(t is not None for t in grads_cam[9:12]) and grads_cam[12] is None  # no shs_rest
    for a, b in zip(grads[:9], grads_cam[:9]):
        assert (a is None and b is None) or torch.equal(a, b)


def test_only_some_inputs_require_grad():
    scene = make_scene(200, sh_degree=1, seed=52)
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    means = scene.means3D.clone().requires_grad_(True)
    view = cam.viewmatrix.detach().clone().requires_grad_(True)
    out = _native()(
        means, None, scene.opacities, scene.shs, None, scene.scales, scene.rotations, None,
        scene.bg, view, cam.projmatrix, cam.campos, image_height=scene.height,
        image_width=scene.width, tanfovx=cam.tanfovx, tanfovy=cam.tanfovy, scale_modifier=1.0,
        sh_degree=1, prefiltered=False, antialiasing=False,
    )
    out[0].sum().backward()
    assert means.grad is not None and view.grad is not None
    assert scene.opacities.grad is None and cam.projmatrix.grad is None


# ------------------------------------------------------------------------------------------------
def _bad_calls(scene):
    tensors, settings = _direct_args(scene)
    i_means, i_opac, i_bg, i_view = 0, 1, 7, 8

    def with_(idx, value):
        t = list(tensors)
        t[idx] = value
        return t

    yield "float64 means", with_(i_means, tensors[i_means].double()), settings
    yield (
        "non-contiguous means",
        with_(i_means, torch.cat([tensors[i_means]] * 2, 1)[:, ::2]),
        settings,
    )
    yield "means [P, 4]", with_(i_means, torch.zeros(tensors[i_means].shape[0], 4)), settings
    yield "opacities [P]", with_(i_opac, tensors[i_opac].view(-1)), settings
    yield "bg [4]", with_(i_bg, torch.zeros(4)), settings
    yield "viewmatrix [3, 4]", with_(i_view, torch.zeros(3, 4)), settings
    yield "no colours", with_(2, None), settings
    yield "no covariance", with_(5, None), settings
    yield "too few SH coefficients", with_(2, tensors[2][:, :4].contiguous()), settings
    yield "sh_degree 4", tensors, settings[:5] + [4]
    yield "zero height", tensors, [0] + settings[1:]


def test_torch_check_errors_are_runtime_errors():
    scene = make_scene(20, sh_degree=3, seed=61)
    ops = _ops()
    for what, tensors, settings in _bad_calls(scene):
        with pytest.raises(RuntimeError):
            ops.rasterize_forward(*tensors, *settings, False, False, None)
            pytest.fail(f"no error for {what}")
    # backward with saved state that does not belong to the inputs
    tensors, settings = _direct_args(scene)
    outs = ops.rasterize_forward(*tensors, *settings, False, False, None)
    H, W = scene.height, scene.width
    g = [torch.zeros(3, H, W), torch.zeros(1, H, W), torch.zeros(1, H, W), torch.zeros(1, H, W)]
    radii, state = outs[4], outs[5:]
    with pytest.raises(RuntimeError):
        ops.rasterize_backward(*tensors, *settings, False, False, None, radii[:-1], *state, *g,
                               True, True)
    with pytest.raises(RuntimeError):
        ops.rasterize_backward(*tensors, *settings, False, False, None, radii, *state,
                               torch.zeros(3, H + 1, W), *g[1:], True, True)
    with pytest.raises(RuntimeError):
        ops.mark_visible(scene.means3D.double(), tensors[8], tensors[9])


# ------------------------------------------------------------------------------------------------
def test_zero_gaussians():
    scene = make_scene(0, height=33, width=17)
    out, grads = run_backend(_native(), scene, pose=True)
    color, radii, invdepth, depth_acc, alpha = out
    assert radii.shape == (0,) and radii.dtype == torch.int32
    assert torch.equal(color, scene.bg.view(3, 1, 1).expand(3, 33, 17))
    for t in (invdepth, depth_acc, alpha):
        assert t.shape == (1, 33, 17) and float(t.abs().max()) == 0.0
    assert grads["means3D"].shape == (0, 3)
    assert float(grads["xi"].abs().max()) == 0.0
    assert grads["bg"].shape == (3,) and float(grads["bg"].abs().sum()) > 0  # bg fills the image


def test_all_gaussians_culled_and_empty_region():
    # Everything behind the camera: pure background, zero gradients except bg.
    scene = make_scene(50, frac_behind=1.0, seed=71)
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    keep = scene.means3D @ cam.viewmatrix[:3, 2] + cam.viewmatrix[3, 2] <= 0.2
    assert int(keep.sum()) > 10
    scene.means3D, scene.opacities = scene.means3D[keep], scene.opacities[keep]
    scene.shs, scene.scales, scene.rotations = (
        scene.shs[keep],
        scene.scales[keep],
        scene.rotations[keep],
    )
    scene.means2D = scene.means2D[keep]
    out, grads = run_backend(_native(), scene, pose=True)
    assert int(out[1].max()) == 0
    assert torch.equal(out[0], scene.bg.view(3, 1, 1).expand_as(out[0]))
    assert float(grads["means3D"].abs().max()) == 0.0 and float(grads["xi"].abs().max()) == 0.0

    # Gaussians only in the left part of a wide image: the right part is exactly background.
    scene = make_scene(60, height=40, width=160, frac_behind=0.0, frac_offscreen=0.0, seed=72,
                       scale_range=(0.01, 0.03))
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    t = scene.means3D @ cam.viewmatrix[:3, :3] + cam.viewmatrix[3, :3]
    px = scene.fx * t[:, 0] / t[:, 2] + (scene.width - 1) / 2
    keep = px < 40
    scene.means3D, scene.opacities = scene.means3D[keep], scene.opacities[keep]
    scene.shs, scene.scales, scene.rotations = (
        scene.shs[keep],
        scene.scales[keep],
        scene.rotations[keep],
    )
    scene.means2D = scene.means2D[keep]
    out, grads = run_backend(_native(), scene, pose=True)
    right = slice(112, None)  # tiles 7..9: no Gaussian reaches them
    assert torch.equal(out[0][:, :, right], scene.bg.view(3, 1, 1).expand(3, 40, 48))
    assert float(out[4][:, :, right].abs().max()) == 0.0
    assert float(out[4].max()) > 0.0
    for name, gr in grads.items():
        assert torch.isfinite(gr).all(), name


def test_mark_visible():
    from gaussian_renderer_pose._native import mark_visible

    scene = make_scene(500, seed=81)
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    vis = mark_visible(scene.means3D, cam.viewmatrix, cam.projmatrix)
    z = scene.means3D @ cam.viewmatrix[:3, 2] + cam.viewmatrix[3, 2]
    assert vis.dtype == torch.bool
    assert torch.equal(vis, z > 0.2)


# ------------------------------------------------------------------------------------------------
def test_tile_lists_hold_exactly_the_tiles_an_alpha_box_reaches():
    # Faint Gaussians (a split or an upstream-trained model has many): their alpha >= 1/255
    # ellipse lies well inside upstream's 3-sigma square, and the tile lists keep only the tiles
    # that the ellipse's box reaches. A tile may be left out only when none of its pixels can pass
    # the alpha test; every tile where one does must be listed; the images stay the reference's.
    scene = make_scene(600, height=72, width=104, sh_degree=0, seed=83,
                       opacity_range=(0.005, 0.08), frac_behind=0.0)
    compare(scene)
    tensors, settings = _direct_args(scene)
    outs = _ops().rasterize_forward(*tensors, *settings, False, False, None)
    radii, geom, binning, tile_ranges = outs[4], outs[5], outs[6], outs[7]
    tile = _ops()._C.TILE_SIZE
    H, W = scene.height, scene.width
    grid_x, grid_y = -(-W // tile), -(-H // tile)
    # The geom record's fields (csrc/common/raster.h GeomField): kGPx .. kGOpacity, kGBoxX/Y.
    px, py, ca, cb, cc, o = (geom[:, k].double() for k in range(6))
    bx, by = geom[:, 11], geom[:, 12]
    listed = torch.zeros(geom.shape[0], grid_y * grid_x, dtype=torch.bool)
    for t in range(grid_y * grid_x):
        listed[binning[tile_ranges[t]:tile_ranges[t + 1], 0].long(), t] = True

    # Every pixel where a Gaussian passes the alpha test (with a margin for the kernel's own exp)
    # lies in a tile that lists it.
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    dx, dy = px[:, None, None] - xs, py[:, None, None] - ys
    a, b, c = (v[:, None, None] for v in (ca, cb, cc))
    power = -0.5 * (a * dx**2 + c * dy**2) - b * dx * dy
    passes = (o[:, None, None] * power.exp() >= 1.001 / 255) & (power <= 0)
    passes &= (radii > 0)[:, None, None]
    tile_of = (ys.long() // tile) * grid_x + xs.long() // tile
    g, yy, xx = passes.nonzero(as_tuple=True)
    assert len(g) > 1000
    assert bool(listed[g, tile_of[yy, xx]].all()), "a tile where a Gaussian is visible misses it"

    # Every listed tile holds a pixel within the Gaussian's alpha box.
    g, t = listed.nonzero(as_tuple=True)
    x0, y0 = (t % grid_x) * tile, (t // grid_x) * tile
    x1, y1 = torch.clamp(x0 + tile - 1, max=W - 1), torch.clamp(y0 + tile - 1, max=H - 1)
    reach_x = (px[g] + bx[g] >= x0) & (px[g] - bx[g] <= x1)
    reach_y = (py[g] + by[g] >= y0) & (py[g] - by[g] <= y1)
    assert bool((reach_x & reach_y).all()), "a tile lists a Gaussian whose alpha box misses it"

    # And the lists are much shorter than upstream's 3-sigma squares would make them.
    vis = radii > 0
    r = radii[vis].double()

    def square_tiles(centre, n):  # upstream's getRect along one axis
        return (torch.clamp(((centre - r) / tile).long(), 0, n),
                torch.clamp(((centre + r + tile - 1) / tile).long(), 0, n))

    (mx0, mx1), (my0, my1) = square_tiles(px[vis], grid_x), square_tiles(py[vis], grid_y)
    squares = int(((mx1 - mx0) * (my1 - my0)).sum())
    assert binning.shape[0] < 0.6 * squares, (binning.shape[0], squares)
