"""SH coefficients in two tensors (``shs`` [P, 1, 3] and ``shs_rest`` [P, M - 1, 3]).

A fitter keeps the first coefficient and the others as separate parameters; the rasterizer takes
them as they are. The images and every gradient must be those of their concatenation: the same
bits on the CPU kernel (it reads the same values), the same values on the reference.
"""
from __future__ import annotations

import pytest
import torch

from gaussian_renderer_pose import GaussianRasterizationSettings, rasterize_gaussians
from gaussian_renderer_pose._validate import RasterizerInputError
from gaussian_renderer_pose.camera import camera_matrices
from tests.helpers.scenes import make_scene


def _render(scene, backend, split, *, threads=None, cot_seed=3):
    """Images and gradients (per leaf name) of sum(out * cot) with the SH joined or split."""
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    settings = GaussianRasterizationSettings(
        image_height=scene.height, image_width=scene.width, tanfovx=cam.tanfovx,
        tanfovy=cam.tanfovy, bg=scene.bg, scale_modifier=1.0, viewmatrix=cam.viewmatrix,
        projmatrix=cam.projmatrix, sh_degree=scene.sh_degree, campos=cam.campos,
        prefiltered=False, debug=False, antialiasing=scene.antialiasing, backend=backend)
    leaves = {n: getattr(scene, n).detach().clone().requires_grad_(True)
              for n in ("means3D", "opacities", "scales", "rotations")}
    sh = scene.shs.detach()
    if split:
        leaves["dc"] = sh[:, :1].clone().requires_grad_(True)
        leaves["rest"] = sh[:, 1:].clone().requires_grad_(True)
        shs = {"shs": leaves["dc"], "shs_rest": leaves["rest"]}
    else:
        leaves["shs"] = sh.clone().requires_grad_(True)
        shs = {"shs": leaves["shs"]}
    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        out = rasterize_gaussians(leaves["means3D"], leaves["opacities"], settings,
                                  scales=leaves["scales"], rotations=leaves["rotations"], **shs)
        g = torch.Generator().manual_seed(cot_seed)
        loss = sum((o * torch.randn(o.shape, generator=g)).sum()
                   for o in (out.color, out.invdepth, out.alpha))
        loss.backward()
    finally:
        torch.set_num_threads(old)
    grads = {n: t.grad for n, t in leaves.items()}
    if split:
        grads["shs"] = torch.cat([grads.pop("dc"), grads.pop("rest")], dim=1)
    return [out.color, out.invdepth, out.depth, out.alpha], grads


@pytest.mark.parametrize("sh_degree, coeffs, num, antialiasing, threads", [
    (3, 16, 203, False, 2),   # not a whole number of vectors: the preprocess's scalar tail
    (1, 16, 64, True, 1),     # coefficients that are never read: their gradient is zero
    (0, 4, 97, False, 2),
    (2, 9, 300, False, 2),
])
def test_cpu_kernel_gives_the_bits_of_the_concatenation(sh_degree, coeffs, num, antialiasing,
                                                        threads):
    scene = make_scene(num, height=40, width=56, sh_degree=sh_degree, seed=19 + sh_degree,
                       antialiasing=antialiasing, sh_coeffs=coeffs)
    joined_out, joined = _render(scene, "cpu", split=False, threads=threads)
    split_out, split = _render(scene, "cpu", split=True, threads=threads)
    for a, b in zip(joined_out, split_out):
        assert torch.equal(a, b)
    assert set(joined) == set(split)
    for name in joined:
        assert torch.equal(joined[name], split[name]), f"{name}: split SH changed the gradient"
    n_read = (sh_degree + 1) ** 2
    assert bool((split["shs"][:, :n_read] != 0).any())
    assert not bool(split["shs"][:, n_read:].any()), "unread coefficients got a gradient"


def test_reference_joins_the_two_tensors():
    scene = make_scene(40, height=24, width=32, sh_degree=2, seed=5, sh_coeffs=9)
    joined_out, joined = _render(scene, "reference", split=False)
    split_out, split = _render(scene, "reference", split=True)
    for a, b in zip(joined_out, split_out):
        assert torch.equal(a, b)
    for name in joined:
        torch.testing.assert_close(split[name], joined[name], rtol=0, atol=0)


def test_cpu_kernel_matches_the_reference_with_split_sh():
    scene = make_scene(120, height=32, width=40, sh_degree=3, seed=8)
    ref_out, ref = _render(scene, "reference", split=True)
    cpu_out, cpu = _render(scene, "cpu", split=True)
    torch.testing.assert_close(cpu_out[0], ref_out[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(cpu["shs"], ref["shs"], rtol=1e-3, atol=1e-5)


def _settings(sh_degree=1):
    scene = make_scene(8, height=16, width=16, sh_degree=sh_degree, seed=2, sh_coeffs=4)
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    s = GaussianRasterizationSettings(
        image_height=16, image_width=16, tanfovx=cam.tanfovx, tanfovy=cam.tanfovy, bg=scene.bg,
        scale_modifier=1.0, viewmatrix=cam.viewmatrix, projmatrix=cam.projmatrix,
        sh_degree=sh_degree, campos=cam.campos, prefiltered=False, debug=False, backend="cpu")
    return scene, s


@pytest.mark.parametrize("shs, rest, message", [
    (None, "ok", "shs_rest must come with shs"),
    ("all", "ok", r"shs \(with shs_rest\) must have shape \[8, 1, 3\]"),
    ("dc", "short", r"at least \(sh_degree\+1\)\*\*2 = 4 coefficients .* got 1 \+ 2"),
    ("dc", "double", "shs_rest must have the same dtype"),
])
def test_bad_split_sh_is_named(shs, rest, message):
    scene, settings = _settings()
    sh = scene.shs
    first = {"all": sh, "dc": sh[:, :1], None: None}[shs]
    others = {"ok": sh[:, 1:], "short": sh[:, 1:3], "double": sh[:, 1:].double()}[rest]
    colors = torch.rand(8, 3) if first is None else None
    with pytest.raises(RasterizerInputError, match=message):
        rasterize_gaussians(scene.means3D, scene.opacities, settings, shs=first, shs_rest=others,
                            colors_precomp=colors, scales=scene.scales, rotations=scene.rotations)
