"""Reference backend: autograd gradients vs central finite differences (float64).

For every input, the three camera matrices, and the 6 dof of a left pose twist on w2c; plus a
literal scalar transcription of the upstream CUDA forward as an independent check of the numerics.

FD scenes avoid the discontinuities of the forward (1/255 skip, tile-rect edges, 3-sigma radius,
near plane, T stop, SH clamp): a 24x20 image (2x2 tiles), few large Gaussians whose rects cover
every tile and whose alpha stays well above 1/255 on the whole image, moderate opacities, colours
away from the clamp, plus Gaussians culled behind / in front of the near plane and one partly off
screen with its tx/tz clamp active (piecewise smooth, away from the kink).
"""
from __future__ import annotations

import math

import pytest
import torch

from gaussian_renderer_pose import (
    GaussianRasterizationSettings,
    camera_matrices,
    rasterize_gaussians,
)
from gaussian_renderer_pose.reference import projection as ref_projection
from gaussian_renderer_pose.reference import rasterize_gaussians_reference
from gaussian_renderer_pose.reference.sh import eval_sh
from tests.helpers.scenes import (
    TENSOR_NAMES,
    Scene,
    cov3d_from_scale_rot,
    make_scene,
    random_w2c,
    se3_exp,
)

F64 = torch.float64
EPS = 1e-6


def fd_scene(
    colors: str, covariance: str, antialiasing: bool, seed: int = 0, cx=None, cy=None
) -> Scene:
    g = torch.Generator().manual_seed(seed)
    H, W = 20, 24
    fx, fy = 0.9 * W, 0.95 * W
    tanx, tany = W / (2 * fx), H / (2 * fy)
    w2c = random_w2c(g, dtype=F64, rot=0.3, trans=0.3)
    # camera-frame centres: (x/z in units of tanfov, y/z likewise, z)
    cam = torch.tensor(
        [
            [0.0, 0.0, 3.0],
            [0.4, -0.3, 2.6],
            [-0.5, 0.4, 3.4],
            [0.2, 0.5, 2.2],
            [1.1, -0.2, 2.9],  # centre off screen, still covering the image
            [1.45, 0.3, 3.2],  # off screen beyond 1.3 tanfov: tx clamp active
            [0.0, 0.1, -1.0],  # behind the camera (culled)
            [0.1, 0.0, 0.15],  # nearer than 0.2 (culled)
        ],
        dtype=F64,
    )
    P = cam.shape[0]
    x_cam = torch.stack([cam[:, 0] * tanx * cam[:, 2], cam[:, 1] * tany * cam[:, 2], cam[:, 2]], -1)
    c2w = torch.linalg.inv(w2c)
    means = x_cam @ c2w[:3, :3].T + c2w[:3, 3]
    # world scales ~1.5..3.5 at depth ~3: sigma 10..25 px, anisotropic
    scales = 1.5 + 2.0 * torch.rand(P, 3, generator=g, dtype=F64)
    quats = torch.randn(P, 4, generator=g, dtype=F64)
    quats = (
        quats / quats.norm(dim=-1, keepdim=True) * (0.6 + torch.rand(P, 1, generator=g, dtype=F64))
    )
    opac = 0.2 + 0.35 * torch.rand(P, 1, generator=g, dtype=F64)
    shs = 0.05 * torch.randn(P, 16, 3, generator=g, dtype=F64)
    shs[:, 0] = 0.6 + 0.5 * torch.rand(P, 3, generator=g, dtype=F64)  # colour ~0.67..0.81: no clamp
    cols = 0.2 + 0.6 * torch.rand(P, 3, generator=g, dtype=F64)
    return Scene(
        means3D=means,
        means2D=torch.zeros(P, 3, dtype=F64),
        opacities=opac,
        shs=shs if colors == "sh" else None,
        colors_precomp=cols if colors == "precomp" else None,
        scales=scales if covariance == "scale_rot" else None,
        rotations=quats if covariance == "scale_rot" else None,
        cov3D_precomp=cov3d_from_scale_rot(scales, quats) if covariance == "precomp" else None,
        bg=torch.tensor([0.2, 0.5, 0.8], dtype=F64),
        w2c=w2c,
        fx=fx,
        fy=fy,
        height=H,
        width=W,
        sh_degree=3,
        antialiasing=antialiasing,
        cx=cx,
        cy=cy,
    )


def output_weights(H: int, W: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    return {k: torch.rand(c, H, W, generator=g, dtype=F64) for k, c in
            (("color", 3), ("invdepth", 1), ("depth", 1), ("alpha", 1))}


def weighted_loss(out, weights) -> torch.Tensor:
    return sum((getattr(out, k) * w).sum() for k, w in weights.items())


def render(scene: Scene, tensors: dict, mats: dict):
    settings = GaussianRasterizationSettings(
        image_height=scene.height,
        image_width=scene.width,
        tanfovx=mats["tanfovx"],
        tanfovy=mats["tanfovy"],
        bg=tensors["bg"],
        scale_modifier=1.0,
        viewmatrix=mats["viewmatrix"],
        projmatrix=mats["projmatrix"],
        sh_degree=scene.sh_degree,
        campos=mats["campos"],
        prefiltered=False,
        debug=False,
        antialiasing=scene.antialiasing,
        backend="reference",
    )
    kw = {k: v for k, v in tensors.items() if k != "bg"}
    return rasterize_gaussians(settings=settings, **kw)


@pytest.fixture
def means2D_as_offset(monkeypatch):
    """Make means2D a real NDC offset (same derivative as the value-neutral upstream trick)."""
    monkeypatch.setattr(ref_projection, "inject_means2D", lambda ndc_xy, m2: ndc_xy + m2)


def _check(name, analytic, numeric):
    scale = max(1.0, float(numeric.abs().max()))
    err = float((analytic - numeric).abs().max())
    assert err <= 1e-5 * scale, (
        f"{name}: max |autograd - FD| = {err:.3e} (scale {scale:.3e})\n{analytic}\n{numeric}"
    )


def _fd_tensor(f, t: torch.Tensor, directions: int, gen: torch.Generator):
    """(autograd-free) numeric gradient along the elements (or random directions) of t."""
    if directions == 0:
        num = torch.zeros(t.numel(), dtype=t.dtype)
        for i in range(t.numel()):
            e = torch.zeros(t.numel(), dtype=t.dtype)
            e[i] = EPS
            e = e.reshape(t.shape)
            num[i] = (f(t + e) - f(t - e)) / (2 * EPS)
        return num.reshape(t.shape), None
    dirs = torch.randn(directions, *t.shape, generator=gen, dtype=t.dtype)
    vals = torch.stack([(f(t + EPS * d) - f(t - EPS * d)) / (2 * EPS) for d in dirs])
    return vals, dirs


CASES = [
    pytest.param("sh", "scale_rot", False, id="sh3-scalerot"),
    pytest.param("sh", "scale_rot", True, id="sh3-scalerot-aa"),
    pytest.param("precomp", "precomp", False, id="precomp-cov3d"),
    pytest.param("precomp", "precomp", True, id="precomp-cov3d-aa"),
]


@pytest.mark.parametrize("colors,covariance,aa", CASES)
def test_gradients_match_finite_differences(colors, covariance, aa, means2D_as_offset):
    scene = fd_scene(
        colors,
        covariance,
        aa,
        cx=None if colors == "sh" else 10.7,
        cy=None if colors == "sh" else 9.9,
    )
    cam = camera_matrices(
        scene.w2c, scene.fx, scene.fy, scene.width, scene.height, scene.cx, scene.cy
    )
    tensors = {k: v for k, v in scene.inputs().items() if v is not None}
    tensors["bg"] = scene.bg
    mats = {"viewmatrix": cam.viewmatrix, "projmatrix": cam.projmatrix, "campos": cam.campos,
            "tanfovx": cam.tanfovx, "tanfovy": cam.tanfovy}
    weights = output_weights(scene.height, scene.width)

    # every pixel covered, nothing near the thresholds the FD scene is meant to avoid
    with torch.no_grad():
        out0 = render(scene, tensors, mats)
    assert float(out0.alpha.min()) > 0.3 and float(out0.alpha.max()) < 0.999
    radii = out0.radii
    assert radii[:6].min() > 0 and radii[6:].max() == 0  # 6 visible, behind/near culled

    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in tensors.items()}
    mleaves = {
        k: v.detach().clone().requires_grad_(True)
        for k, v in mats.items()
        if isinstance(v, torch.Tensor)
    }
    loss = weighted_loss(render(scene, leaves, {**mats, **mleaves}), weights)
    loss.backward()

    gen = torch.Generator().manual_seed(3)
    all_inputs = [(k, leaves, tensors) for k in leaves] + [(k, mleaves, mats) for k in mleaves]
    for name, holder, base in all_inputs:
        x0 = base[name].detach()

        def f(x, name=name, holder_is_mats=(holder is mleaves)):
            t2 = dict(tensors)
            m2 = dict(mats)
            (m2 if holder_is_mats else t2)[name] = x
            with torch.no_grad():
                return weighted_loss(render(scene, t2, m2), weights)

        grad = holder[name].grad
        # only legitimate when the output does not depend on it (campos without SH)
        if grad is None:
            assert name == "campos" and scene.shs is None, f"no gradient reached {name}"
            grad = torch.zeros_like(x0)
        directions = 6 if x0.numel() > 24 else 0
        num, dirs = _fd_tensor(f, x0, directions, gen)
        if dirs is None:
            _check(name, grad, num)
        else:
            _check(name, (dirs * grad).flatten(1).sum(1), num)
        if name not in ("viewmatrix", "projmatrix", "campos", "bg"):
            # culled Gaussians (behind, near) get exactly zero gradient
            assert float(grad[6:].abs().max()) == 0.0, name


@pytest.mark.parametrize("colors,covariance,aa", CASES[:3])
def test_pose_twist_gradient_matches_finite_differences(colors, covariance, aa):
    """d loss / d xi at xi = 0 for w2c = se3_exp(xi) @ w2c0, through camera_matrices."""
    scene = fd_scene(colors, covariance, aa, seed=5, cx=None if colors == "sh" else 12.9)
    weights = output_weights(scene.height, scene.width, seed=2)
    inputs = scene.inputs()

    def loss_at(xi):
        w2c = se3_exp(xi) @ scene.w2c
        return weighted_loss(
            rasterize_gaussians(settings=scene.settings("reference", w2c=w2c), **inputs), weights
        )

    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    loss_at(xi).backward()
    num = torch.zeros(6, dtype=F64)
    with torch.no_grad():
        for i in range(6):
            e = torch.zeros(6, dtype=F64)
            e[i] = EPS
            num[i] = (loss_at(e) - loss_at(-e)) / (2 * EPS)
    _check("xi", xi.grad, num)
    assert float(xi.grad.abs().min()) > 0  # every dof is observed


def test_means2D_gradient_is_value_neutral_and_equal_to_offset_gradient(monkeypatch):
    scene = fd_scene("sh", "scale_rot", False)
    m2a = scene.means2D.clone().requires_grad_(True)
    out_a = rasterize_gaussians(
        settings=scene.settings("reference"), **{**scene.inputs(), "means2D": m2a}
    )
    weights = output_weights(scene.height, scene.width)
    weighted_loss(out_a, weights).backward()
    monkeypatch.setattr(ref_projection, "inject_means2D", lambda ndc_xy, m2: ndc_xy + m2)
    m2b = scene.means2D.clone().requires_grad_(True)
    out_b = rasterize_gaussians(
        settings=scene.settings("reference"), **{**scene.inputs(), "means2D": m2b}
    )
    weighted_loss(out_b, weights).backward()
    torch.testing.assert_close(out_a.color, out_b.color, rtol=0, atol=0)
    torch.testing.assert_close(m2a.grad, m2b.grad, rtol=1e-12, atol=1e-12)
    assert float(m2a.grad[:, 2].abs().max()) == 0.0  # the z component is unused
    # without means2D the render is identical
    out_c = rasterize_gaussians(
        settings=scene.settings("reference"), **{**scene.inputs(), "means2D": None}
    )
    torch.testing.assert_close(out_a.color, out_c.color, rtol=0, atol=0)


def test_gradcheck_small_scene():
    """torch.autograd.gradcheck (fast mode) on means3D, opacities, colors, cov3D and viewmatrix."""
    scene = fd_scene("precomp", "precomp", True, seed=7)
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)

    def fn(means3D, opacities, colors, cov3D, viewmatrix):
        out = rasterize_gaussians_reference(
            means3D,
            None,
            opacities,
            None,
            colors,
            None,
            None,
            cov3D,
            scene.bg,
            viewmatrix,
            cam.projmatrix,
            cam.campos,
            image_height=scene.height,
            image_width=scene.width,
            tanfovx=cam.tanfovx,
            tanfovy=cam.tanfovy,
            scale_modifier=1.0,
            sh_degree=0,
            prefiltered=False,
            antialiasing=True,
        )
        return out[0], out[2], out[3], out[4]

    args = [
        t.detach().clone().requires_grad_(True)
        for t in (
            scene.means3D,
            scene.opacities,
            scene.colors_precomp,
            scene.cov3D_precomp,
            cam.viewmatrix,
        )
    ]
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


# --------------------------------------------------------------------------------------------
# Independent check of the forward numerics: a literal, scalar transcription of upstream CUDA.
# --------------------------------------------------------------------------------------------

def _literal_upstream(scene: Scene):
    """Per-Gaussian preprocess and per-pixel front-to-back loop with Python floats."""
    H, W = scene.height, scene.width
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, W, H, scene.cx, scene.cy)
    V = cam.viewmatrix.tolist()
    PM = cam.projmatrix.tolist()
    campos = cam.campos
    tanx, tany = cam.tanfovx, cam.tanfovy
    fxx, fyy = W / (2 * tanx), H / (2 * tany)
    gx, gy = (W + 15) // 16, (H + 15) // 16
    P = scene.num_gaussians
    if scene.shs is not None:
        d = scene.means3D - campos
        rgb_all = torch.clamp_min(
            eval_sh(scene.sh_degree, scene.shs, d / d.norm(dim=-1, keepdim=True)) + 0.5, 0
        ).tolist()
    else:
        rgb_all = scene.colors_precomp.tolist()
    if scene.cov3D_precomp is not None:
        cov3 = scene.cov3D_precomp.tolist()
    else:
        cov3 = []
        for s, q in zip((scene.scales * scene.scale_modifier).tolist(), scene.rotations.tolist()):
            r, x, y, z = q
            R = [[1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)],
                 [2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)],
                 [2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)]]
            Sg = [
                [sum(R[i][k] * s[k] ** 2 * R[j][k] for k in range(3)) for j in range(3)]
                for i in range(3)
            ]
            cov3.append([Sg[0][0], Sg[0][1], Sg[0][2], Sg[1][1], Sg[1][2], Sg[2][2]])
    gs = []
    radii = [0] * P
    for i, m in enumerate(scene.means3D.tolist()):
        h = m + [1.0]
        t = [sum(h[k] * V[k][j] for k in range(4)) for j in range(3)]
        if t[2] <= 0.2:
            continue
        ph = [sum(h[k] * PM[k][j] for k in range(4)) for j in range(4)]
        pw = 1.0 / (ph[3] + 1e-7)
        ndc = [ph[0] * pw, ph[1] * pw]
        c = cov3[i]
        Sg = [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
        limx, limy = 1.3 * tanx, 1.3 * tany
        tx = min(limx, max(-limx, t[0] / t[2])) * t[2]
        ty = min(limy, max(-limy, t[1] / t[2])) * t[2]
        J = [[fxx / t[2], 0.0, -fxx * tx / t[2] ** 2], [0.0, fyy / t[2], -fyy * ty / t[2] ** 2]]
        Rw = [[V[j][k] for j in range(3)] for k in range(3)]  # viewmatrix[:3,:3].T
        T = [[sum(J[a][k] * Rw[k][b] for k in range(3)) for b in range(3)] for a in range(2)]
        cv = [
            [
                sum(T[a][k] * Sg[k][m] * T[b][m] for k in range(3) for m in range(3))
                for b in range(2)
            ]
            for a in range(2)
        ]
        det0 = cv[0][0] * cv[1][1] - cv[0][1] ** 2
        a_, b_, c_ = cv[0][0] + 0.3, cv[0][1], cv[1][1] + 0.3
        det = a_ * c_ - b_ * b_
        if det == 0:
            continue
        o = scene.opacities[i, 0].item()
        if scene.antialiasing:
            o *= math.sqrt(max(2.5e-5, det0 / det))
        conic = (c_ / det, -b_ / det, a_ / det)
        mid = 0.5 * (a_ + c_)
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        r = math.ceil(3 * math.sqrt(lam))
        px, py = ((ndc[0] + 1) * W - 1) / 2, ((ndc[1] + 1) * H - 1) / 2
        rmin = (min(gx, max(0, int((px - r) / 16))), min(gy, max(0, int((py - r) / 16))))
        rmax = (min(gx, max(0, int((px + r + 15) / 16))), min(gy, max(0, int((py + r + 15) / 16))))
        if (rmax[0] - rmin[0]) * (rmax[1] - rmin[1]) == 0:
            continue
        radii[i] = r
        gs.append((t[2], i, px, py, conic, o, rgb_all[i], rmin, rmax))
    gs.sort(key=lambda g: (g[0], g[1]))
    bg = scene.bg.tolist()
    img = torch.zeros(6, H, W, dtype=F64)
    for y in range(H):
        for x in range(W):
            tile = (x // 16, y // 16)
            T = 1.0
            C = [0.0] * 3
            invd = dacc = 0.0
            for z, i, px, py, conic, o, rgb, rmin, rmax in gs:
                if not (rmin[0] <= tile[0] < rmax[0] and rmin[1] <= tile[1] < rmax[1]):
                    continue
                dx, dy = px - x, py - y
                power = -0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy
                if power > 0:
                    continue
                alpha = min(0.99, o * math.exp(power))
                if alpha < 1 / 255:
                    continue
                test_T = T * (1 - alpha)
                if test_T < 1e-4:
                    break
                for ch in range(3):
                    C[ch] += rgb[ch] * alpha * T
                invd += alpha * T / z
                dacc += alpha * T * z
                T = test_T
            for ch in range(3):
                img[ch, y, x] = C[ch] + T * bg[ch]
            img[3, y, x], img[4, y, x], img[5, y, x] = invd, dacc, 1 - T
    return img, torch.tensor(radii, dtype=torch.int32)


@pytest.mark.parametrize(
    "kw",
    [
        dict(colors="sh", covariance="scale_rot", antialiasing=False),
        dict(colors="precomp", covariance="precomp", antialiasing=True, cx=9.0, cy=12.5),
        dict(colors="sh", covariance="scale_rot", antialiasing=True, scale_modifier=0.7, seed=3,
             opacity_range=(0.7, 0.99), scale_range=(0.05, 0.6)),  # opaque: exercises the T stop
    ],
    ids=["sh3", "precomp-aa-pp", "opaque-stop"],
)
def test_reference_matches_literal_upstream_loop(kw):
    scene = make_scene(60, height=20, width=40, dtype=F64, **kw)
    with torch.no_grad():
        color, radii, invdepth, depth_acc, alpha = rasterize_gaussians_reference(
            *[getattr(scene, k) for k in TENSOR_NAMES],
            *camera_matrices(
                scene.w2c, scene.fx, scene.fy, scene.width, scene.height, scene.cx, scene.cy
            )[:3],
            image_height=scene.height,
            image_width=scene.width,
            tanfovx=scene.width / (2 * scene.fx),
            tanfovy=scene.height / (2 * scene.fy),
            scale_modifier=scene.scale_modifier,
            sh_degree=scene.sh_degree,
            prefiltered=False,
            antialiasing=scene.antialiasing,
        )
    img, radii_lit = _literal_upstream(scene)
    assert torch.equal(radii, radii_lit)
    torch.testing.assert_close(color, img[:3], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(invdepth, img[3:4], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(depth_acc, img[4:5], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(alpha, img[5:6], rtol=1e-9, atol=1e-9)
    if kw.get("opacity_range"):
        assert float(alpha.max()) > 0.999  # some pixels reached the stop
