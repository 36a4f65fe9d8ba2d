"""The CPU preprocess on vectors of Gaussians writes the same records as the scalar path.

csrc/cpu/preprocess_simd.h against common/raster.h preprocess_gaussian.

With one thread the Gaussians are processed in whole vectors from the first, and the last
``P mod lanes`` (lanes = 4, 8 or 16) by the scalar path. Rolling the Gaussians moves different ones
into that tail: each record (and radius) must be the same wherever the Gaussian sits.
"""
from __future__ import annotations

import math

import pytest
import torch

from gaussian_renderer_pose import _backend

pytestmark = pytest.mark.skipif(not _backend.native_status("cpu")[0],
                                reason="native CPU backend not built")

P = 16 * 40 + 15  # a tail of 15 mod lanes Gaussians


def _scene(sh_degree: int, seed: int = 0):
    """Gaussians around the camera.

    In view, behind, at the near plane, off screen, tiny, huge, beyond the Jacobian clamp.
    """
    from icomma_plugin.app.demo_scene import raster_bench_scene

    sc = raster_bench_scene(P, 64, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    w2c = sc["viewmatrix"].T
    c2w = torch.linalg.inv(w2c)
    cam = torch.randn(P, 3, generator=g) * torch.tensor([2.0, 2.0, 1.5]) + torch.tensor(
        [0.0, 0.0, 2.0])
    cam[::17, 2] = 0.2  # on the near plane
    cam[1::19, 2] = -1.0  # behind
    cam[2::23, 0] = 40.0  # far off screen / clamped Jacobian
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]
    scales = torch.exp(torch.randn(P, 3, generator=g) * 1.5 - 3.0)
    scales[3::29] = 1e-7  # degenerate
    sc.update(means3D=means.contiguous(), scales=scales.contiguous())
    sc["shs"] = sc["shs"][:, : (sh_degree + 1) ** 2].contiguous()
    sc["settings"]["sh_degree"] = sh_degree
    return sc


def _forward(sc, order, colors=False, antialiasing=False):
    from gaussian_renderer_pose import _ops

    s = sc["settings"]
    shs = None if colors else sc["shs"][order].contiguous()
    col = (torch.rand(P, 3, generator=torch.Generator().manual_seed(7))[order].contiguous()
           if colors else None)
    out = _ops.rasterize_forward(
        sc["means3D"][order].contiguous(), sc["opacities"][order].contiguous(), shs, col,
        sc["scales"][order].contiguous(), sc["rotations"][order].contiguous(), None, sc["bg"],
        sc["viewmatrix"], sc["projmatrix"], sc["campos"], s["image_height"], s["image_width"],
        s["tanfovx"], s["tanfovy"], 1.0, s["sh_degree"], False, antialiasing, None)
    return out[4], out[5]  # radii, geom


@pytest.mark.parametrize("sh_degree, colors, antialiasing", [
    (0, False, False), (1, False, True), (2, False, False), (3, False, False), (3, True, True),
])
def test_vector_and_scalar_preprocess_agree(sh_degree, colors, antialiasing):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        sc = _scene(sh_degree)
        base = torch.arange(P)
        radii0, geom0 = _forward(sc, base, colors, antialiasing)
        assert (radii0 > 0).sum() > 100 and (radii0 == 0).sum() > 20  # both kinds present
        for shift in range(1, 30):
            order = torch.roll(base, 15 * shift + 3 * shift * shift)
            radii, geom = _forward(sc, order, colors, antialiasing)
            assert torch.equal(radii, radii0[order])
            # The same float operations in the same order; GCC may still fuse a product into an
            # FMA in one path and not the other (it depends on the inlining context), so allow
            # a few ulp. (The build measured for docs/SPEED.md wrote the same bits.)
            torch.testing.assert_close(geom, geom0[order], rtol=4e-6, atol=1e-6)
    finally:
        torch.set_num_threads(threads)
    assert math.isfinite(float(geom0[radii0 > 0].sum()))
