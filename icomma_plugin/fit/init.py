"""Initial Gaussians from a point cloud, as upstream `GaussianModel.create_from_pcd`.

Scales: log(sqrt(mean squared distance to the 3 nearest neighbours)), clamped at 1e-7 (simple-knn
`distCUDA2`), isotropic; rotations identity; opacity `inverse_sigmoid(0.1)`; colour into the SH DC
band (`RGB2SH`), higher bands zero.

Where the points come from: the dataset's cloud (COLMAP, a PLY), `random_cube_points`
(upstream's Blender init), or, for a posed capture without a cloud, `plane_sweep_points`.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..gaussians import GaussianModel, num_sh_coeffs, rgb_to_sh


def mean_knn_sq_dist(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean squared distance of each point to its k nearest other points (simple-knn distCUDA2)."""
    points = np.asarray(points, dtype=np.float64)
    n = points.shape[0]
    if n < 2:
        return np.full((n,), 1e-2, dtype=np.float64)
    kk = min(k, n - 1)
    d, _ = cKDTree(points).query(points, k=kk + 1)
    d = np.asarray(d).reshape(n, kk + 1)[:, 1:]  # drop self
    return np.clip((d ** 2).mean(axis=1), 1e-7, None)


def random_cube_points(
    n: int, half_extent: float = 1.3, seed: int = 0
) -> Tuple[np.ndarray, np.ndarray]:
    """Upstream Blender init: n uniform points in [-h, h]^3, random colours (floats in [0, 1])."""
    if n < 1:
        raise ValueError(f"n (number of random points) must be >= 1, got {n!r}")
    rng = np.random.default_rng(seed)
    xyz = (rng.random((n, 3)) * 2.0 - 1.0) * half_extent
    # upstream draws SH DC ~ U[0,1)/255 -> colour ~ 0.5 + C0 * small; we draw the colour itself
    rgb = rng.random((n, 3))
    return xyz.astype(np.float32), rgb.astype(np.float32)


def model_from_points(
    xyz: np.ndarray,
    rgb: np.ndarray,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    dtype: torch.dtype = torch.float32,
    device: Optional[torch.device] = None,
    max_scale: Optional[np.ndarray] = None,
) -> GaussianModel:
    """A GaussianModel with one isotropic Gaussian per point (upstream `create_from_pcd`).

    max_scale: [N] upper bounds of the initial scales (`init_scale_limits`), or None (upstream:
    the nearest-neighbour scale as it is).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    rgb = np.asarray(rgb, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.shape[0] < 1:
        raise ValueError(f"xyz must be a non-empty [N, 3] array, got shape {list(xyz.shape)}")
    if rgb.shape != xyz.shape:
        raise ValueError(f"rgb must have the shape of xyz {list(xyz.shape)}, got {list(rgb.shape)}")
    if rgb.max(initial=0.0) > 1.0 + 1e-6:  # uint8-style colours
        rgb = rgb / 255.0
    P = xyz.shape[0]
    dist2 = mean_knn_sq_dist(xyz)
    if max_scale is not None:
        max_scale = np.asarray(max_scale, dtype=np.float64).reshape(-1)
        if max_scale.shape != (P,) or not np.all(max_scale > 0):
            raise ValueError(f"max_scale must hold {P} positive values, got shape "
                             f"{list(max_scale.shape)}")
        dist2 = np.minimum(dist2, max_scale ** 2)
    t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    scale_log = t(np.log(np.sqrt(dist2)))[:, None].repeat(1, 3)
    quat = torch.zeros(P, 4, dtype=dtype, device=device)
    quat[:, 0] = 1.0
    logit = math.log(init_opacity / (1.0 - init_opacity))
    return GaussianModel(
        means=t(xyz).contiguous(),
        sh_dc=rgb_to_sh(t(rgb)).view(P, 1, 3).contiguous(),
        sh_rest=torch.zeros(P, num_sh_coeffs(sh_degree) - 1, 3, dtype=dtype, device=device),
        opacity_logit=torch.full((P, 1), logit, dtype=dtype, device=device),
        scale_log=scale_log.contiguous(),
        quat=quat,
        sh_degree=sh_degree,
    )


def init_scale_limits(xyz: np.ndarray, camera_centres: np.ndarray, angle: float) -> np.ndarray:
    """[N] largest initial scale of each point: `angle` x its distance to the nearest camera.

    The nearest-neighbour scale of an isolated point (an SfM outlier far away, a sparse far
    field) can cover much of the image; on a CPU the rasterizer's time grows with the screen
    area of the Gaussians, so the start is kept to about `angle` radians as seen from the
    cameras (densification fills what that leaves open).
    """
    if not (math.isfinite(angle) and angle > 0):
        raise ValueError(f"angle must be a positive finite number of radians, got {angle!r}")
    d, _ = cKDTree(np.asarray(camera_centres, np.float64)).query(np.asarray(xyz, np.float64))
    return np.maximum(angle * np.asarray(d), 1e-7)


def subsample_points(
    xyz: np.ndarray, rgb: np.ndarray, max_points: int, seed: int = 0
) -> Tuple[np.ndarray, np.ndarray]:
    """At most max_points of the cloud, drawn without replacement (order kept)."""
    n = xyz.shape[0]
    if n <= max_points:
        return xyz, rgb
    idx = np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))
    return xyz[idx], rgb[idx]



def _view_arrays(v):
    """(K [3, 3], w2c [4, 4], image [3, H, W], valid [H, W] bool or None) of a FitView, float64."""
    i = v.intrinsics
    K = np.array([[i.fx, 0.0, i.cx_px], [0.0, i.fy, i.cy_px], [0.0, 0.0, 1.0]])
    w2c = v.w2c.detach().cpu().double().numpy() if isinstance(v.w2c, torch.Tensor) \
        else np.asarray(v.w2c, dtype=np.float64)
    valid = None if getattr(v, "valid", None) is None else v.valid.detach().cpu().numpy()[0] > 0.5
    return K, w2c, v.image.detach().cpu().float(), valid


def _sample(img: torch.Tensor, u: np.ndarray, r: np.ndarray) -> torch.Tensor:
    """Bilinear samples [3, *u.shape] of img [3, H, W] at pixel coordinates (u, r)."""
    H, W = img.shape[1:]
    grid = torch.from_numpy(np.stack([2 * (u + 0.5) / W - 1, 2 * (r + 0.5) / H - 1], -1)).float()
    out = torch.nn.functional.grid_sample(img[None], grid.reshape(1, -1, 1, 2), mode="bilinear",
                                          padding_mode="border", align_corners=False)
    return out[0, :, :, 0].reshape(3, *u.shape)


def _mean_costs(X: np.ndarray, ref: torch.Tensor, arrays, blurred) -> np.ndarray:
    """[P, D] mean colour difference of each depth hypothesis X [P, D, 3] over the neighbours.

    Each hypothesis is projected into every neighbour view (its `_view_arrays` and blurred
    image); the cost is the mean L1 distance to the reference colours `ref` [3, P] over the
    views where it lands on a valid pixel in front of the camera, and inf where fewer than
    half of the neighbours (at least 2) see it.
    """
    cost = np.zeros(X.shape[:2])
    seen = np.zeros(X.shape[:2])
    for (Kk, wk, _, vk), img in zip(arrays, blurred):
        xc = X @ wk[:3, :3].T + wk[:3, 3]
        z = xc[..., 2]
        zs = np.where(z > 1e-6, z, 1.0)
        uk = Kk[0, 0] * xc[..., 0] / zs + Kk[0, 2]
        vk_ = Kk[1, 1] * xc[..., 1] / zs + Kk[1, 2]
        Hk, Wk = img.shape[1:]
        inside = (z > 1e-6) & (uk >= 0) & (uk <= Wk - 1) & (vk_ >= 0) & (vk_ <= Hk - 1)
        if vk is not None:
            ii = np.clip(np.rint(vk_).astype(int), 0, Hk - 1)
            jj = np.clip(np.rint(uk).astype(int), 0, Wk - 1)
            inside &= vk[ii, jj]
        smp = _sample(img, np.where(inside, uk, 0.0), np.where(inside, vk_, 0.0))
        d = (smp - ref[:, :, None]).abs().mean(0).numpy()
        cost += np.where(inside, d, 0.0)
        seen += inside
    need = max(2, (len(arrays) + 1) // 2)
    return np.where(seen >= need, cost / np.maximum(seen, 1), np.inf)


def plane_sweep_points(
    views,
    center: Sequence[float],
    half_extent: float,
    n: int,
    seed: int = 0,
    depths: int = 64,
    neighbours: int = 4,
    distinct: float = 0.6,
    near_frac: float = 0.25,
    far_frac: float = 2.5,
    min_contrast: float = 0.02,
    bounds: Optional[Sequence[Tuple[float, float]]] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """Initial points for a posed capture without a point cloud: a coarse plane sweep.

    For random pixels of every view, `depths` depth hypotheses (uniform in inverse depth from
    `near_frac` to `far_frac` times the camera's distance to `center`) are projected into the
    `neighbours` views with the nearest camera centres (looking the same way); the depth whose
    colours agree best (mean L1 to the reference colour, on images blurred with a 3x3 box) is
    kept when its cost is below `distinct` x the median cost along the ray and that median
    exceeds `min_contrast` (uniform regions, whose depth is ambiguous, are dropped), refined to
    the vertex of the parabola through its neighbours' costs. Points take the reference pixel
    colour. When fewer than `n` points pass, the rest are uniform in the cube (grey), so that
    empty regions still get Gaussians.

    Args:
        views: FitView-like objects (`image [3, H, W]`, `intrinsics`, `w2c [4, 4]`, `valid`).
        center: the centre of the cube holding the scene and the cameras.
        half_extent: the cube's half side.
        n: number of points to return.
        seed: seed of the pixel choice and of the filler points.
        depths: depth hypotheses per pixel.
        neighbours: views compared with each reference view.
        distinct: how much better than the ray's median cost the chosen depth must be.
        near_frac: the nearest depth, in units of the camera's distance to `center`.
        far_frac: the farthest depth, in the same units.
        min_contrast: the ray's median cost must exceed this (a uniform region has no depth).
        bounds: per view (near, far) depth bounds (LLFF); when given, the hypotheses span
            0.9 near .. far of each view instead of `near_frac` .. `far_frac`.

    Returns:
        (xyz [n, 3] float32, rgb [n, 3] float32 in [0, 1]).
    """
    if n < 1:
        raise ValueError(f"n (number of points) must be >= 1, got {n!r}")
    if len(views) < 2:
        raise ValueError(f"views must hold at least 2 posed images, got {len(views)}")
    rng = np.random.default_rng(seed)
    arrays = [_view_arrays(v) for v in views]
    blurred = [torch.nn.functional.avg_pool2d(a[2][None], 3, 1, 1, count_include_pad=False)[0]
               for a in arrays]
    centres = np.stack([-a[1][:3, :3].T @ a[1][:3, 3] for a in arrays])
    axes = np.stack([a[1][2, :3] for a in arrays])  # viewing directions in world
    c = np.asarray(center, np.float64)
    per_view = int(math.ceil(2.0 * n / len(views)))  # about half the pixels pass
    pts, cols = [], []
    for r, (K, w2c, _, valid) in enumerate(arrays):
        img = blurred[r]
        H, W = img.shape[1:]
        u = rng.uniform(0, W - 1, per_view)
        v = rng.uniform(0, H - 1, per_view)
        if valid is not None:
            ok = valid[np.rint(v).astype(int), np.rint(u).astype(int)]
            u, v = u[ok], v[ok]
        ref = _sample(img, u, v)  # [3, P]
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        R, t = w2c[:3, :3], w2c[:3, 3]
        d_c = max(float(np.linalg.norm(centres[r] - c)), 1e-3 * half_extent)
        near, far = near_frac * d_c, far_frac * d_c
        if bounds is not None and bounds[r][0] > 0 and bounds[r][1] > bounds[r][0]:
            near, far = 0.9 * bounds[r][0], bounds[r][1]
        inv = np.linspace(1.0 / near, 1.0 / far, depths)
        X = ((rays[:, None, :] / inv[None, :, None]) - t) @ R  # [P, D, 3] world (R^T (x - t))
        cos = axes @ axes[r]
        dist = np.linalg.norm(centres - centres[r], axis=1)
        dist[(cos < 0.5) | (np.arange(len(arrays)) == r)] = np.inf
        nb = [k for k in np.argsort(dist)[:neighbours] if np.isfinite(dist[k])]
        if not nb:
            continue
        mean_cost = _mean_costs(X, ref, [arrays[k] for k in nb], [blurred[k] for k in nb])
        best = np.argmin(mean_cost, axis=1)
        bc = mean_cost[np.arange(len(best)), best]
        finite = np.where(np.isfinite(mean_cost), mean_cost, np.nan)
        with warnings.catch_warnings():  # rays seen by no neighbour: all-NaN rows
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(finite, axis=1)
        keep = np.isfinite(bc) & (bc < distinct * med) & (med > min_contrast)
        # sub-sample refinement: the vertex of the parabola through the costs around the best
        # hypothesis (in inverse depth, where the hypotheses are evenly spaced)
        rows = np.arange(len(best))
        lo, hi = np.clip(best - 1, 0, depths - 1), np.clip(best + 1, 0, depths - 1)
        c0, c1, c2 = mean_cost[rows, lo], bc, mean_cost[rows, hi]
        with np.errstate(all="ignore"):
            curv = c0 - 2 * c1 + c2
            shift = np.where((lo < best) & (hi > best) & np.isfinite(c0 + c2) & (curv > 0),
                             0.5 * (c0 - c2) / curv, 0.0)
        best_inv = inv[best] + np.clip(shift, -0.5, 0.5) * (inv[1] - inv[0])
        Xb = ((rays / best_inv[:, None]) - t) @ R
        pts.append(Xb[keep])
        cols.append(ref.numpy().T[keep])
    xyz = np.concatenate(pts) if pts else np.zeros((0, 3))
    rgb = np.concatenate(cols) if cols else np.zeros((0, 3))
    inbox = np.all(np.abs(xyz - c) <= half_extent, axis=1)
    xyz, rgb = xyz[inbox], rgb[inbox]
    if len(xyz) > n:
        idx = rng.choice(len(xyz), size=n, replace=False)
        xyz, rgb = xyz[idx], rgb[idx]
    elif len(xyz) < n:
        fill = (rng.random((n - len(xyz), 3)) * 2.0 - 1.0) * half_extent + c
        xyz = np.concatenate([xyz, fill])
        rgb = np.concatenate([rgb, np.full((len(fill), 3), 0.5)])
    return xyz.astype(np.float32), np.clip(rgb, 0.0, 1.0).astype(np.float32)


def fibonacci_sphere(n: int) -> np.ndarray:
    """n nearly evenly spread unit vectors [n, 3] (golden-angle spiral)."""
    if n < 1:
        raise ValueError(f"n (number of directions) must be >= 1, got {n!r}")
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def far_field_points(
    views, center: Sequence[float], radius: float, n: int, max_views: int = 24,
) -> Tuple[np.ndarray, np.ndarray]:
    """Points on a sphere of `radius` around `center`, coloured by the photos that see them.

    The background of a capture (walls, the room behind the object) lies beyond the cameras,
    where no plane sweep or random box reaches; a shell of Gaussians there lets the fit explain
    it from the first step instead of growing fog in front of it. Each of `n` directions is
    projected into up to `max_views` training views (evenly spaced); its colour is the median of
    the (3x3-blurred) pixels of the views where it lands on a valid pixel, in front of the camera.
    Directions seen by no view are dropped.

    Args:
        views: FitView-like objects (`image [3, H, W]`, `intrinsics`, `w2c [4, 4]`, `valid`).
        center: the shell's centre (world).
        radius: its radius; must exceed every camera's distance to `center`.
        n: directions on the sphere.
        max_views: views sampled for the colours.

    Returns:
        (xyz [m, 3] float32, rgb [m, 3] float32 in [0, 1]), m <= n.
    """
    c = np.asarray(center, np.float64)
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a positive finite number, got {radius!r}")
    pick = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).round().astype(int))
    xyz = c + radius * fibonacci_sphere(n)
    samples = np.full((len(pick), n, 3), np.nan)
    for row, i in enumerate(pick):
        K, w2c, img, valid = _view_arrays(views[i])
        xc = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        z = xc[:, 2]
        zs = np.where(z > 1e-6, z, 1.0)
        u = K[0, 0] * xc[:, 0] / zs + K[0, 2]
        v = K[1, 1] * xc[:, 1] / zs + K[1, 2]
        H, W = img.shape[1:]
        inside = (z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        if valid is not None:
            inside &= valid[np.clip(np.rint(v), 0, H - 1).astype(int),
                            np.clip(np.rint(u), 0, W - 1).astype(int)]
        if not inside.any():
            continue
        blurred = torch.nn.functional.avg_pool2d(img[None], 3, 1, 1, count_include_pad=False)[0]
        col = _sample(blurred, u[inside], v[inside]).numpy().T
        samples[row, inside] = col
    seen = np.isfinite(samples[:, :, 0]).any(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rgb = np.nanmedian(samples[:, seen], axis=0)
    return xyz[seen].astype(np.float32), np.clip(rgb, 0.0, 1.0).astype(np.float32)


@dataclass
class InitCloud:
    """The fit's initial points: xyz [N, 3], rgb [N, 3] in [0, 1], where they came from.

    source: "dataset" (the capture's cloud), "views" (plane sweep), "random_box" (uniform in the
    camera box) or "random" (upstream's Blender cube); far_points: how many of the N (the last
    ones) lie on the far-field shell; centre / radius: that shell's.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    source: str
    far_points: int = 0
    centre: Optional[Tuple[float, float, float]] = None
    radius: Optional[float] = None


def image_has_alpha(path) -> bool:
    """Whether an image file carries an alpha channel (read from its header)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    except Exception:  # noqa: BLE001 - unreadable here: the loader will say why
        return False


def is_object_render(scene) -> bool:
    """A synthetic object on a transparent background (NeRF-synthetic), not a photographed scene.

    True for a Blender-layout dataset whose images have an alpha channel: it keeps upstream's
    random cube and gets no far field (its background is the flat colour it is composited on).
    """
    views = scene.train or scene.test
    return scene.source == "blender" and bool(views) and image_has_alpha(views[0].image_path)


def far_field_radius(scene, centre: np.ndarray, factor: float) -> float:
    """Radius of the far-field shell around `centre`.

    With LLFF depth bounds: the 90th percentile of the views' far bounds; without: `factor` x
    the largest camera distance to `centre`. At least 1.2 x that distance (the shell encloses
    every camera).
    """
    views = scene.train or scene.test
    dist = max(float(np.linalg.norm(v.campos - centre)) for v in views)
    far = [v.bounds[1] for v in views if v.bounds is not None]
    radius = float(np.percentile(far, 90)) if far else factor * dist
    return max(radius, 1.2 * dist, 1e-6)


def initial_points(scene, train, config) -> InitCloud:
    """The initial cloud of a fit: wherever the capture has points, else made from the photos.

    - a synthetic object render (`is_object_render`): upstream's random cube;
    - a capture with a point cloud (COLMAP, LLFF with a sparse model beside it, a
      transforms.json `ply_file_path`): that cloud, subsampled to `config.max_init_points`;
    - any other capture (LLFF, transforms.json or a Blender layout of photos, without points): a
      plane sweep over the training views in the camera box (`config.box_init == "views"`) or
      uniform random points in that box;
    then, for every photographed capture, `config.far_field_points` on a shell beyond the
    cameras (`far_field_points`, `far_field_radius`).
    """
    from ..io.datasets.transforms_json import camera_box

    if is_object_render(scene):
        xyz, rgb = random_cube_points(config.num_random_points, config.random_points_half_extent,
                                      config.seed)
        return InitCloud(xyz, rgb, "random")
    box = scene.init_box
    if box is None:
        centre, half = camera_box([v.c2w for v in scene.train])
        box = (tuple(float(c) for c in centre), half)
    centre, half = np.asarray(box[0], np.float64), float(box[1])
    if scene.points is not None and len(scene.points) > 0 and scene.init_box is None:
        colors = scene.colors if scene.colors is not None else np.full_like(scene.points, 0.5)
        xyz, rgb = subsample_points(np.asarray(scene.points), np.asarray(colors),
                                    config.max_init_points, config.seed)
        source = "dataset"
    elif config.box_init == "views" and len(train) >= 2:
        bounds = [v.bounds for v in scene.train]
        xyz, rgb = plane_sweep_points(train, centre, half, config.num_sweep_points, config.seed,
                                      bounds=bounds if all(b is not None for b in bounds) else None)
        source = "views"
    else:
        xyz, rgb = random_cube_points(config.num_random_points, half, config.seed)
        xyz, source = xyz + centre.astype(np.float32), "random_box"
    xyz, rgb = np.asarray(xyz, np.float32), np.asarray(rgb, np.float32)
    if config.far_field_points <= 0:
        return InitCloud(xyz, rgb, source)
    radius = far_field_radius(scene, centre, config.far_field_factor)
    fxyz, frgb = far_field_points(train, centre, radius, config.far_field_points)
    return InitCloud(np.concatenate([xyz, fxyz]), np.concatenate([rgb, frgb]), source,
                     far_points=len(fxyz), centre=tuple(float(c) for c in centre), radius=radius)
