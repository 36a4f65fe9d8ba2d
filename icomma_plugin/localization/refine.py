"""Photometric refinement: Levenberg-Marquardt on the paper's comparing loss.

It minimises the masked MSE between render and query over the pose, at one or more scales
(coarse to fine). By default each colour channel of the render is first mapped by the gain and
offset that fit it best to the query (``RefineConfig.exposure``): a photo's exposure is not the
model's.

The gradient is the rasterizer's exact analytic pose gradient. The Hessian is a Gauss-Newton
matrix ``2 J^T J / N`` of the render's Jacobian ``J = dI/dxi``, either

- ``finite_difference`` (default): ``J`` by forward differences of the render (6 forward
  renders); the steps are then close to Newton steps and a few of them reach the optimum; or
- ``motion_field``: a model with no extra render: a small camera motion ``xi`` moves the pixel of
  a surface point at depth ``z`` by ``du = (du/dxi) xi`` (the motion field of a pinhole camera),
  so the render changes by ``-grad(I) . du``.

Optionally a pixel's squared difference counts through a Cauchy loss (``RefineConfig.robust``),
so that what the model cannot explain pulls the pose less.

A step ``-(H + lambda diag H)^-1 g`` is taken only when the loss goes down (Nielsen's damping
update), so the loss never increases. The pose is ``w2c <- se3_exp(step) @ w2c`` (a camera-frame
increment, docs/CONTRACTS.md). The mask of the loss is fixed per scale level: valid query pixels
where the render (or the query's alpha, when given) shows the scene (``verify.coverage_mask``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from ..camera import Intrinsics
from ..checks import check_bool, check_choice, check_int, check_real
from ..losses import compare_loss
from ..pose.se3 import se3_exp
from .state import LocalizationState, Observation
from .types import Stage
from .verify import coverage_mask

logger = logging.getLogger(__name__)

HESSIANS = ("finite_difference", "motion_field")
EXPOSURES = ("none", "affine")
ROBUST_LOSSES = ("none", "cauchy")

__all__ = [
    "RefineConfig",
    "RefineOutcome",
    "exposure_fit",
    "gauss_newton_hessian",
    "gaussian_blur",
    "refine_photometric",
]


@dataclass
class RefineConfig:
    """Constants of the photometric refinement.

    scales: working scale of each level, coarse to fine (fractions of the working resolution).
    blur: Gaussian blur sigma [px of the level] applied to render and query at each level (a
        blurred image stays linear in the pose over a wider misalignment). Same length as
        ``scales``. The default is one sharp level at the working resolution: after the geometric
        stage the pose is within ~0.2 deg, and on a fitted scene the optimum of a blurred or
        downscaled comparison lies elsewhere (lego: a sigma-4 level moved 0.10 deg poses to 0.27
        deg), so coarse levels cost time and accuracy there (docs/BENCHMARK.md).
    iterations: LM iterations per level (same length as ``scales``). 3: from the geometric
        stage's pose the error stops falling after the third step on most lego starts (6 for
        all took 30 % more time for the same median error; docs/SPEED.md).
    extra_iterations, extra_min_gain: after a level's ``iterations``, up to ``extra_iterations``
        more steps while the last one lowered the loss by more than ``extra_min_gain`` (a share
        of the loss): a pose still converging. From 0.2-0.4 deg off, the Gauss-Newton steps of
        a fitted scene fall short (its loss is shallower than ``J^T J`` says) and three steps
        leave it 0.1-0.2 deg off (docs/LOCALIZATION.md, "Steps while the loss falls"). Not with
        a level of detail (a large model): each step renders the full model (0.4-0.7 s at 800 px
        for 300k-1M Gaussians).
    lambda_init: initial LM damping (relative to the Hessian's diagonal).
    hessian: ``"finite_difference"``: Gauss-Newton from the exact Jacobian of the render by
        forward differences (6 extra forward renders); ``"motion_field"``: the cheap model of the
        module docstring (no extra render; its Jacobian is 15-30 % short and 0.9-0.97 aligned on
        the demo scene, so it needs several times as many steps).
    fd_step: forward-difference step of the twist (radians / world units).
    hessian_scale: the finite-difference Jacobian is rendered at this share of the level's
        resolution (1: at it); the Gauss-Newton matrix is a mean over pixels, so a coarser one
        approximates it at a fraction of the cost (7 renders at a quarter of the pixels at 0.5).
    hessian_reduced: the finite-difference Jacobian is rendered from the level of detail's
        reduced model when the Localizer has one (the loss, its gradient and the steps stay the
        full model's: a Hessian only scales the steps, and a step is taken only when the full
        model's loss goes down).
    hessian_every: recompute the finite-difference Hessian after this many accepted steps (0:
        once per level; each recompute costs 6 renders). The motion-field Hessian is recomputed
        at every accepted step (free).
    secant: between recomputes, correct the Hessian with BFGS updates from the exact gradients
        (on a fitted scene the loss is shallower than ``J^T J`` says, and plain Gauss-Newton
        steps fall short).
    stop_rot_deg, stop_trans_rel: a step smaller than this (rotation, and translation relative to
        the scene depth) ends a level.
    exposure: ``"none"``: the render is compared with the query as it is; ``"affine"``: each
        colour channel of the render is first mapped by the gain and offset that fit it best to
        the query over the mask (least squares, the gain clamped to ``exposure_gain``), so that a
        photo's exposure and white balance (which a fitted model does not know) do not pull the
        pose. The loss is then the profiled one, ``min_{a,b} |a I + b - Q|^2``; its gradient at
        the fitted ``a, b`` is exact (the envelope theorem), and the Gauss-Newton matrix is
        the profiled loss's (each channel's Jacobian scaled by ``a`` and without its part along
        ``(I, 1)``, which ``a, b`` absorb: Kaufman's variable projection). Default
        ``"affine"``: on fox's held-out phone photos (exposure changing from photo to photo) the
        median error fell from 0.030 to 0.021 deg; on bird, goldcape and lego it stayed within
        0.01 deg (docs/LOCALIZATION.md).
    exposure_gain: the range ``(lo, hi)`` the fitted gain is clamped to.
    robust: ``"none"``: the loss is the mean squared difference; ``"cauchy"``: each pixel's
        squared difference ``s`` (summed over the channels) counts as ``c2 log(1 + s / c2)``,
        which is ``s`` for small differences and grows only logarithmically for large ones, so
        that pixels the model cannot explain (floaters, a moved background, a highlight) pull the
        pose less. ``c2`` is ``robust_scale**2`` times the median ``s`` over the mask at the
        level's first render, fixed for the level. Its Gauss-Newton matrix weighs each pixel by
        ``1 / (1 + s / c2)``, recomputed at every accepted step from the level's latest Jacobian
        and the new render (iteratively reweighted least squares; with ``hessian_scale`` below 1 the
        Jacobian's pixels are not the level's, and BFGS updates it as for the squared
        difference): with the first render's weights kept, the steps overshot and stalled.
        Off by default: on held-out photos of five real-capture fits it gained on fox (per-photo
        median 0.038 -> 0.025 and 0.028 -> 0.019 deg) but not on bird or goldcape (mean error
        up 0.02-0.03 deg), and lego's largest error grew 0.04 -> 0.07 deg; more poses were
        called ``ok`` (249 -> 280 of 281), none wrongly (docs/LOCALIZATION.md).
    robust_scale: that multiple of the median residual (1.5 and 3 gave the same errors on fox
        and bird, measured with the first, fixed-weight version).
    focal: also estimate the photo's focal length (a 7th parameter, the log of a scale of both
        focal lengths; ``state.focal_scale``), for photos whose intrinsics are approximate: a
        focal length 4 % off moves a pose by 0.1-0.8 deg (docs/LOCALIZATION.md). Its Jacobian
        column is a forward difference too (a 7th render), its gradient the Gauss-Newton one of
        that column (``2 J^T W r / N``; the pose's stays the backward pass's). The focal length
        trades against the camera's distance, and along that valley the Jacobian turns: the
        finite-difference Hessian is made again after every accepted step (7 renders each) and
        a level takes twice its ``iterations`` and ``extra_iterations``. The default method
        starts it from the matches' reprojection fit (``robust._focal_from_matches``): fox's
        photos with their focal lengths 4 % off, 0.49-0.51 -> 0.03-0.07 deg. Needs the
        Hessian at the level's own resolution (``hessian_scale`` 1) and the squared difference
        (``robust`` none). Off by default.
    stop_focal: a step of the focal length's log smaller than this (with the pose's) ends a level.
    still_rot_deg, still_trans_rel: the pose counts as having stopped moving (a signal of the
        verdict) when the last step of the finest level was smaller than this. On a fitted scene
        the last steps creep along flat directions of the loss (0.01-0.1 deg) without changing
        the error; on the lego benchmark every pose still moving by less than 0.25 deg was right.
    """

    scales: Tuple[float, ...] = (1.0,)
    blur: Tuple[float, ...] = (0.0,)
    iterations: Tuple[int, ...] = (3,)
    extra_iterations: int = 3
    extra_min_gain: float = 1e-3
    lambda_init: float = 1e-4
    hessian: str = "finite_difference"
    fd_step: float = 1e-3
    hessian_scale: float = 1.0
    hessian_reduced: bool = True
    hessian_every: int = 0
    secant: bool = True
    stop_rot_deg: float = 3e-3
    stop_trans_rel: float = 3e-5
    still_rot_deg: float = 0.25
    still_trans_rel: float = 2.5e-3
    exposure: str = "affine"
    exposure_gain: Tuple[float, float] = (0.5, 2.0)
    robust: str = "none"
    robust_scale: float = 3.0
    focal: bool = False
    stop_focal: float = 1e-4

    def __post_init__(self):
        self.exposure_gain = tuple(float(g) for g in self.exposure_gain)
        self.scales = tuple(float(s) for s in self.scales)
        self.blur = tuple(float(b) for b in self.blur)
        self.iterations = tuple(int(i) for i in self.iterations)
        if not self.scales or not (len(self.scales) == len(self.iterations) == len(self.blur)):
            raise ValueError(
                f"RefineConfig.scales, .blur and .iterations must be non-empty and of equal "
                f"length, got {self.scales}, {self.blur} and {self.iterations}"
            )
        if any(not (0 < s <= 4) for s in self.scales):
            raise ValueError(f"RefineConfig.scales must lie in (0, 4], got {self.scales}")
        if any(not (0 <= b <= 32) for b in self.blur):
            raise ValueError(f"RefineConfig.blur must lie in [0, 32] px, got {self.blur}")
        check_choice(self.hessian, "RefineConfig.hessian", HESSIANS)
        check_choice(self.exposure, "RefineConfig.exposure", EXPOSURES)
        check_choice(self.robust, "RefineConfig.robust", ROBUST_LOSSES)
        check_real(self.robust_scale, "RefineConfig.robust_scale", 0.0, lo_open=True)
        g = self.exposure_gain
        if len(g) != 2 or not (0 < g[0] <= 1 <= g[1]):
            raise ValueError(f"RefineConfig.exposure_gain must be (lo, hi) with 0 < lo <= 1 <= hi, "
                             f"got {self.exposure_gain}")
        if any(i < 0 for i in self.iterations):
            raise ValueError(f"RefineConfig.iterations must be >= 0, got {self.iterations}")
        check_int(self.extra_iterations, "RefineConfig.extra_iterations", 0)
        check_real(self.extra_min_gain, "RefineConfig.extra_min_gain", 0.0, 1.0)
        check_real(self.lambda_init, "RefineConfig.lambda_init", 0.0, lo_open=True)
        check_real(self.fd_step, "RefineConfig.fd_step", 0.0, 0.1, lo_open=True)
        check_real(self.hessian_scale, "RefineConfig.hessian_scale", 0.0, 1.0, lo_open=True)
        check_int(self.hessian_every, "RefineConfig.hessian_every", 0)
        check_bool(self.secant, "RefineConfig.secant")
        check_bool(self.hessian_reduced, "RefineConfig.hessian_reduced")
        for name in ("stop_rot_deg", "stop_trans_rel", "still_rot_deg", "still_trans_rel",
                     "stop_focal"):
            check_real(getattr(self, name), f"RefineConfig.{name}", 0.0)
        check_bool(self.focal, "RefineConfig.focal")
        if self.focal and not self.can_estimate_focal:
            raise ValueError("RefineConfig.focal needs hessian='finite_difference', "
                             f"hessian_scale=1 and robust='none', got {self.hessian!r}, "
                             f"{self.hessian_scale} and {self.robust!r}")

    @property
    def can_estimate_focal(self) -> bool:
        """Whether the focal length can be a 7th parameter here (``focal``'s requirements)."""
        return (self.hessian == "finite_difference" and self.hessian_scale == 1.0
                and self.robust == "none")

    @property
    def fitted_gain_range(self) -> Optional[Tuple[float, float]]:
        """The range of the exposure's fitted gain, or None when no exposure is fitted."""
        return None if self.exposure == "none" else self.exposure_gain


@dataclass
class RefineOutcome:
    """What the refinement ends with: the pose, its steps, the loss before and after."""

    w2c: np.ndarray
    iterations: int
    accepted: int
    loss_start: Optional[float]
    loss_end: Optional[float]
    converged: bool
    last_step_rot_deg: Optional[float] = None
    last_step_trans: Optional[float] = None
    observation: Optional[Observation] = None  # the render at ``w2c`` (unmatched), if one was made
    focal_scale: float = 1.0  # the focal lengths' scale it ended at (``RefineConfig.focal``)


def _filled_depth(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Depth where the render is opaque, spread a few pixels into empty space; the median elsewhere.

    The spread covers where the image gradient of a silhouette lies.
    """
    fg = (alpha > 0.5).to(depth.dtype)
    if not bool(fg.any()):
        return torch.ones_like(depth)
    med = depth[fg > 0].median()
    num = F.avg_pool2d((depth * fg)[None], 7, stride=1, padding=3)[0]
    den = F.avg_pool2d(fg[None], 7, stride=1, padding=3)[0]
    spread = torch.where(den > 1e-3, num / den.clamp_min(1e-3), med)
    return torch.where(fg > 0, depth, spread)


def _image_gradient(img: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Central differences ``(d/dx, d/dy)`` of ``[C, H, W]`` (replicate border)."""
    p = F.pad(img[None], (1, 1, 1, 1), mode="replicate")[0]
    gx = 0.5 * (p[:, 1:-1, 2:] - p[:, 1:-1, :-2])
    gy = 0.5 * (p[:, 2:, 1:-1] - p[:, :-2, 1:-1])
    return gx, gy


def gauss_newton_hessian(color: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
                         mask: torch.Tensor, intrinsics: Intrinsics,
                         exposure: Optional[Tuple[torch.Tensor, torch.Tensor]] = None,
                         norm: Optional[float] = None) -> torch.Tensor:
    """6x6 Gauss-Newton Hessian (float64) of the masked MSE w.r.t. a camera-frame twist.

    The twist is ``(rho, phi)``; the Hessian comes from the motion-field model of the render
    (module docstring). ``exposure``: ``(gains [C], base [C, H, W])`` for the exposure-profiled
    loss (``_gauss_newton``). ``mask``: the pixels' weights; ``norm``: the loss's normaliser
    (default: the weights' sum).
    """
    with torch.no_grad():
        c = color.detach().double()
        z = _filled_depth(depth.detach().double(), alpha.detach().double())[0]
        H, W = z.shape
        v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64, device=c.device),
                              torch.arange(W, dtype=torch.float64, device=c.device), indexing="ij")
        fx, fy = intrinsics.fx, intrinsics.fy
        x = (u - intrinsics.cx_px) / fx
        y = (v - intrinsics.cy_px) / fy
        iz = 1.0 / z.clamp_min(1e-9)
        zero = torch.zeros_like(x)
        # du/dxi and dv/dxi, [6, H, W] each (xi = (rho, phi), camera frame)
        du = fx * torch.stack([iz, zero, -x * iz, -x * y, 1 + x * x, -y])
        dv = fy * torch.stack([zero, iz, -y * iz, -(1 + y * y), x * y, x])
        gx, gy = _image_gradient(c)  # [C, H, W]
        J = gx[:, None] * du[None] + gy[:, None] * dv[None]  # [C, 6, H, W]
        return _gauss_newton(J, mask, exposure, norm)


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[C, H, W]`` (reflect border); differentiable."""
    if sigma <= 0:
        return img
    r = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-r, r + 1, dtype=img.dtype, device=img.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    C = img.shape[0]
    y = F.pad(img[None], (r, r, r, r), mode="reflect")
    y = F.conv2d(y, k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    y = F.conv2d(y, k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)
    return y[0]


def exposure_fit(render: torch.Tensor, query: torch.Tensor, mask: torch.Tensor,
                 gain_range: Tuple[float, float]) -> Tuple[torch.Tensor, torch.Tensor]:
    """Per-channel gain and offset ``(a, b)``, ``[C, 1, 1]`` each: ``a render + b`` fits ``query``.

    Weighted least squares over ``mask``; the gain clamped to ``gain_range``, the offset then
    refitted. Detached: the profiled loss's gradient at the optimum needs no derivative of
    ``a, b`` (envelope theorem).
    """
    with torch.no_grad():
        return _affine_fit(render.detach(), query.detach(), mask.detach(), gain_range)


def _affine_fit(r: torch.Tensor, q: torch.Tensor, m: torch.Tensor,
                gain_range: Tuple[float, float]) -> Tuple[torch.Tensor, torch.Tensor]:
    """``exposure_fit``, differentiable in ``r`` (a loss other than the fit's own needs it)."""
    q, m = q.to(r.dtype), m.to(r.dtype)
    w = float(m.sum())
    if w < 1:
        one = torch.ones(r.shape[0], 1, 1, dtype=r.dtype, device=r.device)
        return one, torch.zeros_like(one)
    mr = (r * m).sum((1, 2), keepdim=True) / w
    mq = (q * m).sum((1, 2), keepdim=True) / w
    var = (((r - mr) ** 2) * m).sum((1, 2), keepdim=True)
    cov = ((r - mr) * (q - mq) * m).sum((1, 2), keepdim=True)
    a = torch.where(var > 1e-12, cov / var.clamp_min(1e-12), torch.ones_like(var))
    a = a.clamp(gain_range[0], gain_range[1])
    return a, mq - a * mr


def _hessian_and_jacobian(state, cfg, w2c, scale, out, mask, intr, blur, query, robust):
    """The level's Gauss-Newton matrix at ``w2c`` (``cfg.hessian``), and its ``_Jacobian``.

    The Jacobian is the finite-difference one it came from (None: motion field). With
    ``cfg.exposure``, of the exposure-profiled loss: the gains fitted to ``query`` at the render
    ``out``. With ``robust`` (the level's ``_Cauchy``), each pixel weighted by it.
    """
    img = gaussian_blur(out.color.detach(), blur)
    gains = None
    if cfg.fitted_gain_range is not None:
        gains = exposure_fit(img, query, mask, cfg.fitted_gain_range)[0].flatten().double()
    if cfg.hessian == "motion_field":
        weights = mask
        if robust is not None:
            weights = robust.weights(_sq_residual(img, query, mask, cfg.fitted_gain_range), mask)
        return gauss_newton_hessian(img, out.depth, out.alpha, weights, intr,
                                    None if gains is None else (gains, img),
                                    norm=float(mask.sum())).cpu(), None
    args = (state, cfg, w2c, scale, out, mask, blur, gains, query)
    if not (cfg.hessian_reduced and state.reduced is not None):
        jac = _fd_jacobian(*args, own_render=False)
    else:
        with state.serving("hessian", reduced=True):
            jac = _fd_jacobian(*args, own_render=True)
    return jac.matrix(robust, cfg.fitted_gain_range), jac


#: Pixels a block of ``_gauss_newton``: each block's moments are summed in the Jacobian's dtype
#: and the blocks in float64, so a float32 Jacobian's matrix stays within ~1e-6 of float64's.
_GN_BLOCK = 1 << 16


def _gauss_newton(J: torch.Tensor, mask: torch.Tensor, exposure=None,
                  norm: Optional[float] = None) -> torch.Tensor:
    """``2 J^T W J / (C N)`` (float64, on the CPU) of a ``[C, K, H, W]`` Jacobian, ``W`` = mask.

    ``N`` is ``norm``, or the mask's sum (a robust loss's weights are not its normaliser).
    ``exposure`` ``(gains [C], base [C, H, W])``: the Gauss-Newton matrix of the exposure-profiled
    loss (Kaufman's variable projection): each channel's Jacobian scaled by its gain and with its
    part along the fitted basis ``(base render, 1)`` removed, which the gain and offset absorb.
    That projection is applied to the 6x6 moments, not to the Jacobian: with ``a = J W 1``,
    ``c = J W r`` (``r`` the base render less its weighted mean, so orthogonal to 1) and
    ``s = sum W``, the projected ``J'`` has ``J' W J'^T = J W J^T - a a^T / s - c c^T / r^T W r``
    (one pass over the Jacobian instead of six; a 800x800 render's took 0.4 s). The moments are
    taken in ``J``'s dtype over blocks of ``_GN_BLOCK`` pixels (a float32 Jacobian: half the
    memory traffic of float64) and summed in float64.
    """
    C, K = J.shape[0], J.shape[1]
    Jf = J.reshape(C, K, -1)
    w = mask.detach()[0].reshape(-1).to(J.dtype)
    sw = max(float(w.double().sum()), 1e-12)
    f64 = dict(dtype=torch.float64, device=J.device)
    H, a, c = torch.zeros(C, K, K, **f64), torch.zeros(C, K, **f64), torch.zeros(C, K, **f64)
    b = None if exposure is None else exposure[1].detach().reshape(C, -1).to(J.dtype)
    sb, sbb = torch.zeros(C, **f64), torch.zeros(C, **f64)  # sum W b, sum W b^2 per channel
    for s in range(0, Jf.shape[-1], _GN_BLOCK):
        Jb, wb = Jf[..., s:s + _GN_BLOCK], w[s:s + _GN_BLOCK]
        Jw = Jb * wb
        H += torch.bmm(Jw, Jb.transpose(1, 2)).double()  # [C, 6, 6]
        if b is not None:
            bb = b[:, s:s + _GN_BLOCK]
            a += Jw.sum(-1).double()  # [C, 6]
            c += (Jw * bb.unsqueeze(1)).sum(-1).double()  # J W b, centred below (a matrix-
            # vector bmm took 7x the time of this product on a CPU)
            bw = bb * wb
            sb += bw.sum(-1).double()
            sbb += (bw * bb).sum(-1).double()
    if exposure is not None:
        mean = sb / sw  # r = b - mean: J W r = J W b - a mean, r^T W r = sum W b^2 - sb mean
        c = c - a * mean.unsqueeze(1)
        rr = (sbb - sb * mean).clamp_min(1e-12)
        H = (H - a.unsqueeze(2) * a.unsqueeze(1) / sw
             - c.unsqueeze(2) * c.unsqueeze(1) / rr.view(C, 1, 1))
        H = H * (exposure[0].double() ** 2).view(C, 1, 1)
    # on the CPU, with the twist and its gradient (the Jacobian may be on the GPU)
    return (2.0 * H.sum(0) / (C * max(norm or sw, 1e-12))).cpu()


@dataclass
class _Jacobian:
    """The render's Jacobian ``J`` by forward differences, and what its Gauss-Newton matrix needs.

    ``base``: the (blurred) render it was taken at; ``query`` the photo at its resolution;
    ``exposure`` ``(gains, base)`` or None; ``blur`` the level's blur at its resolution.
    """

    J: torch.Tensor  # [C, 6, H, W] (7 with the focal length), float32
    mask: torch.Tensor  # [1, H, W] float64
    base: torch.Tensor
    query: torch.Tensor
    exposure: Optional[Tuple[torch.Tensor, torch.Tensor]]
    blur: float

    def matrix(self, robust: Optional["_Cauchy"], gain_range, color: Optional[torch.Tensor] = None
               ) -> torch.Tensor:
        """The Gauss-Newton matrix; with ``robust``, each pixel weighted by its residual.

        The residual is the base render's, or that of ``color`` (a later render of the level at
        the Jacobian's resolution: iteratively reweighted least squares with the Jacobian kept).
        """
        weights = self.mask
        if robust is not None:
            img = self.base if color is None else gaussian_blur(color.detach().double(), self.blur)
            weights = robust.weights(_sq_residual(img, self.query, self.mask, gain_range),
                                     self.mask)
        return _gauss_newton(self.J, weights, self.exposure, float(self.mask.sum()))


def _fd_jacobian(state, cfg, w2c, scale, out, mask, blur, gains, query,
                 own_render: bool) -> _Jacobian:
    """The render's Jacobian by forward differences (6 renders).

    ``own_render``: the base render ``out`` is made again here (by the model now served).
    ``gains``: the exposure's per-channel gains (None: no exposure), with the render
    differentiated here as the fitted basis.
    """
    if cfg.hessian_scale < 1.0 or own_render:  # the Jacobian of a coarser (or another) render
        if cfg.hessian_scale < 1.0:
            query = gaussian_blur(state.query_at(scale * cfg.hessian_scale).rgb,
                                  blur * cfg.hessian_scale)
        scale = scale * cfg.hessian_scale
        blur = blur * cfg.hessian_scale
        with torch.no_grad():
            out = state.render(torch.as_tensor(w2c, dtype=torch.float64), scale)
        mask = coverage_mask(Observation(w2c, scale, out.color, out.depth, out.alpha), state)
    # finite differences of the render: J[:, k] = (I(exp(h e_k) w2c) - I(w2c)) / h, in the
    # renders' float32: the difference of two float32 renders is exact to their last bit (float64
    # doubled the memory traffic of a [3, 6, 800, 800] Jacobian, and its Gauss-Newton matrix
    # sums in float64 anyway)
    base = gaussian_blur(out.color.detach().float(), blur)
    J = torch.empty((base.shape[0], 7 if cfg.focal else 6) + tuple(base.shape[1:]),
                    dtype=base.dtype, device=base.device)
    w2c_t = torch.as_tensor(w2c, dtype=torch.float64)
    with torch.no_grad():
        for k in range(6):
            e = torch.zeros(6, dtype=torch.float64)
            e[k] = cfg.fd_step
            img = gaussian_blur(state.render((se3_exp(e) @ w2c_t).numpy(), scale).color.float(),
                                blur)
            torch.sub(img, base, out=J[:, k]).div_(cfg.fd_step)
        if cfg.focal:  # d/d log(focal scale)
            f0 = state.focal_scale
            state.focal_scale = f0 * math.exp(cfg.fd_step)
            try:
                img = gaussian_blur(state.render(w2c, scale).color.float(), blur)
            finally:
                state.focal_scale = f0
            torch.sub(img, base, out=J[:, 6]).div_(cfg.fd_step)
    exposure = None if gains is None else (gains, base)
    return _Jacobian(J, mask.detach().double(), base, query, exposure, blur)


def _jacobian_gradient(jac: _Jacobian, color: torch.Tensor, gain_range,
                       first: int = 0) -> torch.Tensor:
    """The loss's Gauss-Newton gradient from the level's Jacobian, ``[K - first]`` float64.

    Of the Jacobian's columns from ``first`` on (6: the focal length's alone, which is all the
    refinement takes from it).

    ``2 sum_c a_c sum_p W (a_c I_c + b_c - Q_c) J_c / (C sum W)`` of the render ``color`` (at the
    Jacobian's resolution), the exposure ``a, b`` fitted (its derivative is not needed at the fit:
    the envelope theorem). The focal length's column serves its gradient (``focal``); the pose's
    columns give the loss's gradient to the forward differences' accuracy at the Jacobian's own
    render, nearer the loss's differences than the backward pass (docs/LOCALIZATION.md).
    """
    with torch.no_grad():
        img = gaussian_blur(color.detach().to(jac.J.dtype), jac.blur)
        q = jac.query.to(img.dtype)
        w = jac.mask.to(img.dtype)
        C, K = jac.J.shape[0], jac.J.shape[1] - first
        a = torch.ones(C, 1, 1, dtype=img.dtype, device=img.device)
        if gain_range is not None:
            a, b = exposure_fit(img, q, w, gain_range)
            img = a * img + b
        r = (a * (img - q) * w).reshape(C, -1, 1)
        Jf = jac.J[:, first:].reshape(C, K, -1)
        g = torch.zeros(K, dtype=torch.float64, device=img.device)
        for s in range(0, Jf.shape[-1], _GN_BLOCK):  # float32 blocks summed in float64
            g += torch.bmm(Jf[..., s:s + _GN_BLOCK], r[:, s:s + _GN_BLOCK]).double().sum((0, 2))
        return (2.0 * g / (C * max(float(w.double().sum()), 1e-12))).cpu()


def _bfgs_update(hess: torch.Tensor, s: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """BFGS update of ``hess`` so that ``hess @ s = y``.

    That is the curvature along the step that the exact gradients measured; skipped when
    ``y . s`` is not positive.
    """
    ys = float(y @ s)
    Hs = hess @ s
    sHs = float(s @ Hs)
    if ys <= 1e-12 * max(float(y.norm() * s.norm()), 1e-30) or sHs <= 0:
        return hess
    return hess - torch.outer(Hs, Hs) / sHs + torch.outer(y, y) / ys


@dataclass
class _Cauchy:
    """A level's Cauchy loss (``RefineConfig.robust``): ``c2`` is set at its first evaluation."""

    scale: float
    c2: Optional[float] = None

    def loss(self, sq: torch.Tensor, mask: torch.Tensor, channels: int) -> torch.Tensor:
        """``sum(mask c2 log(1 + sq / c2)) / (C sum(mask))`` of per-pixel squared residuals."""
        if self.c2 is None:
            sel = sq.detach()[mask > 0]
            med = float(sel.median()) if sel.numel() else 0.0
            self.c2 = max(self.scale ** 2 * med, 1e-12)
        w = mask.to(sq.dtype)
        c2 = self.c2
        return (w * c2 * torch.log1p(sq / c2)).sum() / (channels * w.sum()).clamp_min(1e-30)

    def weights(self, sq: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The Gauss-Newton weight of each pixel: ``mask / (1 + sq / c2)``."""
        return mask / (1.0 + sq.detach().to(mask.dtype) / self.c2)


def _sq_residual(img: torch.Tensor, query: torch.Tensor, mask: torch.Tensor,
                 gain_range: Optional[Tuple[float, float]]) -> torch.Tensor:
    """Per-pixel squared difference ``[1, H, W]`` (summed over channels), the exposure fitted.

    The fitted gain and offset stay in the autograd graph: they are the least-squares fit, not
    the minimiser of a robust loss, so its gradient needs their derivative (no envelope theorem).
    """
    if gain_range is not None:
        a, b = _affine_fit(img, query, mask.detach(), gain_range)
        img = a * img + b
    return ((img - query.to(img.dtype)) ** 2).sum(0, keepdim=True)


def _evaluate(state: LocalizationState, w2c: np.ndarray, scale: float, mask: Optional[torch.Tensor],
              best: Optional[float], blur: float = 0.0, query: Optional[torch.Tensor] = None,
              want_grad: bool = True, exposure_gain: Optional[Tuple[float, float]] = None,
              robust: Optional[_Cauchy] = None):
    """Loss at ``w2c``, and its gradient and render when it beats ``best``.

    The gradient is w.r.t. the camera-frame twist; ``best`` None always counts as beaten.
    ``mask`` None: the coverage mask of this very render (detached) is made and returned, for the
    caller to keep for the rest of the level. ``want_grad`` False: no backward pass (the level's
    last step: its gradient would be used by nothing). ``exposure_gain``: the loss is the
    exposure-profiled one (``RefineConfig.exposure``), its gain clamped to this range.
    ``robust``: the level's Cauchy loss instead of the squared difference (its scale set here
    when it has none yet).

    Returns:
        (loss, grad or None, render or None, mask): render None when ``best`` was not beaten.
    """
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    w2c_t = se3_exp(xi) @ torch.as_tensor(w2c, dtype=torch.float64)
    out = state.render(w2c_t, scale)
    if mask is None:
        mask = coverage_mask(Observation(w2c, scale, out.color.detach(), out.depth.detach(),
                                         out.alpha.detach()), state)
        if float(mask.sum()) < 16:
            return float("nan"), None, None, mask
    if query is None:
        query = state.query_at(scale).rgb
    img = gaussian_blur(out.color, blur)
    if robust is not None:
        loss = robust.loss(_sq_residual(img, query, mask, exposure_gain), mask, img.shape[0])
    else:
        if exposure_gain is not None:
            a, b = exposure_fit(img, query, mask, exposure_gain)
            img = a * img + b
        loss = compare_loss(img, query.to(out.color.dtype), mask)
    val = float(loss.detach())
    if best is not None and not val < best:
        return val, None, None, mask
    if not want_grad:
        return val, None, out, mask
    with state.timed("backward"):
        loss.backward()
    return val, xi.grad.detach().clone(), out, mask


def _lm_level(state: LocalizationState, cfg: RefineConfig, w2c: np.ndarray, scale: float,
              level: Tuple, start: Tuple, counts: Dict[str, int], scene_depth: float,
              hypothesis: Optional[int]):
    """Levenberg-Marquardt steps at one level, from ``start`` = (loss, grad, render).

    ``level`` = (intrinsics, blur, query, mask, iterations, robust loss or None); ``counts``
    (``total``, ``accepted``) run over all levels.

    Returns:
        (w2c, loss, render at w2c, converged at this level, last step's rotation [deg] and
        translation, or None).
    """
    intr, blur, query, mask, n_it, robust = level
    extra = cfg.extra_iterations
    if cfg.focal:  # twice the steps: along the valley where the focal length and the camera's
        n_it, extra = 2 * n_it, 2 * extra  # distance trade, Gauss-Newton steps fall short
    # steps past the level's own only without a level of detail (each renders the full model)
    n_max = n_it + (extra if state.reduced is None else 0)
    loss, grad, out = start
    hess, jac = _hessian_and_jacobian(state, cfg, w2c, scale, out, mask, intr, blur, query,
                                      robust)
    gain = cfg.fitted_gain_range
    K = 7 if cfg.focal else 6
    if cfg.focal:  # the focal length's log: a 7th parameter (``state.focal_scale``)
        grad = torch.cat([grad, _jacobian_gradient(jac, out.color, gain, first=6)])
    lam, nu = cfg.lambda_init, 2.0
    last_rot = last_trans = None
    drop = 1.0  # the share of the loss the last step took off
    for it in range(n_max):
        if it >= n_it and drop <= cfg.extra_min_gain:
            break  # past the level's steps, only while the loss still falls
        counts["total"] += 1
        damp = torch.diag(torch.diag(hess)).clamp_min(0) + 1e-12 * torch.eye(
            K, dtype=torch.float64
        )
        step = -torch.linalg.solve(hess + lam * damp, grad)
        if not bool(torch.isfinite(step).all()):
            break
        predicted = -float(grad @ step + 0.5 * step @ hess @ step)
        w2c_try = (se3_exp(step[:6]) @ torch.as_tensor(w2c)).numpy()
        last = it == n_max - 1  # the last step's gradient would serve no further step
        focal = state.focal_scale
        if cfg.focal:
            state.focal_scale = focal * math.exp(float(step[6]))
        loss_try, grad_try, out_try, _ = _evaluate(state, w2c_try, scale, mask, loss, blur, query,
                                                   want_grad=not last, exposure_gain=gain,
                                                   robust=robust)
        ok = out_try is not None
        if cfg.focal and not ok:
            state.focal_scale = focal
        state.record(state.new_record(Stage.REFINE, w2c_try, loss=loss_try, loss_compare=loss_try,
                                      accepted=ok, hypothesis=hypothesis, scale=scale, lr=lam))
        if not ok:
            drop = 0.0
            lam *= nu
            nu *= 2.0
            if lam > 1e6:
                return w2c, loss, out, True, last_rot, last_trans  # no step lowers the loss
            continue
        # Nielsen's damping update: the gain ratio of the actual to the predicted decrease
        # corrects for the approximate Hessian.
        rho = (loss - loss_try) / max(predicted, 1e-30)
        lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        lam, nu = max(lam, 1e-9), 2.0
        counts["accepted"] += 1
        drop = (loss - loss_try) / loss if loss > 0 else 0.0
        grad_prev = grad
        w2c, loss, grad, out = w2c_try, loss_try, grad_try, out_try
        if last:
            pass  # no step follows: no Hessian for one
        elif cfg.hessian == "motion_field" or cfg.focal or (
            cfg.hessian_every and counts["accepted"] % cfg.hessian_every == 0
        ):
            # a new Jacobian too: the robust reweighting below must not go on with the old one;
            # with the focal length, at every step (along the valley where it trades against the
            # camera's distance the Jacobian turns: with one per level it crept, 1.00 -> 1.02 of
            # 1.04 in 12 steps on the demo scene, with one a step it reached 1.04)
            hess, jac = _hessian_and_jacobian(state, cfg, w2c, scale, out_try, mask, intr, blur,
                                              query, robust)
            if cfg.focal:
                grad = torch.cat([grad, _jacobian_gradient(jac, out_try.color, gain, first=6)])
        elif robust is not None and jac is not None and jac.mask.shape == mask.shape:
            # the weights of the new residuals (those of the level's start were of a misaligned
            # render: too little curvature, overshooting steps; docs/LOCALIZATION.md)
            hess = jac.matrix(robust, gain, out_try.color)
        elif cfg.secant:
            hess = _bfgs_update(hess, step, grad - grad_prev)
        last_rot, last_trans = math.degrees(float(step[3:6].norm())), float(step[:3].norm())
        if (last_rot < cfg.stop_rot_deg and last_trans < cfg.stop_trans_rel * scene_depth
                and (not cfg.focal or abs(float(step[6])) < cfg.stop_focal)):
            return w2c, loss, out, True, last_rot, last_trans
    return w2c, loss, out, False, last_rot, last_trans


def refine_photometric(state: LocalizationState, w2c_start: np.ndarray, cfg: RefineConfig,
                       base_scale: float = 1.0, scene_depth: float = 1.0,
                       hypothesis: Optional[int] = None) -> RefineOutcome:
    """Levenberg-Marquardt on the comparing loss from ``w2c_start`` (module docstring).

    ``base_scale`` is the working scale the levels' ``scales`` are relative to.
    """
    w2c = np.asarray(w2c_start, np.float64).copy()
    counts = {"total": 0, "accepted": 0}
    loss0 = loss = None
    last_out, last_scale = None, None
    converged = False
    last_rot = last_trans = None
    for scale_rel, blur, n_it in zip(cfg.scales, cfg.blur, cfg.iterations):
        if n_it == 0:
            continue
        scale = scale_rel * base_scale
        intr = state.intrinsics_at(scale)
        if min(intr.width, intr.height) < 8:
            continue
        query = gaussian_blur(state.query_at(scale).rgb, blur)
        robust = _Cauchy(cfg.robust_scale) if cfg.robust == "cauchy" else None
        loss, grad, out, mask = _evaluate(state, w2c, scale, None, None, blur, query,
                                          exposure_gain=cfg.fitted_gain_range, robust=robust)
        if grad is None:  # the render covers (almost) nothing: no photometric signal here
            continue
        last_scale = scale
        if loss0 is None:
            loss0 = loss
        w2c, loss, last_out, level_converged, last_rot, last_trans = _lm_level(
            state, cfg, w2c, scale, (intr, blur, query, mask, n_it, robust), (loss, grad, out),
            counts, scene_depth, hypothesis)
        converged = level_converged or (
            last_rot is not None
            and last_rot < cfg.still_rot_deg
            and last_trans < cfg.still_trans_rel * scene_depth
        )
    final = None
    if last_out is not None:  # the render at the returned pose (the verification reuses it)
        final = Observation(
            w2c,
            last_scale,
            last_out.color.detach().clamp(0.0, 1.0),
            last_out.depth.detach(),
            last_out.alpha.detach(),
        )
    return RefineOutcome(w2c, counts["total"], counts["accepted"], loss0, loss, converged,
                         last_rot, last_trans, final, state.focal_scale)
