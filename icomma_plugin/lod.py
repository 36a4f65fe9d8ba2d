"""Upstream-size models and level of detail for a 3DGS model (issue 19).

- :func:`split_gaussians`: a model with ``factor`` times (or ``target``) as many Gaussians, each
  Gaussian split into children sampled from its own Gaussian, as upstream's densification splits
  (``densify_and_split``). ``mode="upstream"`` is upstream's rule literally (children at
  ``R (s * eps)``, ``eps ~ N(0, I)``, scale ``s / (0.8 N)``, the parent's opacity, colour and
  rotation); it does not render the parent's image (children that small and that opaque
  speckle it: 16-27 dB on the demo scene, 20-25 dB on fitted lego at 300k).
  ``mode="preserve"`` (default) aims at the same image: children sampled with a std of
  ``spread * s``, their scale moment-matched (``s sqrt(1 - spread^2)``, so the mixture has the
  parent's covariance) and their opacity fitted so that the N stacked children compose to the
  parent's alpha profile (:func:`stacked_opacity`); the extra children go mostly to opaque
  Gaussians (``opacity_power``). On fitted lego (52,701 Gaussians): 37-39 dB at 300k, 31-33 dB
  at 1M (docs/SPEED.md).
- :func:`reduce_model`: a reduced model for rendering at a working resolution: Gaussians that
  can never reach alpha 1/255 are left out; Gaussians whose footprint from every given camera is
  far below a pixel are merged per world cell of about a pixel (moment-matched: weights opacity x
  volume for the mean, covariance and SH; the opacity of the stack, ``1 - prod(1 - o_i)``);
  optionally a cap on the count (the merge threshold grows until it holds). Deterministic for a
  given model, cameras and :class:`LodConfig`.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from .camera import Intrinsics
from .checks import check_bool, check_choice, check_int, check_real

from .gaussians import GaussianModel, quat_to_rotmat

__all__ = ["LodConfig", "LodInfo", "reduce_model", "split_gaussians", "stacked_opacity"]

SPLIT_MODES = ("preserve", "upstream")


# ------------------------------------------------------------------------------------------------
# Splitting (upstream-size models)
# ------------------------------------------------------------------------------------------------
def stacked_opacity(opacity: torch.Tensor, n: int, samples: int = 200) -> torch.Tensor:
    """Opacity of each of ``n`` coincident copies whose stack renders like one of ``opacity``.

    ``n`` copies of opacity ``c`` compose to ``1 - (1 - c G)^n`` where one Gaussian of opacity
    ``o`` gives ``o G`` (G the Gaussian profile, 1 at the centre). ``c`` minimises the squared
    difference of the two over the image plane (weight r dr, r < 4 sigma), per ``o`` on a grid of
    201 values (golden-section search, then linear interpolation). ``c = o`` for ``n = 1``.

    Raises:
        ValueError: ``n`` not a positive int.
    """
    check_int(n, "n", 1)
    if n == 1:
        return opacity.clone()
    r = torch.linspace(0.0, 4.0, samples, dtype=torch.float64)
    profile, weight = torch.exp(-0.5 * r * r), r
    o_grid = torch.linspace(0.0, 1.0, 201, dtype=torch.float64)[:, None]

    def err(c: torch.Tensor) -> torch.Tensor:
        stack = 1.0 - (1.0 - c[:, None] * profile) ** n
        return ((stack - o_grid * profile) ** 2 * weight).sum(-1)

    lo, hi = torch.zeros(201, dtype=torch.float64), torch.ones(201, dtype=torch.float64)
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(60):
        a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
        left = err(a) < err(b)
        hi = torch.where(left, b, hi)
        lo = torch.where(left, lo, a)
    table = (0.5 * (lo + hi)).to(opacity.dtype)
    pos = opacity.clamp(0.0, 1.0) * 200.0
    i0 = pos.floor().long().clamp(0, 199)
    frac = pos - i0.to(pos.dtype)
    return table[i0] * (1.0 - frac) + table[i0 + 1] * frac


def _children_per_gaussian(P: int, factor: Optional[int], target: Optional[int],
                           generator: torch.Generator,
                           weights: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Children of each of the P Gaussians.

    ``factor`` each; or ``target`` in all: without ``weights``, ``target // P`` each and one more
    for ``target mod P`` Gaussians drawn at random; with ``weights`` [P] (>= 0, not all 0), one
    each and the other ``target - P`` in proportion to the weights (the rounding remainder to the
    largest weights, ties by index).
    """
    if (factor is None) == (target is None):
        raise ValueError("split_gaussians: give exactly one of factor and target")
    if factor is not None:
        check_int(factor, "factor", 1)
        return torch.full((P,), factor, dtype=torch.long)
    check_int(target, "target", P)
    if weights is None or P == 0 or not float(weights.sum()) > 0:
        counts = torch.full((P,), target // P if P else 0, dtype=torch.long)
        extra = torch.randperm(P, generator=generator)[: target - int(counts.sum())]
    else:
        w = weights.to(torch.float64)
        counts = 1 + torch.floor((target - P) * w / w.sum()).long()
        extra = torch.argsort(-w, stable=True)[: target - int(counts.sum())]
    counts[extra] += 1
    return counts


def split_gaussians(model: GaussianModel, factor: Optional[int] = None,
                    target: Optional[int] = None, generator: Optional[torch.Generator] = None,
                    mode: str = "preserve", spread: float = 0.3,
                    opacity_power: Optional[float] = None) -> GaussianModel:
    """The model with every Gaussian split into children (module docstring).

    Args:
        model: the Gaussians (CPU).
        factor: children per Gaussian (>= 1); or
        target: the number of Gaussians wanted (>= P); see ``opacity_power``.
        generator: random source (a fixed seed gives the same model); None = a fresh one, seed 0.
        mode: ``"preserve"`` (renders the parent's image) or ``"upstream"`` (upstream's rule).
        spread: ``"preserve"`` only: std of the children's offsets, relative to the parent's
            scales, in (0, 1).
        opacity_power: with ``target``: the children beyond one each go to the Gaussians in
            proportion to opacity ** opacity_power (0 = evenly). None = 4 in ``"preserve"`` mode
            (a stack of many faint copies loses its tails to the rasterizer's 1/255 alpha cut,
            so faint Gaussians are split least), 0 in ``"upstream"`` mode.

    Returns:
        A new model; the children of Gaussian i are consecutive, in the order of the parents.

    Raises:
        ValueError: both or neither of factor / target, a factor < 1, a target < P, an unknown
            mode, a spread outside (0, 1) or a negative opacity_power.
    """
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    check_choice(mode, "mode", SPLIT_MODES)
    check_real(spread, "spread", 0.0, 1.0, lo_open=True, hi_open=True)
    if opacity_power is None:
        opacity_power = 4.0 if mode == "preserve" else 0.0
    check_real(opacity_power, "opacity_power", 0.0)
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    P = model.num_gaussians
    weights = model.opacities().detach()[:, 0] ** opacity_power if opacity_power > 0 else None
    counts = _children_per_gaussian(P, factor, target, gen, weights)
    parent = torch.repeat_interleave(torch.arange(P), counts)
    n = counts[parent]  # children of each child's parent
    scales = model.scales().detach()[parent]
    rot = quat_to_rotmat(model.quat.detach())[parent]
    eps = torch.randn(parent.numel(), 3, generator=gen, dtype=model.dtype)
    if mode == "upstream":
        offsets = eps * scales
        scale_log = torch.log(scales / (0.8 * n[:, None].to(scales.dtype)))
        opacity_logit = model.opacity_logit.detach()[parent]
    else:
        offsets = eps * scales * spread
        scale_log = torch.log(scales * math.sqrt(1.0 - spread * spread))
        opacity_logit = _stacked_opacity_logit(model.opacities().detach(), counts)[parent]
    means = model.means.detach()[parent] + torch.bmm(rot, offsets[..., None])[..., 0]
    return GaussianModel(means, model.sh_dc.detach()[parent], model.sh_rest.detach()[parent],
                         opacity_logit, scale_log, model.quat.detach()[parent], model.sh_degree)


def _stacked_opacity_logit(opacity: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Per parent, the logit of :func:`stacked_opacity` for its number of children."""
    out = torch.empty_like(opacity)
    for n in torch.unique(counts).tolist():
        sel = counts == n
        c = stacked_opacity(opacity[sel], int(n)).clamp(1e-6, 1.0 - 1e-6)
        out[sel] = torch.log(c / (1.0 - c))
    return out


# ------------------------------------------------------------------------------------------------
# Level of detail
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LodConfig:
    """What :func:`reduce_model` may leave out or merge.

    Attributes:
        min_opacity: Gaussians below it are left out (the default, 1/255, is the rasterizer's own
            alpha threshold: they never reach a pixel, so leaving them out is exact).
        merge_below_px: Gaussians whose largest projected std (pixels, the largest scale over the
            nearest depth among the cameras that see them) is below it are merged; 0 = none.
        cell_px: size of a merge cell in pixels at the nearest depth of its Gaussians, and
        cell_sigmas: at least this many of the Gaussian's largest std (cells of a power-of-two
            ladder of world sizes, so cells of neighbouring depths and sizes nest).
        max_gaussians: cap on the count (None = none): the merge threshold ``merge_below_px``
            grows by ``cap_growth`` until the reduced model holds it (the cells follow the sizes
            of the Gaussians merged), then, once every seen Gaussian is a candidate, ``cell_px``
            grows (at most ``cap_rounds`` rounds in all).
        cap_growth, cap_rounds: see ``max_gaussians``.
        drop_unseen: leave out Gaussians that no given camera sees (centre behind the near plane
            or outside the image by more than 3 std); off by default: a localization renders
            between the cameras.
    """

    min_opacity: float = 1.0 / 255.0
    merge_below_px: float = 0.35
    cell_px: float = 1.0
    cell_sigmas: float = 1.0
    max_gaussians: Optional[int] = None
    cap_growth: float = 1.5
    cap_rounds: int = 12
    drop_unseen: bool = False

    def __post_init__(self):
        check_real(self.min_opacity, "LodConfig.min_opacity", 0.0, 1.0, hi_open=True)
        check_real(self.merge_below_px, "LodConfig.merge_below_px", 0.0)
        check_real(self.cell_px, "LodConfig.cell_px", 0.0, lo_open=True)
        check_real(self.cell_sigmas, "LodConfig.cell_sigmas", 0.0)
        if self.max_gaussians is not None:
            check_int(self.max_gaussians, "LodConfig.max_gaussians", 1)
        check_real(self.cap_growth, "LodConfig.cap_growth", 1.0, lo_open=True)
        check_int(self.cap_rounds, "LodConfig.cap_rounds", 0)
        check_bool(self.drop_unseen, "LodConfig.drop_unseen")


@dataclass
class LodInfo:
    """What :func:`reduce_model` did.

    Attributes:
        input_count, output_count: Gaussians before and after.
        dropped_opacity: left out for their opacity.
        dropped_unseen: left out as seen by no camera (``drop_unseen``).
        merged_inputs: Gaussians merged; merged_outputs: the Gaussians they became.
        kept: Gaussians passed through unchanged.
        merge_scale, cell_scale: growth applied by the cap to ``merge_below_px`` and to
            ``cell_px`` (1 = none).
        capped: the cap still did not hold after ``cap_rounds`` (the model is above it).
        seconds: wall time.
    """

    input_count: int
    output_count: int
    dropped_opacity: int
    dropped_unseen: int
    merged_inputs: int
    merged_outputs: int
    kept: int
    merge_scale: float
    cell_scale: float
    capped: bool
    seconds: float

    def to_dict(self) -> Dict[str, object]:
        """The fields as a dict (JSON-ready)."""
        return asdict(self)


def _c2w_stack(cameras_c2w: Union[torch.Tensor, np.ndarray, Sequence]) -> torch.Tensor:
    """``[C, 4, 4]`` float64 camera-to-world matrices; ValueError otherwise."""
    try:
        c2w = torch.as_tensor(np.asarray(
            [np.asarray(c, dtype=np.float64) for c in cameras_c2w]
            if not isinstance(cameras_c2w, (torch.Tensor, np.ndarray)) else
            (cameras_c2w.detach().cpu().numpy() if isinstance(cameras_c2w, torch.Tensor)
             else cameras_c2w), dtype=np.float64))
    except (TypeError, ValueError) as e:
        raise ValueError(f"cameras_c2w must be a sequence of [4, 4] matrices ({e})") from e
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or c2w.shape[0] == 0:
        raise ValueError("cameras_c2w must be a non-empty sequence of [4, 4] camera-to-world "
                         f"matrices, got shape {list(c2w.shape)}")
    if not torch.isfinite(c2w).all():
        raise ValueError("cameras_c2w must be finite")
    return c2w


def _footprints(means: torch.Tensor, max_scale: torch.Tensor, intrinsics: Intrinsics,
                c2w: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per Gaussian: its nearest depth among the cameras that see it, and its footprint there.

    Returns ``(near, sigma_px)``: the depth (inf when no camera sees it) and the largest scale
    projected at that depth [px].
    """
    f32 = torch.float32
    near = torch.full((means.shape[0],), math.inf, dtype=f32)
    m = means.detach().to(f32)
    margin = 3.0 * max_scale.detach().to(f32)
    W, H = intrinsics.width, intrinsics.height
    for k in range(c2w.shape[0]):
        R, t = c2w[k, :3, :3].to(f32), c2w[k, :3, 3].to(f32)
        cam = (m - t) @ R  # world -> camera (OpenCV axes)
        z = cam[:, 2]
        inv_z = 1.0 / z.clamp_min(1e-9)
        u = (intrinsics.fx * inv_z) * cam[:, 0] + intrinsics.cx_px
        v = (intrinsics.fy * inv_z) * cam[:, 1] + intrinsics.cy_px
        slack_x = (intrinsics.fx * inv_z) * margin + 0.5
        slack_y = (intrinsics.fy * inv_z) * margin + 0.5
        seen = (z > 0.2) & ((u + slack_x) > 0) & ((u - slack_x) < W) & ((v + slack_y) > 0) & (
            (v - slack_y) < H)
        near = torch.where(seen, torch.minimum(near, z), near)
    near = near.to(torch.float64)
    focal = max(intrinsics.fx, intrinsics.fy)
    sigma_px = focal * max_scale.to(torch.float64) / near
    return near, sigma_px


def _rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z) unit quaternions ``[n, 4]`` of proper rotations ``[n, 3, 3]``.

    Shepperd's method: of the four candidate formulas, the one with the largest divisor.
    """
    m = R
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = torch.stack([
        torch.stack([1 + tr, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                     m[:, 1, 0] - m[:, 0, 1]], -1),
        torch.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                     m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
        torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0],
                     1 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
        torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                     1 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1]], -1),
    ], 1)  # [n, 4 candidates, 4]; candidate k has 4 q_k^2 in entry k
    diag = torch.stack([cands[:, k, k] for k in range(4)], -1)
    best = diag.argmax(-1)
    q = cands[torch.arange(R.shape[0]), best]
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    return torch.nn.functional.normalize(q, dim=-1)


def _cell_ids(means: torch.Tensor, cell_world: torch.Tensor) -> torch.Tensor:
    """Cluster index of each point: its cell in a power-of-two ladder of world sizes.

    A point's cell has the largest ladder size not above its ``cell_world``; points in cells of
    the same size and position share a cluster.
    """
    level = torch.floor(torch.log2(cell_world))
    coords = torch.floor(means.to(torch.float64) / torch.exp2(level)[:, None])
    key = torch.cat([level[:, None], coords], 1).to(torch.int64)
    if key.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64)
    lo = key.min(0).values
    span = (key.max(0).values - lo + 1).tolist()
    if math.prod(span) >= 2 ** 62:  # rows too spread out to pack in one int64
        return torch.unique(key, dim=0, return_inverse=True)[1]
    k = key - lo
    flat = ((k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]) * span[3] + k[:, 3]
    return torch.unique(flat, return_inverse=True)[1]  # the same (lexicographic) order


def _merge(model: GaussianModel, members: torch.Tensor, cluster: torch.Tensor) -> GaussianModel:
    """One Gaussian per cluster of ``members`` (moment-matched; see the module docstring)."""
    n = int(cluster.max()) + 1 if cluster.numel() else 0
    f64 = torch.float64
    o = model.opacities().detach()[members, 0].to(f64)
    s = model.scales().detach()[members].to(f64)
    R = quat_to_rotmat(model.quat.detach()[members].to(f64))
    mu_i = model.means.detach()[members].to(f64)
    w = o * s.prod(-1)
    w = torch.where(w > 0, w, torch.full_like(w, 1e-30))

    def wsum(x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros((n,) + x.shape[1:], dtype=f64)
        return out.index_add_(0, cluster, x * w.view(-1, *([1] * (x.dim() - 1))))

    W = wsum(torch.ones_like(w))
    mu = wsum(mu_i) / W[:, None]
    cov_i = R @ torch.diag_embed(s * s) @ R.transpose(1, 2)
    second = wsum(cov_i + mu_i[:, :, None] * mu_i[:, None, :]) / W[:, None, None]
    cov = second - mu[:, :, None] * mu[:, None, :]
    evals, evecs = torch.linalg.eigh(0.5 * (cov + cov.transpose(1, 2)))
    evecs = evecs * torch.where(torch.linalg.det(evecs) < 0, -1.0, 1.0)[:, None, None]
    scales = evals.clamp_min(1e-20).sqrt()
    log_t = torch.zeros(n, dtype=f64).index_add_(0, cluster, torch.log1p(-o.clamp(max=1 - 1e-7)))
    opacity = (1.0 - torch.exp(log_t)).clamp(1e-7, 1 - 1e-7)
    dt = model.dtype
    return GaussianModel(
        mu.to(dt), (wsum(model.sh_dc.detach()[members].to(f64)) / W[:, None, None]).to(dt),
        (wsum(model.sh_rest.detach()[members].to(f64)) / W[:, None, None]).to(dt),
        torch.log(opacity / (1.0 - opacity)).to(dt)[:, None], torch.log(scales).to(dt),
        _rotmat_to_quat(evecs).to(dt), model.sh_degree)


@dataclass
class _MergePlan:
    """Which Gaussians pass through and which merge into which cluster."""

    passthrough: torch.Tensor  # bool [P]
    grouped: torch.Tensor  # indices of the merged Gaussians
    ids: torch.Tensor  # their cluster, 0 .. clusters - 1
    clusters: int

    @property
    def count(self) -> int:
        """Gaussians of the reduced model."""
        return int(self.passthrough.sum()) + self.clusters


def _plan_merge(model: GaussianModel, max_scale: torch.Tensor, keep: torch.Tensor,
                near: torch.Tensor, sigma_px: torch.Tensor, focal: float, merge_px: float,
                cell_px: float, cell_sigmas: float) -> _MergePlan:
    """Kept Gaussians pass through, the small seen ones sharing a cell merge."""
    small = keep & torch.isfinite(near) & (sigma_px < merge_px)
    members = torch.nonzero(small).flatten()
    cell = torch.maximum(cell_px * near[members] / focal,
                         cell_sigmas * max_scale[members].to(torch.float64))
    cluster = _cell_ids(model.means.detach()[members], cell)
    sizes = torch.bincount(cluster, minlength=int(cluster.max()) + 1 if cluster.numel() else 0)
    alone = sizes[cluster] == 1
    grouped = members[~alone]
    passthrough = keep.clone()
    passthrough[grouped] = False
    ids = torch.unique(cluster[~alone], return_inverse=True)[1]
    return _MergePlan(passthrough, grouped, ids, int(ids.max()) + 1 if ids.numel() else 0)


def _apply(model: GaussianModel, plan: _MergePlan) -> GaussianModel:
    """The reduced model of a plan: the passed-through Gaussians, then the merged ones."""
    if plan.grouped.numel() == 0:
        return model.index(plan.passthrough)
    return GaussianModel.concatenate([model.index(plan.passthrough),
                                      _merge(model, plan.grouped, plan.ids)])


def reduce_model(model: GaussianModel, intrinsics: Intrinsics,
                 cameras_c2w: Union[torch.Tensor, np.ndarray, Sequence],
                 cfg: Optional[LodConfig] = None) -> Tuple[GaussianModel, LodInfo]:
    """A reduced model for rendering at ``intrinsics`` from around ``cameras_c2w``.

    Args:
        model: the full model (CPU).
        intrinsics: the working resolution (the size of a pixel).
        cameras_c2w: ``[C, 4, 4]`` camera-to-world poses (OpenCV axes) the model will be seen from
            (e.g. the candidate views); a Gaussian's footprint is taken at its nearest depth
            among those that see it.
        cfg: what to leave out and merge (None = ``LodConfig()``).

    Returns:
        ``(reduced model, LodInfo)``; the same inputs always give the same model.

    Raises:
        ValueError: a bad model, intrinsics, camera list or config.
    """
    t0 = time.perf_counter()
    cfg = LodConfig() if cfg is None else cfg
    if not isinstance(cfg, LodConfig):
        raise ValueError(f"cfg must be a LodConfig, got {type(cfg).__name__}")
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise ValueError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    c2w = _c2w_stack(cameras_c2w)
    opacity = model.opacities().detach()[:, 0]
    max_scale = model.scales().detach().max(-1).values
    near, sigma_px = _footprints(model.means.detach(), max_scale, intrinsics, c2w)
    keep = opacity >= cfg.min_opacity
    dropped_opacity = int((~keep).sum())
    unseen = keep & ~torch.isfinite(near)
    if cfg.drop_unseen:
        keep = keep & torch.isfinite(near)
    focal = float(max(intrinsics.fx, intrinsics.fy))
    seen = keep & torch.isfinite(near)
    largest = float(sigma_px[seen].max()) if bool(seen.any()) else 0.0
    merge_scale, cell_scale, rounds = 1.0, 1.0, 0
    while True:
        plan = _plan_merge(model, max_scale, keep, near, sigma_px, focal,
                           cfg.merge_below_px * merge_scale, cfg.cell_px * cell_scale,
                           cfg.cell_sigmas)
        over = cfg.max_gaussians is not None and plan.count > cfg.max_gaussians
        if not over or rounds >= cfg.cap_rounds:
            break
        # the threshold first; once every seen Gaussian is a candidate, the cells
        if cfg.merge_below_px * merge_scale <= largest:
            merge_scale *= cfg.cap_growth
        else:
            cell_scale *= cfg.cap_growth
        rounds += 1
    out = _apply(model, plan)
    merged_in, merged_out = int(plan.grouped.numel()), plan.clusters
    info = LodInfo(
        input_count=model.num_gaussians, output_count=out.num_gaussians,
        dropped_opacity=dropped_opacity, dropped_unseen=int(unseen.sum()) if cfg.drop_unseen else 0,
        merged_inputs=merged_in, merged_outputs=merged_out,
        kept=out.num_gaussians - merged_out, merge_scale=merge_scale, cell_scale=cell_scale,
        capped=over,
        seconds=time.perf_counter() - t0)
    return out, info
