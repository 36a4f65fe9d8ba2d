"""A deterministic, procedurally textured 3DGS scene for demos, tests and benchmarks.

`build_demo_scene(path, seed)` writes (once; later calls reuse the cache):

```
<path>/
  cfg_args, cameras.json, input.ply,         # the upstream 3DGS model-folder layout
  point_cloud/iteration_<N>/point_cloud.ply  # (icomma_plugin.io.model_folder.write_model_folder)
  query.png                                  # the query photo, rendered at a hidden pose
  query_gt.json                              # that pose + intrinsics (read only to report errors)
  init_c2w.txt                               # the initial guess: 4x4 camera-to-world, OpenCV axes
  demo.json                                  # manifest: build parameters, scene centre/scale
```

Scene (world frame z up, metres-ish): a 5 x 5 ground plane with a checker/blob/glyph texture, a
cube and two boxes whose faces carry different procedural textures (coloured noise blobs,
stripes, checkers, glyph-like shapes), all tiled with thin disc-shaped Gaussians (about 11k in
total at the default spacing), plus a baked per-face shading. A ring of 12 cameras looks at the
scene centre (`cameras.json`). The query camera sits at a random azimuth off the ring; the initial
pose is the query pose rotated by 20-40 degrees about a random axis through the SCENE CENTRE (as
iComMa / iNeRF perturb about the world origin, which moves the camera centre too) plus a small
random translation: `icomma_plugin.pose.convert.perturb_pose(..., pivot=centre)`.

Camera axes are OpenCV (x right, y down, z forward); poses are camera-to-world unless named w2c.
"""
from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple, Union

import numpy as np
import torch

from ..camera import Intrinsics
from ..gaussians import GaussianModel, rgb_to_sh
from ..pose.convert import invert_rigid, look_at_c2w, perturb_pose, rotation_about_axis

logger = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]

#: Bump when the generated content changes, so that stale caches are rebuilt.
DEMO_VERSION = 3
#: The point_cloud/iteration_<N> the demo model is written as.
DEMO_ITERATION = 30000


def default_demo_path(seed: int = 0) -> Path:
    """`./outputs/demo_scene` for seed 0, `./outputs/demo_scene_seed<N>` otherwise (absolute).

    Relative to the current folder, beside the tools' Hydra outputs (`outputs/localize/...`), so
    that an installed package never writes into site-packages; `make demo` runs in the checkout
    and so keeps its cache in `<repo>/outputs/demo_scene`.
    """
    name = "demo_scene" if seed == 0 else f"demo_scene_seed{seed}"
    return Path.cwd() / "outputs" / name


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion of a proper rotation matrix."""
    m = R
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


# ----------------------------------------------------------------------------------------------
# procedural textures: an [h, w, 3] float image in [0, 1], one texel per Gaussian
# ----------------------------------------------------------------------------------------------


def _palette(rng: np.random.Generator, n: int) -> np.ndarray:
    """`n` saturated, varied colours (random hues, alternating light/dark)."""
    hues = (rng.uniform() + np.arange(n) * 0.61803398875) % 1.0
    out = []
    for i, h in enumerate(hues):
        s = rng.uniform(0.55, 1.0)
        v = rng.uniform(0.75, 1.0) if i % 2 == 0 else rng.uniform(0.25, 0.5)
        out.append(_hsv_to_rgb(h, s, v))
    return np.asarray(out)


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.asarray([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def _blobs(rng, img, n, rmin, rmax):
    h, w, _ = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    cols = _palette(rng, n)
    for c in cols:
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        r = rng.uniform(rmin, rmax)
        wgt = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r))[..., None]
        img[:] = img * (1 - 0.85 * wgt) + c * 0.85 * wgt
    return img


def _glyphs(rng, img, n, smin, smax):
    """Stamp `n` hard-edged glyph-like shapes (boxes, rings, crosses, triangles, L/T bars)."""
    h, w, _ = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    cols = _palette(rng, n)
    for c in cols:
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        s = rng.uniform(smin, smax)
        dy, dx = yy - cy, xx - cx
        ang = rng.uniform(0, np.pi)
        u, v = dx * math.cos(ang) + dy * math.sin(ang), -dx * math.sin(ang) + dy * math.cos(ang)
        kind = rng.integers(0, 6)
        if kind == 0:
            m = (np.abs(u) < s) & (np.abs(v) < s * rng.uniform(0.3, 1.0))
        elif kind == 1:
            r = np.sqrt(u * u + v * v)
            m = (r < s) & (r > s * 0.55)
        elif kind == 2:
            t = s * 0.3
            m = ((np.abs(u) < t) & (np.abs(v) < s)) | ((np.abs(v) < t) & (np.abs(u) < s))
        elif kind == 3:
            m = (v > -s) & (v < s) & (np.abs(u) < (v + s) * 0.5)
        elif kind == 4:  # L
            t = s * 0.35
            m = ((np.abs(u + s * 0.5) < t) & (np.abs(v) < s)) | (
                (np.abs(v - s * 0.7) < t) & (np.abs(u) < s)
            )
        else:  # T
            t = s * 0.3
            m = ((np.abs(u) < t) & (np.abs(v) < s)) | ((np.abs(v + s * 0.75) < t) & (np.abs(u) < s))
        img[m] = c
    return img


def _stripes(rng, h, w):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    ang = rng.uniform(0, np.pi)
    period = rng.uniform(5, 9)
    s = xx * math.cos(ang) + yy * math.sin(ang)
    cols = _palette(rng, 3)
    idx = (np.floor(s / period) % 3).astype(int)
    return cols[idx]


def _checker(rng, h, w, cell):
    yy, xx = np.mgrid[0:h, 0:w]
    cols = _palette(rng, 2)
    idx = ((yy // cell + xx // cell) % 2).astype(int)
    return cols[idx]


def paint_texture(rng: np.random.Generator, h: int, w: int, style: str) -> np.ndarray:
    """Procedural texture `[h, w, 3]` in [0, 1] (one texel per Gaussian).

    Styles: checker, stripes, blobs, glyphs, ground.
    """
    area = h * w
    if style == "checker":
        img = _checker(rng, h, w, cell=max(3, int(rng.uniform(0.12, 0.2) * min(h, w))))
        img = _glyphs(rng, img, max(2, area // 500), 2.0, 4.0)
    elif style == "stripes":
        img = _stripes(rng, h, w)
        img = _glyphs(rng, img, max(3, area // 350), 2.0, 4.5)
    elif style == "blobs":
        img = np.tile(_palette(rng, 1)[0], (h, w, 1))
        img = _blobs(rng, img, max(6, area // 60), 1.5, 4.0)
        img = _glyphs(rng, img, max(2, area // 500), 2.0, 4.0)
    elif style == "glyphs":
        img = np.tile(_palette(rng, 1)[0] * 0.5 + 0.3, (h, w, 1))
        img = _glyphs(rng, img, max(6, area // 120), 1.5, 5.0)
    elif style == "ground":
        img = _checker(rng, h, w, cell=max(4, min(h, w) // 8)) * 0.7 + 0.15
        img = _blobs(rng, img, max(8, area // 250), 2.0, 5.0)
        img = _glyphs(rng, img, max(8, area // 160), 1.5, 4.5)
    else:
        raise ValueError(f"style must be checker|stripes|blobs|glyphs|ground, got {style!r}")
    noise = rng.normal(0.0, 0.03, size=img.shape)
    return np.clip(img + noise, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# Gaussians
# ----------------------------------------------------------------------------------------------


def _face_gaussians(centre, t1, t2, half1, half2, spacing, texture_fn, shade, rng):
    """Disc Gaussians tiling the rectangle centre + u t1 + v t2, |u|<=half1, |v|<=half2."""
    n1 = max(2, int(round(2 * half1 / spacing)))
    n2 = max(2, int(round(2 * half2 / spacing)))
    u = (np.arange(n1) + 0.5) / n1 * 2 * half1 - half1
    v = (np.arange(n2) + 0.5) / n2 * 2 * half2 - half2
    uu, vv = np.meshgrid(u, v, indexing="xy")  # [n2, n1]
    pts = centre[None, None] + uu[..., None] * t1 + vv[..., None] * t2
    tex = texture_fn(rng, n2, n1) * shade
    normal = np.cross(t1, t2)
    R = np.stack([t1, t2, normal], axis=1)  # columns: local x, y, z -> world
    q = _quat_from_matrix(R)
    step = max(2 * half1 / n1, 2 * half2 / n2)
    P = n1 * n2
    scales = np.tile([0.62 * step, 0.62 * step, 0.04 * step], (P, 1))
    return pts.reshape(-1, 3), np.clip(tex.reshape(-1, 3), 0, 1), np.tile(q, (P, 1)), scales


@dataclass
class _Box:
    centre: Tuple[float, float, float]
    half: Tuple[float, float, float]
    yaw_deg: float


def _build_gaussians(seed: int, spacing: float, ground_half: float) -> Tuple[GaussianModel, dict]:
    rng = np.random.default_rng(seed)
    parts = []
    # Ground plane (z = 0), seen from above: normal +z.
    parts.append(
        _face_gaussians(
            np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), ground_half, ground_half,
            spacing * 1.25, lambda r, h, w: paint_texture(r, h, w, "ground"), 0.9, rng,
        )
    )
    boxes = [
        _Box((0.0, 0.0, 0.5), (0.5, 0.5, 0.5), float(rng.uniform(10, 35))),
        _Box((1.3, -0.9, 0.3), (0.35, 0.3, 0.3), float(rng.uniform(-30, 30))),
        _Box((-1.1, 1.0, 0.6), (0.3, 0.3, 0.6), float(rng.uniform(-30, 30))),
    ]
    styles = ["checker", "stripes", "blobs", "glyphs"]
    for b in boxes:
        c = np.asarray(b.centre, np.float64)
        Rz = rotation_about_axis((0, 0, 1), b.yaw_deg)
        ex, ey, ez = Rz[:, 0], Rz[:, 1], Rz[:, 2]
        hx, hy, hz = b.half
        # (face centre offset, t1, t2, half1, half2, shade); t1 x t2 = outward normal.
        faces = [
            (ez * hz, ex, ey, hx, hy, 1.0),
            (ex * hx, ey, ez, hy, hz, 0.85),
            (-ex * hx, -ey, ez, hy, hz, 0.7),
            (ey * hy, -ex, ez, hx, hz, 0.78),
            (-ey * hy, ex, ez, hx, hz, 0.62),
        ]
        for off, t1, t2, h1, h2, shade in faces:
            style = styles[int(rng.integers(0, len(styles)))]
            parts.append(
                _face_gaussians(c + off, t1, t2, h1, h2, spacing,
                                lambda r, h, w, s=style: paint_texture(r, h, w, s), shade, rng)
            )
    means = np.concatenate([p[0] for p in parts])
    rgb = np.concatenate([p[1] for p in parts])
    quat = np.concatenate([p[2] for p in parts])
    scales = np.concatenate([p[3] for p in parts])
    P = means.shape[0]
    sh_degree = 3
    K = (sh_degree + 1) ** 2 - 1
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    model = GaussianModel(
        means=f32(means),
        sh_dc=rgb_to_sh(f32(rgb))[:, None, :],
        sh_rest=torch.zeros(P, K, 3),
        opacity_logit=torch.full((P, 1), math.log(0.98 / 0.02)),
        scale_log=torch.log(f32(scales)),
        quat=f32(quat),
        sh_degree=sh_degree,
    )
    info = {"boxes": [vars(b) for b in boxes], "num_gaussians": P, "rgb": rgb}
    return model, info


def textured_plane_model(
    n: int = 40, size: float = 2.0, seed: int = 0, style: str = "ground"
) -> GaussianModel:
    """A small test model: an ``n x n`` grid of disc Gaussians.

    They tile the square ``[-size/2, size/2]^2`` of the plane z = 0 (normal +z), coloured by
    :func:`paint_texture`.
    """
    rng = np.random.default_rng(seed)
    pts, rgb, quat, scales = _face_gaussians(
        np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), size / 2, size / 2, size / n,
        lambda r, h, w: paint_texture(r, h, w, style), 1.0, rng)
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    P = pts.shape[0]
    return GaussianModel(
        means=f32(pts), sh_dc=rgb_to_sh(f32(rgb))[:, None, :], sh_rest=torch.zeros(P, 0, 3),
        opacity_logit=torch.full((P, 1), math.log(0.98 / 0.02)), scale_log=torch.log(f32(scales)),
        quat=f32(quat), sh_degree=0,
    )


def blob_model(num_gaussians: int = 300, seed: int = 0, extent: float = 1.0) -> GaussianModel:
    """Colourful anisotropic blobs in ``[-extent, extent]^3`` (SH degree 0, float32)."""
    g = torch.Generator().manual_seed(int(seed))
    P = int(num_gaussians)
    means = (torch.rand(P, 3, generator=g) * 2 - 1) * extent
    rgb = torch.rand(P, 3, generator=g) * 0.9 + 0.05
    scales = torch.exp(torch.randn(P, 3, generator=g) * 0.3) * (0.12 * extent)
    quat = torch.randn(P, 4, generator=g)
    return GaussianModel(
        means=means, sh_dc=rgb_to_sh(rgb)[:, None, :], sh_rest=torch.zeros(P, 0, 3),
        opacity_logit=torch.full((P, 1), 2.0), scale_log=scales.log(), quat=quat, sh_degree=0,
    )


def raster_bench_scene(num_gaussians: int, resolution: int, seed: int = 0) -> dict:
    """Raw rasterizer inputs for timing (``tools/bench_rasterizer.py``).

    ``num_gaussians`` SH-3 Gaussians 2-8 units in front of a ``resolution``-square camera (a few
    just off screen), with footprints of 0.5-4 px, as the keyword arguments of the backend
    contract (docs/CONTRACTS.md) plus ``settings``.
    """
    g = torch.Generator().manual_seed(seed)
    P, H, W = num_gaussians, resolution, resolution
    tanfov = 0.5
    focal = W / (2 * tanfov)

    def U(*shape, lo=0.0, hi=1.0):
        return torch.rand(*shape, generator=g) * (hi - lo) + lo

    z = U(P, lo=2.0, hi=8.0)
    x = U(P, lo=-1.1, hi=1.1) * tanfov * z  # a few just off screen
    y = U(P, lo=-1.1, hi=1.1) * tanfov * z
    means_cam = torch.stack([x, y, z], -1)
    # camera: a mild rotation + translation (w2c), means moved to the world
    angle = 0.2
    c, s = math.cos(angle), math.sin(angle)
    w2c = torch.tensor(
        [[c, 0, s, 0.1], [0, 1, 0, -0.2], [-s, 0, c, 0.3], [0, 0, 0, 1]], dtype=torch.float32
    )
    c2w = invert_rigid(w2c)
    means3D = means_cam @ c2w[:3, :3].T + c2w[:3, 3]
    # footprint: sigma of 0.5..4 pixels, anisotropic
    sigma_px = torch.exp(U(P, 3, lo=math.log(0.5), hi=math.log(4.0)))
    scales = sigma_px * z[:, None] / focal
    rotations = torch.randn(P, 4, generator=g)
    rotations = rotations / rotations.norm(dim=-1, keepdim=True)
    opacities = U(P, 1, lo=0.05, hi=0.99)
    shs = torch.randn(P, 16, 3, generator=g) * 0.2
    shs[:, 0] = torch.randn(P, 3, generator=g) * 0.8
    znear, zfar = 0.01, 100.0
    proj = torch.zeros(4, 4)
    proj[0, 0] = 1 / tanfov
    proj[1, 1] = 1 / tanfov
    proj[3, 2] = 1.0
    proj[2, 2] = zfar / (zfar - znear)
    proj[2, 3] = -(zfar * znear) / (zfar - znear)
    return dict(
        means3D=means3D.contiguous(),
        means2D=torch.zeros(P, 3),
        opacities=opacities,
        shs=shs,
        colors_precomp=None,
        scales=scales.contiguous(),
        rotations=rotations,
        cov3D_precomp=None,
        bg=torch.tensor([0.1, 0.2, 0.3]),
        viewmatrix=w2c.T.contiguous(),
        projmatrix=(proj @ w2c).T.contiguous(),
        campos=c2w[:3, 3].contiguous(),
        settings=dict(
            image_height=H,
            image_width=W,
            tanfovx=tanfov,
            tanfovy=tanfov,
            scale_modifier=1.0,
            sh_degree=3,
            prefiltered=False,
            antialiasing=False,
        ),
    )


# ----------------------------------------------------------------------------------------------
# the scene folder
# ----------------------------------------------------------------------------------------------


@dataclass
class DemoScene:
    """A built demo scene (see the module docstring for the folder layout)."""

    path: Path
    seed: int
    intrinsics: Intrinsics
    gt_c2w: np.ndarray  # [4, 4] OpenCV camera-to-world of the query
    init_c2w: np.ndarray  # [4, 4] initial guess
    scene_centre: np.ndarray  # [3] pivot of the perturbation
    scene_scale: float  # 3DGS cameras_extent (1.1 x max camera distance from the camera mean)
    init_rot_deg: float
    init_trans: float
    white_background: bool = False
    manifest: dict = field(default_factory=dict)

    @property
    def model_path(self) -> Path:
        """The model folder (the scene folder itself)."""
        return self.path

    @property
    def query_image_path(self) -> Path:
        """The query photo, query.png."""
        return self.path / "query.png"

    @property
    def query_gt_path(self) -> Path:
        """query_gt.json: the query's true pose and intrinsics."""
        return self.path / "query_gt.json"

    @property
    def init_c2w_path(self) -> Path:
        """init_c2w.txt: the initial guess, 4x4 camera-to-world."""
        return self.path / "init_c2w.txt"

    def load_model(self) -> GaussianModel:
        """The scene's Gaussians, read from the model folder."""
        from ..io.model_folder import load_model_folder

        return load_model_folder(self.path).model

    def load_query(self) -> torch.Tensor:
        """The query image `[3, H, W]` float in [0, 1]."""
        from PIL import Image

        arr = np.asarray(Image.open(self.query_image_path).convert("RGB"), dtype=np.float32) / 255.0
        return torch.from_numpy(arr).permute(2, 0, 1).contiguous()


def _params(seed, width, height, fov_deg, spacing, rot_range_deg, trans) -> dict:
    return {
        "version": DEMO_VERSION,
        "seed": int(seed),
        "width": int(width),
        "height": int(height),
        "fov_deg": float(fov_deg),
        "spacing": float(spacing),
        "rot_range_deg": [float(rot_range_deg[0]), float(rot_range_deg[1])],
        "trans": float(trans),
    }


def _to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def build_demo_scene(
    path: Optional[PathLike] = None,
    seed: int = 0,
    *,
    width: int = 200,
    height: int = 200,
    fov_deg: float = 60.0,
    spacing: float = 0.04,
    rot_range_deg: Tuple[float, float] = (20.0, 40.0),
    trans: float = 0.1,
    num_ring_cameras: int = 12,
    rebuild: bool = False,
    backend: str = "auto",
) -> DemoScene:
    """Build (or reuse) the demo scene folder; deterministic in all arguments.

    Args:
        path: target folder; None uses `default_demo_path(seed)`.
        seed: drives textures, box placement, the query pose and the initial perturbation.
        width: query / ring camera image width [px].
        height: their image height [px].
        fov_deg: their horizontal field of view [deg].
        spacing: Gaussian spacing on the object faces (world units; the ground uses 1.25x).
        rot_range_deg: the initial rotation error is drawn uniformly in this range.
        trans: extra random translation (world units) of the initial camera centre.
        num_ring_cameras: cameras written to cameras.json (a ring around the scene).
        rebuild: rebuild even if a matching cache exists.
        backend: renderer backend used to render the query image.

    The folder is reused when its `demo.json` records the same parameters; otherwise it is built
    in a temporary sibling folder and moved into place (safe against concurrent builders).
    """
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    lo, hi = (float(x) for x in rot_range_deg)
    if not (0 <= lo <= hi < 180):
        raise ValueError(
            f"rot_range_deg must be (lo, hi) with 0 <= lo <= hi < 180, got {rot_range_deg!r}"
        )
    path = Path(path) if path is not None else default_demo_path(seed)
    params = _params(seed, width, height, fov_deg, spacing, (lo, hi), trans)
    if not rebuild:
        scene = _try_load(path, params)
        if scene is not None:
            return scene
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".building", dir=path.parent))
    try:
        _build_into(tmp, path, params, num_ring_cameras, backend)
        if path.exists():
            # A stale cache (other parameters) or a concurrent builder: replace it.
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            try:
                os.replace(path, old / "x")
            except OSError:
                pass
            shutil.rmtree(old, ignore_errors=True)
        try:
            os.replace(tmp, path)
        except OSError:
            # Another process moved its build in first; use theirs if it matches.
            scene = _try_load(path, params)
            if scene is None:
                raise
            return scene
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    scene = _try_load(path, params)
    if scene is None:  # pragma: no cover - just written
        raise RuntimeError(f"demo scene at {path} could not be read back after building")
    return scene


def _try_load(path: Path, params: dict) -> Optional[DemoScene]:
    manifest_path = path / "demo.json"
    if not manifest_path.is_file():
        return None
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if manifest.get("params") != params:
        return None
    needed = ["query.png", "query_gt.json", "init_c2w.txt", "cfg_args", "cameras.json",
              f"point_cloud/iteration_{DEMO_ITERATION}/point_cloud.ply"]
    if not all((path / n).is_file() for n in needed):
        return None
    gt = json.loads((path / "query_gt.json").read_text())
    intr = Intrinsics(int(gt["width"]), int(gt["height"]), float(gt["fx"]), float(gt["fy"]))
    return DemoScene(
        path=path,
        seed=params["seed"],
        intrinsics=intr,
        gt_c2w=np.asarray(gt["c2w"], np.float64),
        init_c2w=np.loadtxt(path / "init_c2w.txt").reshape(4, 4),
        scene_centre=np.asarray(manifest["scene_centre"], np.float64),
        scene_scale=float(manifest["scene_scale"]),
        init_rot_deg=float(manifest["init_rot_deg"]),
        init_trans=float(manifest["init_trans"]),
        white_background=False,
        manifest=manifest,
    )


def _ring_cameras(intr: Intrinsics, centre: np.ndarray, radius: float, height: float, n: int):
    """A ring of ``n`` cameras looking at ``centre`` (what a capture would have produced)."""
    from ..io.cameras_json import CameraEntry

    cams = []
    for i in range(n):
        az = 2 * math.pi * i / n
        eye = centre + np.array([radius * math.cos(az), radius * math.sin(az), height - centre[2]])
        cams.append(CameraEntry(id=i, img_name=f"ring_{i:03d}", width=intr.width,
                                height=intr.height, c2w=look_at_c2w(eye, centre),
                                fx=float(intr.fx), fy=float(intr.fy)))
    return cams


def _build_into(
    folder: Path, final_path: Path, params: dict, num_ring_cameras: int, backend: str
) -> None:
    from PIL import Image

    from ..io.atomic import write_json_atomic, write_text_atomic
    from ..io.model_folder import write_model_folder
    from ..render import model_for_backend, render

    seed = params["seed"]
    W, H = params["width"], params["height"]
    model, info = _build_gaussians(seed, params["spacing"], ground_half=2.5)
    intr = Intrinsics.from_fov(W, H, math.radians(params["fov_deg"]))
    centre = np.array([0.0, 0.0, 0.4])

    ring_radius, ring_height = 4.0, 2.2
    cams = _ring_cameras(intr, centre, ring_radius, ring_height, num_ring_cameras)
    centres = np.stack([c.c2w[:3, 3] for c in cams])
    scene_scale = 1.1 * float(np.max(np.linalg.norm(centres - centres.mean(0), axis=1)))

    # The hidden query pose: random azimuth off the ring, varied distance / height / aim.
    rng = np.random.default_rng(10_000 + seed)
    az = rng.uniform(0, 2 * math.pi)
    r = rng.uniform(3.4, 4.2)
    h = rng.uniform(1.6, 2.6)
    eye = np.array([r * math.cos(az), r * math.sin(az), h])
    target = centre + rng.uniform(-0.25, 0.25, size=3) * np.array([1, 1, 0.5])
    gt_c2w = look_at_c2w(eye, target)
    # Initial guess: rotation about a random axis through the scene centre + small translation.
    rot_deg = float(rng.uniform(*params["rot_range_deg"]))
    init_c2w = perturb_pose(gt_c2w, rot_deg, float(params["trans"]), generator=rng, pivot=centre)

    cfg = {
        "data_device": "cuda",
        "depths": "",
        "eval": True,
        "images": "images",
        "model_path": str(final_path.resolve()),
        "resolution": -1,
        "sh_degree": model.sh_degree,
        "source_path": "",
        "train_test_exp": False,
        "white_background": False,
    }
    write_model_folder(folder, model, cfg, cams, DEMO_ITERATION,
                       input_points=(model.means.numpy(), info["rgb"]))

    w2c = torch.as_tensor(invert_rigid(gt_c2w), dtype=torch.float32)
    with torch.no_grad():  # render() takes the pose and background to the model's device
        out = render(model_for_backend(model, backend), intr, w2c, torch.zeros(3),
                     backend=backend)
    Image.fromarray(_to_uint8(out.color.cpu())).save(folder / "query.png")
    write_json_atomic(
        folder / "query_gt.json",
        {
            "name": "query",
            "width": W,
            "height": H,
            "fx": intr.fx,
            "fy": intr.fy,
            "c2w": gt_c2w.tolist(),
            "note": "ground-truth pose of query.png (OpenCV camera-to-world); used only to "
            "report errors",
        },
    )
    write_text_atomic(folder / "init_c2w.txt",
                      "\n".join(" ".join(f"{v:.12g}" for v in row) for row in init_c2w) + "\n")
    write_json_atomic(folder / "demo.json", {
        "params": params,
        "num_gaussians": info["num_gaussians"],
        "boxes": info["boxes"],
        "scene_centre": centre.tolist(),
        "scene_scale": scene_scale,
        "init_rot_deg": rot_deg,
        "init_trans": params["trans"],
        "ring": {"radius": ring_radius, "height": ring_height, "count": num_ring_cameras},
    })
