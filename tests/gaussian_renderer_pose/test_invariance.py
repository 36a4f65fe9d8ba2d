"""Rendering at pose T equals rendering the Gaussians moved by T at the identity pose.

The image and the gradient w.r.t. a left pose twist (w2c = se3_exp(xi) @ w2c0) alike.

Moving by T = [R t]: means -> R m + t; rotations -> q_R (x) q (quaternion product; exact for unit
quaternions, since the upstream formula is not homogeneous in q); cov3D -> R Sigma R^T (exact for
any Sigma); SH degree 1 band-1 coefficients rotate as the vector u = (-s3, -s1, s2) -> R u.
"""
from __future__ import annotations

import pytest
import torch

from gaussian_renderer_pose import rasterize_gaussians
from tests.helpers.scenes import Scene, make_scene, se3_exp

def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z) of a rotation matrix (Shepperd, branch on the largest component)."""
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    cands = torch.stack([tr, m[0, 0], m[1, 1], m[2, 2]])
    k = int(torch.argmax(cands))
    if k == 0:
        w = torch.sqrt(1 + tr) / 2
        q = [
            w,
            (m[2, 1] - m[1, 2]) / (4 * w),
            (m[0, 2] - m[2, 0]) / (4 * w),
            (m[1, 0] - m[0, 1]) / (4 * w),
        ]
    elif k == 1:
        x = torch.sqrt(1 + m[0, 0] - m[1, 1] - m[2, 2]) / 2
        q = [
            (m[2, 1] - m[1, 2]) / (4 * x),
            x,
            (m[0, 1] + m[1, 0]) / (4 * x),
            (m[0, 2] + m[2, 0]) / (4 * x),
        ]
    elif k == 2:
        y = torch.sqrt(1 - m[0, 0] + m[1, 1] - m[2, 2]) / 2
        q = [
            (m[0, 2] - m[2, 0]) / (4 * y),
            (m[0, 1] + m[1, 0]) / (4 * y),
            y,
            (m[1, 2] + m[2, 1]) / (4 * y),
        ]
    else:
        z = torch.sqrt(1 - m[0, 0] - m[1, 1] + m[2, 2]) / 2
        q = [
            (m[1, 0] - m[0, 1]) / (4 * z),
            (m[0, 2] + m[2, 0]) / (4 * z),
            (m[1, 2] + m[2, 1]) / (4 * z),
            z,
        ]
    return torch.stack(q)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def moved_scene(scene: Scene) -> Scene:
    """The same picture at the identity pose: Gaussians moved by the scene's w2c."""
    T = scene.w2c
    R, t = T[:3, :3], T[:3, 3]
    s = scene.to()
    s.means3D = scene.means3D @ R.T + t
    if scene.rotations is not None:
        s.rotations = quat_mul(rotmat_to_quat(R).expand_as(scene.rotations), scene.rotations)
    if scene.cov3D_precomp is not None:
        c = scene.cov3D_precomp
        S = torch.stack([c[:, [0, 1, 2]], c[:, [1, 3, 4]], c[:, [2, 4, 5]]], -2)
        S2 = R @ S @ R.T
        s.cov3D_precomp = torch.stack(
            [S2[:, 0, 0], S2[:, 0, 1], S2[:, 0, 2], S2[:, 1, 1], S2[:, 1, 2], S2[:, 2, 2]], -1
        )
    if scene.shs is not None:
        assert scene.sh_degree <= 1
        shs = scene.shs.clone()
        # [P, 3(xyz), 3(rgb)]
        u = torch.stack([-scene.shs[:, 3], -scene.shs[:, 1], scene.shs[:, 2]], 1)
        u2 = torch.einsum("ij,pjc->pic", R, u)
        shs[:, 1], shs[:, 2], shs[:, 3] = -u2[:, 1], u2[:, 2], -u2[:, 0]
        s.shs = shs
    s.w2c = torch.eye(4, dtype=T.dtype)
    return s


def render_with_twist(scene: Scene, backend: str, weights):
    xi = torch.zeros(6, dtype=scene.w2c.dtype, requires_grad=True)
    w2c = se3_exp(xi) @ scene.w2c
    out = rasterize_gaussians(settings=scene.settings(backend, w2c=w2c), **scene.inputs())
    loss = sum((getattr(out, k) * w).sum() for k, w in weights.items())
    loss.backward()
    return out, xi.grad


CASES = [
    pytest.param(
        dict(colors="precomp", covariance="scale_rot", sh_degree=0), id="precomp-colors-quat"
    ),
    pytest.param(
        dict(colors="precomp", covariance="precomp", sh_degree=0, antialiasing=True), id="cov3d-aa"
    ),
    pytest.param(dict(colors="sh", covariance="precomp", sh_degree=0), id="sh0"),
    pytest.param(
        dict(colors="sh", covariance="scale_rot", sh_degree=1, cx=25.0, cy=30.0), id="sh1-pp"
    ),
]


@pytest.mark.parametrize("kw", CASES)
def test_pose_equals_moved_gaussians(backend, backend_dtype, kw):
    dtype = backend_dtype
    scene = make_scene(120, height=40, width=56, seed=11, dtype=torch.float64, **kw)
    if scene.rotations is not None:  # composition is exact for unit quaternions only
        scene.rotations = scene.rotations / scene.rotations.norm(dim=-1, keepdim=True)
    moved = moved_scene(scene)
    scene, moved = scene.to(dtype=dtype), moved.to(dtype=dtype)
    g = torch.Generator().manual_seed(5)
    weights = {k: torch.rand(c, 40, 56, generator=g, dtype=torch.float64).to(dtype)
               for k, c in (("color", 3), ("invdepth", 1), ("depth", 1), ("alpha", 1))}
    out_a, grad_a = render_with_twist(scene, backend, weights)
    out_b, grad_b = render_with_twist(moved, backend, weights)
    tol = dict(rtol=1e-7, atol=1e-8) if dtype == torch.float64 else dict(rtol=2e-3, atol=2e-3)
    assert torch.equal(out_a.radii, out_b.radii) or dtype == torch.float32
    for k in ("color", "invdepth", "depth", "alpha"):
        torch.testing.assert_close(getattr(out_a, k), getattr(out_b, k), **tol)
    assert float(out_a.alpha.detach().max()) > 0.5  # the scene is not empty
    torch.testing.assert_close(
        grad_a,
        grad_b,
        rtol=1e-6 if dtype == torch.float64 else 2e-2,
        atol=1e-6 * float(grad_a.abs().max())
        if dtype == torch.float64
        else 1e-2 * float(grad_a.abs().max()),
    )
