"""Deterministic random Gaussian scenes for the renderer tests (reference, native, benchmark).

`make_scene(P, ...)` builds Gaussians in the CAMERA frame and moves them to the world with the
scene's pose, so that every random scene contains, in controlled proportions:
- anisotropic Gaussians (independent log-uniform scales per axis) with UNNORMALISED quaternions,
- Gaussians partly off screen (centres beyond the image border),
- Gaussians behind the camera or nearer than the 0.2 cull plane,
- overlapping Gaussians (a dense cluster near the image centre).

Usage:
    scene = make_scene(200, sh_degree=3)
    out = rasterize_gaussians(settings=scene.settings(backend="reference"), **scene.inputs())
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Iterable, Optional, Sequence

import torch

from gaussian_renderer_pose.camera import camera_matrices
from gaussian_renderer_pose.rasterizer import GaussianRasterizationSettings
from gaussian_renderer_pose.reference.projection import quat_to_rotmat_unnormalised

TENSOR_NAMES = (
    "means3D",
    "means2D",
    "opacities",
    "shs",
    "colors_precomp",
    "scales",
    "rotations",
    "cov3D_precomp",
    "bg",
)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of NORMALISED quaternions (w, x, y, z), [..., 4] -> [..., 3, 3]."""
    return quat_to_rotmat_unnormalised(q / q.norm(dim=-1, keepdim=True))


def cov3d_from_scale_rot(
    scales: torch.Tensor, rotations: torch.Tensor, modifier: float = 1.0
) -> torch.Tensor:
    """[P, 6] (xx, xy, xz, yy, yz, zz) of R S^2 R^T with R from the normalised quaternion."""
    R = quat_to_rotmat(rotations)
    M = R * (scales * modifier)[..., None, :]
    S = M @ M.transpose(-1, -2)
    return torch.stack([S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]], -1)


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rodrigues, [3] -> [3, 3] (test helper, exact enough away from 0 and at 0)."""
    theta = phi.norm()
    K = torch.zeros(3, 3, dtype=phi.dtype, device=phi.device)
    K[0, 1], K[0, 2], K[1, 2] = -phi[2], phi[1], -phi[0]
    K = K - K.T
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    if float(theta) < 1e-8:
        return eye + K + 0.5 * K @ K
    return eye + torch.sin(theta) / theta * K + (1 - torch.cos(theta)) / theta**2 * (K @ K)


def hat(v: torch.Tensor) -> torch.Tensor:
    """[3] -> skew-symmetric [3, 3] (differentiable)."""
    z = torch.zeros((), dtype=v.dtype, device=v.device)
    return torch.stack(
        [
            torch.stack([z, -v[2], v[1]]),
            torch.stack([v[2], z, -v[0]]),
            torch.stack([-v[1], v[0], z]),
        ]
    )


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """xi = (rho, phi) [6] -> [4, 4] via the matrix exponential of the twist (differentiable)."""
    X = torch.zeros(4, 4, dtype=xi.dtype, device=xi.device)
    X = X + torch.nn.functional.pad(hat(xi[3:]), (0, 1, 0, 1))
    X = X + torch.nn.functional.pad(xi[:3, None], (3, 0, 0, 1))
    return torch.linalg.matrix_exp(X)


def random_w2c(
    generator: torch.Generator, dtype=torch.float64, rot: float = 0.3, trans: float = 0.3
) -> torch.Tensor:
    phi = (torch.rand(3, generator=generator, dtype=torch.float64) * 2 - 1) * rot
    t = (torch.rand(3, generator=generator, dtype=torch.float64) * 2 - 1) * trans
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = so3_exp(phi)
    w2c[:3, 3] = t
    return w2c.to(dtype)


@dataclass
class Scene:
    means3D: torch.Tensor  # [P, 3] world
    means2D: torch.Tensor  # [P, 3] zeros (gradient holder)
    opacities: torch.Tensor  # [P, 1]
    shs: Optional[torch.Tensor]  # [P, 16, 3] (or (D+1)^2 coefficients) when colors == "sh"
    colors_precomp: Optional[torch.Tensor]  # [P, 3] when colors == "precomp"
    scales: Optional[torch.Tensor]  # [P, 3] when covariance == "scale_rot"
    rotations: Optional[torch.Tensor]  # [P, 4] unnormalised (w, x, y, z)
    cov3D_precomp: Optional[torch.Tensor]  # [P, 6] when covariance == "precomp"
    bg: torch.Tensor  # [3]
    w2c: torch.Tensor  # [4, 4]
    fx: float
    fy: float
    height: int
    width: int
    sh_degree: int
    scale_modifier: float = 1.0
    antialiasing: bool = False
    cx: Optional[float] = None
    cy: Optional[float] = None
    extras: Dict[str, object] = field(default_factory=dict)

    @property
    def num_gaussians(self) -> int:
        return int(self.means3D.shape[0])

    def settings(
        self, backend: str = "auto", w2c: Optional[torch.Tensor] = None
    ) -> GaussianRasterizationSettings:
        """Settings for this scene, matrices via `camera_matrices`.

        Pass a grad-requiring w2c for pose gradients.
        """
        cam = camera_matrices(
            self.w2c if w2c is None else w2c,
            self.fx,
            self.fy,
            self.width,
            self.height,
            self.cx,
            self.cy,
        )
        return GaussianRasterizationSettings(
            image_height=self.height,
            image_width=self.width,
            tanfovx=cam.tanfovx,
            tanfovy=cam.tanfovy,
            bg=self.bg,
            scale_modifier=self.scale_modifier,
            viewmatrix=cam.viewmatrix,
            projmatrix=cam.projmatrix,
            sh_degree=self.sh_degree,
            campos=cam.campos,
            prefiltered=False,
            debug=False,
            antialiasing=self.antialiasing,
            backend=backend,
        )

    def inputs(self) -> Dict[str, Optional[torch.Tensor]]:
        """kwargs for `rasterize_gaussians(settings=..., **scene.inputs())`.

        Absent tensors are None.
        """
        return {
            "means3D": self.means3D,
            "opacities": self.opacities,
            "means2D": self.means2D,
            "shs": self.shs,
            "colors_precomp": self.colors_precomp,
            "scales": self.scales,
            "rotations": self.rotations,
            "cov3D_precomp": self.cov3D_precomp,
        }

    def to(self, device=None, dtype=None) -> "Scene":
        """A copy with every tensor moved/cast (w2c included)."""
        kw = {}
        for name in TENSOR_NAMES + ("w2c",):
            t = getattr(self, name)
            kw[name] = None if t is None else t.detach().to(device=device, dtype=dtype).clone()
        rest = {
            k: getattr(self, k)
            for k in (
                "fx",
                "fy",
                "height",
                "width",
                "sh_degree",
                "scale_modifier",
                "antialiasing",
                "cx",
                "cy",
            )
        }
        return Scene(**kw, **rest, extras=dict(self.extras))


def scene_tensors_requiring_grad(
    scene: Scene, names: Optional[Iterable[str]] = None
) -> Dict[str, torch.Tensor]:
    """Make the scene's present tensors fresh leaves requiring grad.

    All of TENSOR_NAMES, or `names`. Mutates `scene` in place and returns {name: leaf tensor}.
    """
    out = {}
    for name in TENSOR_NAMES if names is None else names:
        t = getattr(scene, name)
        if t is None:
            continue
        leaf = t.detach().clone().requires_grad_(True)
        setattr(scene, name, leaf)
        out[name] = leaf
    return out


def make_scene(
    num_gaussians: int,
    *,
    height: int = 48,
    width: int = 64,
    sh_degree: int = 3,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    colors: str = "sh",
    covariance: str = "scale_rot",
    bg: Sequence[float] = (0.2, 0.5, 0.8),
    scale_modifier: float = 1.0,
    antialiasing: bool = False,
    w2c: Optional[torch.Tensor] = None,
    sh_coeffs: int = 16,
    scale_range: Sequence[float] = (0.02, 0.4),
    depth_range: Sequence[float] = (1.5, 6.0),
    opacity_range: Sequence[float] = (0.1, 0.95),
    frac_behind: float = 0.1,
    frac_offscreen: float = 0.2,
    frac_cluster: float = 0.2,
    fx: Optional[float] = None,
    fy: Optional[float] = None,
    cx: Optional[float] = None,
    cy: Optional[float] = None,
    device: Optional[torch.device] = None,
) -> Scene:
    """A deterministic random scene (torch.Generator seeded with `seed`).

    See the module docstring.
    """
    if colors not in ("sh", "precomp"):
        raise ValueError(f"colors must be 'sh' or 'precomp', got {colors!r}")
    if covariance not in ("scale_rot", "precomp"):
        raise ValueError(f"covariance must be 'scale_rot' or 'precomp', got {covariance!r}")
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    P = num_gaussians

    def U(*shape, lo=0.0, hi=1.0):
        return torch.rand(*shape, generator=g, dtype=f64) * (hi - lo) + lo

    fx = float(0.9 * width) if fx is None else float(fx)
    fy = float(0.95 * width) if fy is None else float(fy)
    tanx, tany = width / (2 * fx), height / (2 * fy)
    if w2c is None:
        w2c = random_w2c(g)
    w2c = w2c.detach().to(f64)

    # Category per Gaussian: 0 on screen, 1 partly off screen, 2 behind/near, 3 overlapping cluster.
    cat = torch.zeros(P, dtype=torch.long)
    u = U(P)
    cat[u < frac_behind + frac_offscreen + frac_cluster] = 3
    cat[u < frac_behind + frac_offscreen] = 1
    cat[u < frac_behind] = 2
    z = U(P, lo=depth_range[0], hi=depth_range[1])
    sx = U(P, lo=-0.95, hi=0.95)
    sy = U(P, lo=-0.95, hi=0.95)
    # off screen: |x/z| in [1.0, 1.4] tan (beyond the border, some past the 1.3 clamp)
    off = cat == 1
    sgn = torch.where(U(P) < 0.5, -1.0, 1.0).to(f64)
    mag = U(P, lo=1.0, hi=1.4)
    which = U(P) < 0.5
    sx = torch.where(off & which, sgn * mag, sx)
    sy = torch.where(off & ~which, sgn * mag, sy)
    # behind / near: z in [-1.5, 0.25]
    z = torch.where(cat == 2, U(P, lo=-1.5, hi=0.25), z)
    # cluster: near the centre at similar depth
    cl = cat == 3
    sx = torch.where(cl, U(P, lo=-0.25, hi=0.25), sx)
    sy = torch.where(cl, U(P, lo=-0.25, hi=0.25), sy)
    z = torch.where(cl, U(P, lo=2.5, hi=3.5), z)
    zpos = torch.where(z.abs() < 1e-3, torch.full_like(z, 1e-3), z)
    x_cam = torch.stack([sx * tanx * zpos.abs(), sy * tany * zpos.abs(), z], -1)
    c2w = torch.linalg.inv(w2c)
    means = x_cam @ c2w[:3, :3].T + c2w[:3, 3]

    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(U(P, 3, lo=lo, hi=hi))  # independent per axis -> anisotropic
    quats = torch.randn(P, 4, generator=g, dtype=f64)
    quats = quats / quats.norm(dim=-1, keepdim=True) * U(P, 1, lo=0.5, hi=2.0)  # unnormalised
    opac = U(P, 1, lo=opacity_range[0], hi=opacity_range[1])
    shs = torch.randn(P, sh_coeffs, 3, generator=g, dtype=f64) * 0.25
    shs[:, 0] = torch.randn(P, 3, generator=g, dtype=f64) * 0.8
    cols = U(P, 3)

    def cast(t):
        return t.to(dtype=dtype, device=device)

    scene = Scene(
        means3D=cast(means),
        means2D=torch.zeros(P, 3, dtype=dtype, device=device),
        opacities=cast(opac),
        shs=cast(shs) if colors == "sh" else None,
        colors_precomp=cast(cols) if colors == "precomp" else None,
        scales=cast(scales) if covariance == "scale_rot" else None,
        rotations=cast(quats) if covariance == "scale_rot" else None,
        cov3D_precomp=cast(cov3d_from_scale_rot(scales, quats, scale_modifier))
        if covariance == "precomp"
        else None,
        bg=torch.tensor(list(bg), dtype=dtype, device=device),
        w2c=cast(w2c),
        fx=fx,
        fy=fy,
        height=height,
        width=width,
        sh_degree=sh_degree,
        scale_modifier=scale_modifier,
        antialiasing=antialiasing,
        cx=cx,
        cy=cy,
        extras={"category": cat},
    )
    return scene
