"""iComMa camera localisation: invert a 3DGS model by gradient descent on the camera pose.

Pose parametrisation (docs/CONTRACTS.md): a twist ``xi = (rho, phi)`` in se(3), translation part
first, optimised by Adam. The pose is the LEFT perturbation of world-to-camera,

    w2c_t = se3_exp(xi_t) @ w2c_0,

so ``xi`` is an increment in the CAMERA frame (its rotation turns the camera about its own
centre). ``xi`` starts at exactly 0 and accumulates (iComMa keeps its twist relative to the fixed
start pose too, but perturbs c2w on the left, i.e. in the world frame; the optimum is the same).

Loss and schedule (iComMa ``run.py``; defaults in :class:`LocalizerConfig`):

- Stage 1 ("match"): ``L = (1 - lambda) L_compare + lambda L_match`` with ``lambda = 0.8``,
  Adam lr 0.05 (constant), betas (0.9, 0.999). ``L_compare`` is the MSE between render and query
  (``losses.compare_loss``); ``L_match`` the mean squared distance of matched keypoints in
  coordinates normalised by the image size. Matches below ``confidence_threshold`` are dropped;
  with fewer than ``min_matches`` left, that step compares alone (``L = L_compare``, weight 1, as
  iComMa does) and stage 1 goes on.
- The switch: once ``L_match < switch_threshold`` (1e-3), stage 2 starts at the NEXT iteration.
- Stage 2 ("compare"): ``L = L_compare``, ``lr = lr0 * lr_decay_base ** (t / lr_decay_steps)``
  with ``t = k - k_switch + 1`` (1 at the first stage-2 iteration ``k_switch``), i.e.
  ``0.05 * 0.6 ** (t / 50)``.
- Stop: after ``max_iterations`` (iComMa: always 500), or earlier when the pose has stopped
  moving: over the last ``converge_patience`` iterations it turned by less than
  ``converge_rot_deg`` and its centre moved by less than ``converge_trans_rel`` times the mean
  rendered depth (an addition; set ``converge_patience = 0`` to disable).

Matching gradient modes (``gradient_mode``):

- ``"image"`` (the paper's): ``matcher.match(render, query, differentiable=True)``; the
  render-side keypoints are refined differentiably from the rendered image, so ``d L_match / d
  pose`` flows through the image and the rasterizer.
- ``"depth"``: the render-side keypoints are lifted to 3D with the rendered expected depth at the
  current pose (detached bilinear sample of ``RasterOutput.depth``; only where alpha > 0.5), and
  their normalised reprojection error in the query is minimised
  (``losses.reprojection_match_loss``): the gradient flows through the projection alone, so any
  matcher works. At the current pose the value equals the image-mode ``L_match`` of the same
  matches, so the switch threshold means the same in both modes.

Default choice: ``gradient_mode="image"`` (the paper's), by measurement. Demo scene
(``icomma_plugin.demo_scene``) seeds 0, 1, 2; initial pose = ground truth rotated by 20 / 30 / 40
degrees about a random axis through the scene centre + 0.1 translation (scene scale 4.4); xfeat
matcher, all other settings the defaults except ``max_iterations=300``; native CPU backend, one
thread, on a shared 2-core machine (seconds are indicative only: the load varied 3-10).
Success = final rotation error < 0.5 deg and translation error < 1% of the scene scale.

200 x 200 (the demo's default size), per case: iterations, stage switch, seconds, final rotation error

    | seed | init deg | image                              | depth                              |
    |------|----------|------------------------------------|------------------------------------|
    | 0 | 20 | 159 it  sw  35   29.1 s  0.0062 deg | 170 it  sw  36    9.3 s  0.0053 deg |
    | 0 | 30 | 156 it  sw  28    9.0 s  0.0059 deg | 157 it  sw  30    6.1 s  0.0028 deg |
    | 0 | 40 | FAIL  43.5 deg (no switch)         | FAIL  43.5 deg (no switch)         |
    | 1 | 20 | 177 it  sw  43   20.1 s  0.0035 deg | 173 it  sw  37   12.5 s  0.0024 deg |
    | 1 | 30 | 171 it  sw  54   21.1 s  0.0047 deg | 183 it  sw  59   14.4 s  0.0049 deg |
    | 1 | 40 | 300 it  sw 203   49.1 s  0.0254 deg | FAIL  36.9 deg (switch@2)          |
    | 2 | 20 | 184 it  sw  46   16.3 s  0.0055 deg | 159 it  sw  36   10.2 s  0.0082 deg |
    | 2 | 30 | 168 it  sw  46   16.6 s  0.0065 deg | 183 it  sw  50   11.8 s  0.0036 deg |
    | 2 | 40 | 190 it  sw  67   18.1 s  0.0059 deg | 206 it  sw  68   17.3 s  0.0025 deg |

Summary (successful runs: medians, except the mean seconds):

    | size | mode  | success | iterations | seconds (median / mean) | stage-1 s/it | final rot deg |
    |------|-------|---------|------------|-------------------------|--------------|---------------|
    | 200  | image | 8/9     | 174        | 19.1 / 22.4             | 0.26         | 0.0059        |
    | 200  | depth | 7/9     | 173        | 11.8 / 11.7             | 0.18         | 0.0036        |
    | 100  | image | 7/9     | 195        | 22.2 / 22.4             | 0.29         | 0.0055        |
    | 100  | depth | 7/9     | 171        | 23.4 / 18.9             | 0.24         | 0.0102        |

Both modes reach the same photometric optimum once they switch (stage 2 is identical). The image
mode was more robust at 40 degrees (depth mode once switched on a handful of spurious matches
whose reprojection error was tiny by chance); the depth mode's stage-1 iterations are cheaper (no
differentiable refinement). Below ~30 degrees, ``gradient_mode=depth`` is a faster choice.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from .camera import Intrinsics
from .gaussians import GaussianModel

logger = logging.getLogger(__name__)

GRADIENT_MODES = ("image", "depth")
STAGE_MATCH = 1
STAGE_COMPARE = 2


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass
class LocalizerConfig:
    """Every constant of the method. Defaults are iComMa's (``run.py`` / ``iComMaParams``).

    Attributes:
        lr: Adam learning rate on the twist (iComMa ``camera_pose_lr`` 0.05). Units: the twist
            is (translation in world units, rotation in radians).
        betas: Adam betas.
        adam_eps: Adam epsilon.
        use_matching: False = compare-only (iComMa ``deprecate_matching``): stage 2 from the start.
        lambda_match: weight of L_match in stage 1, ``L = (1-l) L_compare + l L_match`` (0.8).
        switch_threshold: leave stage 1 once L_match < this (normalised squared px, 1e-3).
        max_stage1_iterations: force the switch after this many stage-1 iterations (None = never,
            as iComMa).
        lr_decay_base, lr_decay_steps: stage-2 lr = lr * base ** (t / steps) (0.6, 50).
        confidence_threshold: matches with a confidence below this are dropped (0.5).
        min_matches: with fewer usable matches the step compares alone (5).
        max_iterations: hard cap on iterations (iComMa: 500, no other stop).
        converge_patience: window (iterations) of the "pose stopped moving" stop; 0 disables it.
        converge_rot_deg: rotation change over the window below which the pose counts as still.
        converge_trans_rel: centre displacement over the window, relative to the mean rendered
            depth at the initial pose, below which the pose counts as still.
        min_iterations: never stop for convergence before this many iterations.
        gradient_mode: "image" (paper: through the matcher's differentiable refinement and the
            rendered image) or "depth" (lift render keypoints with the rendered depth, minimise
            reprojection error).
        depth_min_alpha: depth mode keeps keypoints whose rendered alpha exceeds this.
        use_query_mask: use the query's alpha (when given) as the mask of L_compare.
        image_scale: working scale; query and intrinsics are resized by it before optimising.
        sh_degree: SH degree used for rendering (None = the model's).
        antialiasing: rasterizer antialiasing flag (upstream 3DGS ``--antialiasing``).
        record_trace: keep the per-iteration trace in the result.
    """

    lr: float = 0.05
    betas: Tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8
    use_matching: bool = True
    lambda_match: float = 0.8
    switch_threshold: float = 1e-3
    max_stage1_iterations: Optional[int] = None
    lr_decay_base: float = 0.6
    lr_decay_steps: float = 50.0
    confidence_threshold: float = 0.5
    min_matches: int = 5
    max_iterations: int = 500
    converge_patience: int = 20
    converge_rot_deg: float = 0.02
    converge_trans_rel: float = 2e-4
    min_iterations: int = 0
    gradient_mode: str = "image"
    depth_min_alpha: float = 0.5
    use_query_mask: bool = True
    image_scale: float = 1.0
    sh_degree: Optional[int] = None
    antialiasing: bool = False
    record_trace: bool = True

    def __post_init__(self):
        self.validate()

    def validate(self) -> "LocalizerConfig":
        """Raise ValueError naming the field when a value is out of range."""
        def bad(name, want):
            raise ValueError(f"LocalizerConfig.{name} must be {want}, got {getattr(self, name)!r}")

        if isinstance(self.betas, list):
            self.betas = tuple(self.betas)
        for name in ("lr", "lr_decay_steps", "image_scale"):
            v = getattr(self, name)
            if not (_is_num(v) and v > 0):
                bad(name, "a positive finite number")
        for name in ("switch_threshold", "converge_rot_deg", "converge_trans_rel", "adam_eps",
                     "confidence_threshold", "depth_min_alpha"):
            v = getattr(self, name)
            if not (_is_num(v) and v >= 0):
                bad(name, "a non-negative finite number")
        if not (_is_num(self.lambda_match) and 0.0 <= self.lambda_match <= 1.0):
            bad("lambda_match", "a number in [0, 1]")
        if not (_is_num(self.lr_decay_base) and 0.0 < self.lr_decay_base <= 1.0):
            bad("lr_decay_base", "a number in (0, 1]")
        if not (isinstance(self.betas, tuple) and len(self.betas) == 2
                and all(_is_num(b) and 0.0 <= b < 1.0 for b in self.betas)):
            bad("betas", "a pair of numbers in [0, 1)")
        for name in ("min_matches", "max_iterations", "converge_patience", "min_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                bad(name, "a non-negative int")
        if self.max_iterations < 1:
            bad("max_iterations", "a positive int")
        if self.max_stage1_iterations is not None and not (
            isinstance(self.max_stage1_iterations, int) and self.max_stage1_iterations >= 0
        ):
            bad("max_stage1_iterations", "a non-negative int or None")
        if self.gradient_mode not in GRADIENT_MODES:
            bad("gradient_mode", f"one of {GRADIENT_MODES}")
        if self.sh_degree is not None and self.sh_degree not in (0, 1, 2, 3):
            bad("sh_degree", "0..3 or None")
        for name in ("use_matching", "use_query_mask", "antialiasing", "record_trace"):
            if not isinstance(getattr(self, name), bool):
                bad(name, "a bool")
        return self

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "LocalizerConfig":
        """Build from a plain mapping (e.g. a Hydra config converted to a container); unknown
        keys raise ValueError listing the known ones."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown LocalizerConfig keys {unknown}; known keys: {sorted(names)}")
        kw = dict(d)
        if "betas" in kw and kw["betas"] is not None:
            kw["betas"] = tuple(float(b) for b in kw["betas"])
        for name in ("lr", "lr_decay_steps", "image_scale", "switch_threshold", "lambda_match"):
            if isinstance(kw.get(name), int) and not isinstance(kw.get(name), bool):
                kw[name] = float(kw[name])
        return cls(**kw)

    def to_dict(self) -> Dict[str, Any]:
        d = dataclasses.asdict(self)
        d["betas"] = list(self.betas)
        return d

    def stage2_lr(self, t: int) -> float:
        """Stage-2 learning rate at its ``t``-th iteration (t = 1 at the first)."""
        return self.lr * self.lr_decay_base ** (t / self.lr_decay_steps)


@dataclass
class LocalizationResult:
    """Outcome of :func:`localize`. Poses are float64 numpy, OpenCV axes."""

    w2c: np.ndarray
    c2w: np.ndarray
    init_w2c: np.ndarray
    iterations: int
    stop_reason: str  # "converged" | "max_iterations"
    switch_iteration: Optional[int]  # first stage-2 iteration (None: never switched)
    match_counts: Dict[str, Any]
    seconds: float
    gradient_mode: str
    matcher: Optional[str]
    initial_rotation_error_deg: Optional[float] = None
    initial_translation_error: Optional[float] = None
    final_rotation_error_deg: Optional[float] = None
    final_translation_error: Optional[float] = None
    final_loss: Optional[float] = None
    scene_depth: Optional[float] = None
    trace: List[Dict[str, Any]] = field(default_factory=list)
    config: Dict[str, Any] = field(default_factory=dict)

    def to_json(self, include_trace: bool = True) -> Dict[str, Any]:
        """A JSON-serialisable dict (numbers, lists, None)."""
        d = {
            "w2c": self.w2c.tolist(),
            "c2w": self.c2w.tolist(),
            "init_w2c": self.init_w2c.tolist(),
            "iterations": self.iterations,
            "stop_reason": self.stop_reason,
            "switch_iteration": self.switch_iteration,
            "match_counts": self.match_counts,
            "seconds": self.seconds,
            "gradient_mode": self.gradient_mode,
            "matcher": self.matcher,
            "initial_rotation_error_deg": self.initial_rotation_error_deg,
            "initial_translation_error": self.initial_translation_error,
            "final_rotation_error_deg": self.final_rotation_error_deg,
            "final_translation_error": self.final_translation_error,
            "final_loss": self.final_loss,
            "scene_depth": self.scene_depth,
            "config": self.config,
        }
        if include_trace:
            d["trace"] = self.trace
        return json.loads(json.dumps(d, default=_json_default))


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------


def _as_pose(T, name: str) -> torch.Tensor:
    if isinstance(T, np.ndarray):
        T = torch.from_numpy(np.asarray(T, dtype=np.float64))
    if not isinstance(T, torch.Tensor):
        raise ValueError(f"{name} must be a 4x4 numpy array or torch tensor, got {type(T).__name__}")
    if tuple(T.shape) != (4, 4):
        raise ValueError(f"{name} must have shape [4, 4], got {list(T.shape)}")
    T = T.detach().to(torch.float64).cpu()
    if not bool(torch.isfinite(T).all()):
        raise ValueError(f"{name} contains NaN or infinite values")
    R = T[:3, :3]
    if float((R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max()) > 1e-3 or float(torch.det(R)) < 0:
        raise ValueError(f"{name} must be a rigid transform (orthonormal rotation, det +1)")
    return T


def _invert(T: torch.Tensor) -> torch.Tensor:
    R, t = T[..., :3, :3], T[..., :3, 3:4]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -(Rt @ t)], -1)
    return torch.cat([top, T[..., 3:4, :]], -2)


def _rot_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    tr = float(np.clip(np.trace(Ra @ Rb.T), -1.0, 3.0))
    return math.degrees(math.acos(0.5 * (tr - 1.0)))


def _resize(img: torch.Tensor, h: int, w: int) -> torch.Tensor:
    if tuple(img.shape[-2:]) == (h, w):
        return img
    return F.interpolate(img[None], size=(h, w), mode="bilinear", align_corners=False, antialias=True)[0]


def sample_bilinear(img: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Sample ``img [C, H, W]`` at pixel coordinates ``xy [N, 2]`` (pixel centres at integers,
    3DGS convention) bilinearly; points outside get 0. Returns ``[N, C]``."""
    C, H, W = img.shape
    gx = 2.0 * xy[:, 0] / max(W - 1, 1) - 1.0
    gy = 2.0 * xy[:, 1] / max(H - 1, 1) - 1.0
    grid = torch.stack([gx, gy], -1).to(img.dtype).view(1, -1, 1, 2)
    out = F.grid_sample(img[None], grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return out[0, :, :, 0].T


def lift_keypoints(
    kpts: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, intrinsics: Intrinsics,
    c2w: torch.Tensor, min_alpha: float = 0.5,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Back-project render keypoints ``[N, 2]`` with the rendered expected depth ``[1, H, W]``.

    Returns ``(points_world [M, 3] float64, keep [N] bool)``; a keypoint is kept when the
    bilinearly sampled alpha exceeds ``min_alpha`` and the depth is positive. Everything is
    detached (the points are constants of the depth-mode loss).
    """
    with torch.no_grad():
        k = kpts.detach().to(torch.float64)
        dep = depth.detach().to(torch.float64)
        alp = alpha.detach().to(torch.float64)
        # Coverage-weighted bilinear depth: a plain bilinear sample next to an alpha edge would
        # mix in the zero depth of empty pixels, so interpolate depth * alpha and divide.
        a = sample_bilinear(alp, k)[:, 0]
        d = sample_bilinear(dep * alp, k)[:, 0] / a.clamp_min(1e-12)
        W, H = intrinsics.width, intrinsics.height
        inside = (k[:, 0] >= 0) & (k[:, 0] <= W - 1) & (k[:, 1] >= 0) & (k[:, 1] <= H - 1)
        keep = inside & (a > min_alpha) & (d > 0)
        x = (k[keep, 0] - intrinsics.cx_px) / intrinsics.fx
        y = (k[keep, 1] - intrinsics.cy_px) / intrinsics.fy
        z = d[keep]
        pc = torch.stack([x * z, y * z, z, torch.ones_like(z)], -1)
        pw = (c2w.detach().to(torch.float64).to(pc.device) @ pc.T).T[:, :3]
    return pw, keep


# ----------------------------------------------------------------------------------------------
# the loop
# ----------------------------------------------------------------------------------------------


def localize(
    model: GaussianModel,
    query_rgb: torch.Tensor,
    intrinsics: Intrinsics,
    init_w2c,
    matcher=None,
    config: Optional[LocalizerConfig] = None,
    gt_w2c=None,
    query_alpha: Optional[torch.Tensor] = None,
    backend: str = "auto",
    bg: Optional[torch.Tensor] = None,
    progress: Optional[Callable[[Dict[str, Any]], Any]] = None,
) -> LocalizationResult:
    """Estimate the camera pose of ``query_rgb`` in ``model``, starting from ``init_w2c``.

    Args:
        model: the 3DGS scene (its device and dtype are used).
        query_rgb: ``[3, H, W]`` float in [0, 1].
        intrinsics: pinhole intrinsics of the query at ``W x H``.
        init_w2c: ``[4, 4]`` initial world-to-camera (OpenCV axes), numpy or torch.
        matcher: an ``icomma_plugin.matchers.Matcher``; None (or the ``none`` matcher) means
            compare-only.
        config: :class:`LocalizerConfig` (defaults: the paper's).
        gt_w2c: optional ground-truth world-to-camera, used ONLY for error reporting.
        query_alpha: optional ``[1, H, W]`` foreground mask of the query (L_compare mask).
        backend: renderer backend ("auto" | "cpu" | "cuda" | "reference").
        bg: background colour ``[3]`` (default black).
        progress: called after every iteration with that iteration's trace record (a dict).

    Pose update: ``w2c_t = se3_exp(xi_t) @ w2c_0`` (left perturbation of world-to-camera,
    ``xi = (rho, phi)``), Adam on ``xi``.
    """
    from .losses import compare_loss, match_loss, reprojection_match_loss
    from .pose.se3 import se3_exp
    from .render import render

    cfg = config if config is not None else LocalizerConfig()
    if not isinstance(cfg, LocalizerConfig):
        raise ValueError(f"config must be a LocalizerConfig, got {type(cfg).__name__}")
    cfg.validate()
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise ValueError(f"intrinsics must be an Intrinsics, got {type(intrinsics).__name__}")
    if not isinstance(query_rgb, torch.Tensor) or query_rgb.ndim != 3 or query_rgb.shape[0] != 3:
        raise ValueError(
            f"query_rgb must be a [3, H, W] tensor, got {getattr(query_rgb, 'shape', type(query_rgb).__name__)}"
        )
    H0, W0 = int(query_rgb.shape[1]), int(query_rgb.shape[2])
    if (intrinsics.width, intrinsics.height) != (W0, H0):
        raise ValueError(
            f"intrinsics size {intrinsics.width}x{intrinsics.height} (WxH) does not match query_rgb "
            f"{W0}x{H0}; scale the intrinsics with Intrinsics.scaled"
        )
    if query_alpha is not None and (
        not isinstance(query_alpha, torch.Tensor) or tuple(query_alpha.shape) != (1, H0, W0)
    ):
        raise ValueError(
            f"query_alpha must be a [1, {H0}, {W0}] tensor or None, got "
            f"{getattr(query_alpha, 'shape', type(query_alpha).__name__)}"
        )
    device, dtype = model.device, model.dtype
    model = model.detach()
    if cfg.sh_degree is None and model.sh_degree > 0 and not bool(model.sh_rest.any()):
        # Higher SH bands all zero: degree 0 renders the same image (and gradients), faster.
        model = model.with_sh_degree(0)
    w2c0 = _as_pose(init_w2c, "init_w2c")
    gt = _as_pose(gt_w2c, "gt_w2c") if gt_w2c is not None else None
    gt_c2w_np = _invert(gt).numpy() if gt is not None else None

    use_matching = cfg.use_matching and matcher is not None and getattr(matcher, "name", None) != "none"
    mode = cfg.gradient_mode
    if use_matching and mode == "image" and not getattr(matcher, "supports_image_gradient", False):
        raise ValueError(
            f"gradient_mode='image' needs a matcher whose keypoints carry image gradients; "
            f"matcher {getattr(matcher, 'name', matcher)!r} does not: use gradient_mode='depth'"
        )

    # Working resolution.
    intr = intrinsics.scaled(cfg.image_scale) if cfg.image_scale != 1.0 else intrinsics
    W, H = intr.width, intr.height
    query = _resize(query_rgb.detach().to(device=device, dtype=dtype), H, W).clamp(0.0, 1.0)
    mask = None
    if query_alpha is not None and cfg.use_query_mask:
        mask = _resize(query_alpha.detach().to(device=device, dtype=dtype), H, W).clamp(0.0, 1.0)
    if bg is None:
        bg = torch.zeros(3, device=device, dtype=dtype)
    bg = torch.as_tensor(bg, device=device, dtype=dtype).reshape(3)

    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([xi], lr=cfg.lr, betas=cfg.betas, eps=cfg.adam_eps)

    def current_w2c() -> torch.Tensor:
        return se3_exp(xi) @ w2c0

    def errors(w2c_np: np.ndarray) -> Tuple[Optional[float], Optional[float]]:
        if gt_c2w_np is None:
            return None, None
        c2w_np = np.linalg.inv(w2c_np)
        return (_rot_angle_deg(c2w_np[:3, :3], gt_c2w_np[:3, :3]),
                float(np.linalg.norm(c2w_np[:3, 3] - gt_c2w_np[:3, 3])))

    init_rot, init_trans = errors(w2c0.numpy())
    stage = STAGE_MATCH if use_matching else STAGE_COMPARE
    switch_iteration: Optional[int] = None if use_matching else 0
    stage1_iters = 0
    trace: List[Dict[str, Any]] = []
    counts: List[int] = []
    n_compare_alone = 0
    history: deque = deque(maxlen=max(cfg.converge_patience, 0) + 1)
    history.append(w2c0.numpy())
    scene_depth: Optional[float] = None
    stop_reason = "max_iterations"
    last_loss = None
    t_start = time.perf_counter()
    it = 0
    for it in range(cfg.max_iterations):
        t_it = time.perf_counter()
        if stage == STAGE_COMPARE:
            lr = cfg.stage2_lr(it - switch_iteration + 1)
        else:
            lr = cfg.lr
        for g in opt.param_groups:
            g["lr"] = lr

        xi_now = [float(v) for v in xi.detach()]
        w2c = current_w2c()
        w2c_np = w2c.detach().numpy().copy()
        out = render(model, intr, w2c.to(device=device, dtype=dtype), bg, backend=backend,
                     sh_degree=cfg.sh_degree, antialiasing=cfg.antialiasing)
        image = out.color
        if scene_depth is None:
            with torch.no_grad():
                sel = out.alpha > 0.5
                scene_depth = float(out.depth[sel].mean()) if bool(sel.any()) else float(
                    torch.linalg.norm(model.means.detach().mean(0).double().cpu() - _invert(w2c0)[:3, 3]))
        l_compare = compare_loss(image, query, mask)
        l_match = None
        n_raw = n_used = 0
        switch_now = False
        if stage == STAGE_MATCH:
            stage1_iters += 1
            image_mode = mode == "image"
            m = matcher.match(image if image_mode else image.detach(), query, differentiable=image_mode)
            n_raw = len(m)
            if cfg.confidence_threshold > 0 and n_raw:
                m = m.filter(cfg.confidence_threshold)
            if mode == "image":
                if len(m) >= cfg.min_matches:
                    l_match = match_loss(m.kpts0, m.kpts1, (W, H), (W, H))
                    n_used = len(m)
            else:
                if len(m) >= cfg.min_matches:
                    pts, keep = lift_keypoints(m.kpts0, out.depth, out.alpha, intr,
                                               _invert(w2c.detach()), cfg.depth_min_alpha)
                    n_used = int(keep.sum())
                    if n_used >= cfg.min_matches:
                        l_match = reprojection_match_loss(
                            pts, m.kpts1[keep].detach().to(torch.float64), w2c, intr)
                    if l_match is None:
                        n_used = 0
            counts.append(n_used)
            if l_match is None:
                loss = l_compare
                n_compare_alone += 1
            else:
                lam = cfg.lambda_match
                loss = (1.0 - lam) * l_compare + lam * l_match.to(l_compare.dtype)
                if float(l_match.detach()) < cfg.switch_threshold:
                    switch_now = True
            if cfg.max_stage1_iterations is not None and stage1_iters >= cfg.max_stage1_iterations:
                switch_now = True
        else:
            loss = l_compare

        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        last_loss = float(loss.detach())

        with torch.no_grad():
            new_w2c = current_w2c().numpy()
        history.append(new_w2c)
        rot_err, trans_err = errors(w2c_np)
        record = {
            "iteration": it,
            "stage": stage,
            "lr": lr,
            "loss": last_loss,
            "loss_compare": float(l_compare.detach()),
            "loss_match": None if l_match is None else float(l_match.detach()),
            "matches": n_raw,
            "matches_used": n_used,
            "rot_err_deg": rot_err,
            "trans_err": trans_err,
            "seconds": time.perf_counter() - t_it,
            "xi": xi_now,  # the twist rendered at this iteration: w2c = se3_exp(xi) @ init_w2c
        }
        if cfg.record_trace:
            trace.append(record)
        if progress is not None:
            progress(record)

        if switch_now and stage == STAGE_MATCH:
            stage = STAGE_COMPARE
            switch_iteration = it + 1
            logger.debug("switch to stage 2 at iteration %d (L_match=%s)", it + 1, record["loss_match"])

        # Convergence: the pose barely moved over the last `converge_patience` iterations.
        P = cfg.converge_patience
        if P > 0 and len(history) == P + 1 and it + 1 >= max(cfg.min_iterations, P):
            a, b = np.linalg.inv(history[0]), np.linalg.inv(history[-1])
            drot = _rot_angle_deg(a[:3, :3], b[:3, :3])
            dtrans = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
            if drot < cfg.converge_rot_deg and dtrans < cfg.converge_trans_rel * max(scene_depth, 1e-12):
                stop_reason = "converged"
                break

    iterations = it + 1
    with torch.no_grad():
        final_w2c = current_w2c().numpy()
    final_rot, final_trans = errors(final_w2c)
    seconds = time.perf_counter() - t_start
    match_counts = {
        "stage1_iterations": stage1_iters,
        "compare_alone_steps": n_compare_alone,
        "first": counts[0] if counts else None,
        "last": counts[-1] if counts else None,
        "mean": float(np.mean(counts)) if counts else None,
        "min": int(min(counts)) if counts else None,
        "max": int(max(counts)) if counts else None,
    }
    return LocalizationResult(
        w2c=final_w2c,
        c2w=np.linalg.inv(final_w2c),
        init_w2c=w2c0.numpy(),
        iterations=iterations,
        stop_reason=stop_reason,
        switch_iteration=switch_iteration if (use_matching and stage == STAGE_COMPARE) else (
            None if use_matching else 0),
        match_counts=match_counts,
        seconds=seconds,
        gradient_mode=mode,
        matcher=getattr(matcher, "name", None) if use_matching else None,
        initial_rotation_error_deg=init_rot,
        initial_translation_error=init_trans,
        final_rotation_error_deg=final_rot,
        final_translation_error=final_trans,
        final_loss=last_loss,
        scene_depth=scene_depth,
        trace=trace,
        config=cfg.to_dict(),
    )
