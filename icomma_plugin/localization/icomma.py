"""The paper's method (iComMa, ECCV 2024).

Kept exactly, for reproduction and the benchmark's paper rows: Adam on an se(3) twist, a matching
stage and then a comparing stage.

Pose parametrisation (docs/CONTRACTS.md): a twist ``xi = (rho, phi)`` in se(3), translation part
first, optimised by Adam. The pose is the LEFT perturbation of world-to-camera,

    w2c_t = se3_exp(xi_t) @ w2c_0,

so ``xi`` is an increment in the CAMERA frame (its rotation turns the camera about its own
centre). ``xi`` starts at exactly 0 and accumulates (iComMa keeps its twist relative to the fixed
start pose too, but perturbs c2w on the left, i.e. in the world frame; the optimum is the same).

Loss and schedule (iComMa ``run.py``; defaults in :class:`LocalizerConfig`):

- Stage 1 ("match", :func:`match_step`): ``L = (1 - lambda) L_compare + lambda L_match`` with
  ``lambda = 0.8``, Adam lr 0.05 (constant), betas (0.9, 0.999). ``L_compare`` is the MSE between
  render and query (``losses.compare_loss``); ``L_match`` the mean squared distance of matched
  keypoints in coordinates normalised by the image size. Matches below ``confidence_threshold``
  are dropped; with fewer than ``min_matches`` left, that step compares alone (``L = L_compare``,
  weight 1, as iComMa does) and stage 1 goes on.
- The switch: once ``L_match < switch_threshold`` (1e-3), stage 2 starts at the NEXT iteration.
- Stage 2 ("compare"): ``L = L_compare``, ``lr = lr0 * lr_decay_base ** (t / lr_decay_steps)``
  with ``t = k - k_switch + 1`` (1 at the first stage-2 iteration ``k_switch``), i.e.
  ``0.05 * 0.6 ** (t / 50)``.
- Stop: after ``max_iterations`` (iComMa: always 500), or earlier when the pose has stopped
  moving: over the last ``converge_patience`` iterations it turned by less than
  ``converge_rot_deg`` and its centre moved by less than ``converge_trans_rel`` times the scene
  depth (the median rendered depth at the start, ``geometry.median_depth``); an addition, set
  ``converge_patience = 0`` to disable it.

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

``gradient_mode="image"`` is the default, by measurement on the demo scene (docs/BENCHMARK.md,
"Gradient modes"): it was more robust at 40 degrees, the depth mode's stage-1 iterations are
cheaper.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from ..checks import check_bool, check_choice, check_int, check_real, config_from_dict
from ..losses import compare_loss, match_loss, reprojection_match_loss
from ..pose.convert import invert_rigid, rotation_error_deg
from ..pose.se3 import se3_exp
from .geometry import lift_keypoints, median_depth
from .state import LocalizationState
from .types import MethodOutcome, Stage, TraceRecord
from .verify import VerdictConfig, can_match, verify_pose

logger = logging.getLogger(__name__)

__all__ = ["GRADIENT_MODES", "IcommaOutcome", "LocalizerConfig", "run_icomma"]

GRADIENT_MODES = ("image", "depth")
STAGE_MATCH = Stage.MATCH
STAGE_COMPARE = Stage.COMPARE


@dataclass
class LocalizerConfig:
    """Every constant of the paper's method. Defaults are iComMa's (``run.py`` / ``iComMaParams``).

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
        converge_trans_rel: centre displacement over the window, relative to the scene depth (the
            median rendered depth at the initial pose), below which the pose counts as still.
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
        verdict: thresholds of the verdict on the final pose (a render-and-match there).

    Its results' ``details``: ``switch_iteration``, ``gradient_mode``, ``final_loss``,
    ``scene_depth`` and ``match_counts`` (matches used per stage-1 step: first, last, mean, min,
    max; stage-1 steps; steps that compared alone).
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
    verdict: VerdictConfig = field(default_factory=VerdictConfig)

    #: The method needs a start pose (it follows the loss downhill from there).
    needs_start = True

    def __post_init__(self):
        if isinstance(self.verdict, dict):  # Hydra's instantiate passes nested groups as mappings
            self.verdict = config_from_dict(VerdictConfig, self.verdict, "LocalizerConfig.verdict")
        self.validate()

    @property
    def name(self) -> str:
        """The method's name in results: ``icomma``, or ``compare_only`` without matching."""
        return "icomma" if self.use_matching else "compare_only"

    def validate(self) -> "LocalizerConfig":
        """Raise ValueError naming the field when a value is out of range."""
        def n(field: str) -> str:
            return f"LocalizerConfig.{field}"

        if isinstance(self.betas, list):
            self.betas = tuple(self.betas)
        for name in ("lr", "lr_decay_steps", "image_scale"):
            check_real(getattr(self, name), n(name), 0.0, lo_open=True)
        for name in ("switch_threshold", "converge_rot_deg", "converge_trans_rel", "adam_eps",
                     "confidence_threshold", "depth_min_alpha"):
            check_real(getattr(self, name), n(name), 0.0)
        check_real(self.lambda_match, n("lambda_match"), 0.0, 1.0)
        check_real(self.lr_decay_base, n("lr_decay_base"), 0.0, 1.0, lo_open=True)
        if not (isinstance(self.betas, tuple) and len(self.betas) == 2):
            raise ValueError(
                f"{n('betas')} must be a pair of numbers in [0, 1), got {self.betas!r}"
            )
        for i, b in enumerate(self.betas):
            check_real(b, f"{n('betas')}[{i}]", 0.0, 1.0, hi_open=True)
        for name in ("min_matches", "converge_patience", "min_iterations"):
            check_int(getattr(self, name), n(name), 0)
        check_int(self.max_iterations, n("max_iterations"), 1)
        check_int(self.max_stage1_iterations, n("max_stage1_iterations"), 0, optional=True)
        check_choice(self.gradient_mode, n("gradient_mode"), GRADIENT_MODES)
        if self.sh_degree is not None:
            check_choice(self.sh_degree, n("sh_degree"), (0, 1, 2, 3))
        for name in ("use_matching", "use_query_mask", "antialiasing", "record_trace"):
            check_bool(getattr(self, name), n(name))
        return self

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "LocalizerConfig":
        """Build from a plain mapping (e.g. a Hydra config converted to a container).

        Raises:
            ValueError: unknown keys (the message lists the known ones), or bad values.
        """
        return config_from_dict(cls, d, "LocalizerConfig")

    def to_dict(self) -> Dict[str, Any]:
        """The fields as a JSON-friendly dict (``betas`` as a list)."""
        d = dataclasses.asdict(self)
        d["betas"] = list(self.betas)
        return d

    def at_model_side(self, intrinsics, model_side: Optional[int],
                      scale_pixels: bool = True) -> "LocalizerConfig":
        """This config working at no more than ``model_side`` px, unless it sets ``image_scale``.

        ``scale_pixels`` is the default method's (its thresholds); this one has none to scale.

        A photo sharper than the model adds rendering and matching cost, not accuracy (14 s an
        iteration on a 1080x1920 fox photo against its 270x480 model).
        """
        if model_side is None or self.image_scale != 1.0 \
                or max(intrinsics.width, intrinsics.height) <= model_side:
            return self
        return dataclasses.replace(self, image_scale=intrinsics.scale_to_side(model_side))

    def needs(self, matcher) -> Optional[str]:
        """Why this method cannot run with ``matcher`` (None when it can: any, or none)."""
        return None

    def run(self, state: LocalizationState, init_w2c: Optional[np.ndarray]) -> MethodOutcome:
        """The paper's method from ``init_w2c``, then the verdict at the pose it ends on."""
        if init_w2c is None:
            raise ValueError("the paper's method (optimizer=icomma) needs a start pose; without "
                             "one use the default method (optimizer=robust)")
        out = run_icomma(state, init_w2c, self)
        converged = out.stop_reason == "converged"
        verdict, score = verify_pose(state, out.w2c, self.image_scale, self.verdict, converged)
        details = {"switch_iteration": out.switch_iteration, "gradient_mode": self.gradient_mode,
                   "final_loss": out.final_loss, "scene_depth": out.scene_depth,
                   "match_counts": out.match_counts}
        return MethodOutcome(out.w2c, verdict, score, out.iterations, out.stop_reason, details)

    def stage2_lr(self, t: int) -> float:
        """Stage-2 learning rate at its ``t``-th iteration (t = 1 at the first)."""
        return self.lr * self.lr_decay_base ** (t / self.lr_decay_steps)


@dataclass
class IcommaOutcome:
    """What the paper's method ends with: the pose, how and when it stopped, its match counts."""

    w2c: np.ndarray
    iterations: int
    stop_reason: str
    switch_iteration: Optional[int]
    match_counts: Dict[str, Any]
    final_loss: Optional[float]
    scene_depth: Optional[float]


def match_step(state: LocalizationState, cfg: LocalizerConfig, image, out, query, w2c, intr,
               l_compare) -> Tuple[torch.Tensor, Optional[torch.Tensor], int, int, bool]:
    """One stage-1 loss: (loss, L_match or None, raw matches, matches used, switch now)."""
    image_mode = cfg.gradient_mode == "image"
    W, H = intr.width, intr.height
    # A 3DGS render can exceed 1 (SH colours); the matcher takes [0, 1] (the clamp passes the
    # gradient wherever the render is in range).
    image = image.clamp(0.0, 1.0)
    with state.timed("matcher"):
        m = state.matcher.match(
            image if image_mode else image.detach(), query, differentiable=image_mode
        )
    n_raw = len(m)
    if cfg.confidence_threshold > 0 and n_raw:
        m = m.filter(cfg.confidence_threshold)
    l_match, n_used = None, 0
    if image_mode:
        if len(m) >= cfg.min_matches:
            l_match = match_loss(m.kpts0, m.kpts1, (W, H), (W, H))
            n_used = len(m)
    elif len(m) >= cfg.min_matches:
        c2w_now = invert_rigid(w2c.detach())
        pts, keep = lift_keypoints(
            m.kpts0, out.depth, out.alpha, intr, c2w_now, cfg.depth_min_alpha
        )
        n_used = int(keep.sum())
        if n_used >= cfg.min_matches:
            l_match = reprojection_match_loss(
                pts, m.kpts1[keep].detach().to(torch.float64), w2c, intr
            )
        if l_match is None:
            n_used = 0
    if l_match is None:
        return l_compare, None, n_raw, n_used, False
    lam = cfg.lambda_match
    loss = (1.0 - lam) * l_compare + lam * l_match.to(l_compare.dtype)
    return loss, l_match, n_raw, n_used, float(l_match.detach()) < cfg.switch_threshold


class _PaperLoop:
    """The state of the paper's loop: the twist, Adam, the stage and what it counted."""

    def __init__(self, state: LocalizationState, init_w2c: np.ndarray, cfg: LocalizerConfig):
        self.state, self.cfg = state, cfg
        matcher = state.matcher
        self.use_matching = cfg.use_matching and can_match(matcher)
        if (self.use_matching and cfg.gradient_mode == "image"
                and not getattr(matcher, "supports_image_gradient", False)):
            raise ValueError(
                f"gradient_mode='image' needs a matcher whose keypoints carry image gradients; "
                f"matcher {getattr(matcher, 'name', matcher)!r} does not: use gradient_mode='depth'"
            )
        q = state.query_at(cfg.image_scale)
        self.intr, self.query = q.intrinsics, q.rgb
        self.mask = q.alpha if cfg.use_query_mask else None
        self.w2c0 = torch.as_tensor(np.asarray(init_w2c, np.float64))
        self.xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        self.opt = torch.optim.Adam([self.xi], lr=cfg.lr, betas=cfg.betas, eps=cfg.adam_eps)
        self.stage = STAGE_MATCH if self.use_matching else STAGE_COMPARE
        self.switch_iteration: Optional[int] = None if self.use_matching else 0
        self.stage1_iters = self.n_compare_alone = 0
        self.counts: List[int] = []
        self.history: deque = deque(maxlen=max(cfg.converge_patience, 0) + 1)
        self.history.append(self.w2c0.numpy())
        self.scene_depth: Optional[float] = None
        self.last_loss: Optional[float] = None

    def current_w2c(self) -> torch.Tensor:
        """The pose of the twist: ``se3_exp(xi) @ w2c_0``."""
        return se3_exp(self.xi) @ self.w2c0

    def step(self, it: int) -> None:
        """One iteration: render, loss (stage 1 or 2), backward, Adam step, trace record."""
        cfg, state = self.cfg, self.state
        t_it = time.perf_counter()
        lr = cfg.stage2_lr(it - self.switch_iteration + 1) if self.stage == STAGE_COMPARE \
            else cfg.lr
        for g in self.opt.param_groups:
            g["lr"] = lr
        xi_now = [float(v) for v in self.xi.detach()]
        w2c = self.current_w2c()
        w2c_np = w2c.detach().numpy().copy()
        out = state.render(w2c, cfg.image_scale)
        if self.scene_depth is None:
            self.scene_depth = median_depth(out.depth, out.alpha)
        l_compare = compare_loss(out.color, self.query, self.mask)
        l_match, n_raw, n_used, switch_now = None, 0, 0, False
        loss = l_compare
        if self.stage == STAGE_MATCH:
            self.stage1_iters += 1
            loss, l_match, n_raw, n_used, switch_now = match_step(
                state, cfg, out.color, out, self.query, w2c, self.intr, l_compare)
            self.counts.append(n_used)
            self.n_compare_alone += l_match is None
            if cfg.max_stage1_iterations is not None \
                    and self.stage1_iters >= cfg.max_stage1_iterations:
                switch_now = True
        self.opt.zero_grad(set_to_none=True)
        with state.timed("backward"):
            loss.backward()
        self.opt.step()
        self.last_loss = float(loss.detach())
        with torch.no_grad():
            self.history.append(self.current_w2c().numpy())
        rot_err, trans_err = state.errors(w2c_np)
        state.record(TraceRecord(
            iteration=it, stage=self.stage, seconds=time.perf_counter() - t_it, lr=lr,
            loss=self.last_loss, loss_compare=float(l_compare.detach()),
            loss_match=None if l_match is None else float(l_match.detach()),
            matches=n_raw, matches_used=n_used, rot_err_deg=rot_err, trans_err=trans_err,
            xi=xi_now,  # the twist rendered at this iteration: w2c = se3_exp(xi) @ init_w2c
        ))
        if switch_now and self.stage == STAGE_MATCH:
            self.stage = STAGE_COMPARE
            self.switch_iteration = it + 1
            logger.debug("switch to stage 2 at iteration %d", it + 1)

    def stopped_moving(self, it: int) -> bool:
        """The pose barely moved over the last ``converge_patience`` iterations."""
        cfg, P = self.cfg, self.cfg.converge_patience
        if P <= 0 or len(self.history) != P + 1 or it + 1 < max(cfg.min_iterations, P):
            return False
        a, b = invert_rigid(self.history[0]), invert_rigid(self.history[-1])
        drot = float(rotation_error_deg(a, b))
        dtrans = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
        return drot < cfg.converge_rot_deg and \
            dtrans < cfg.converge_trans_rel * max(self.scene_depth, 1e-12)

    def outcome(self, iterations: int, stop_reason: str) -> IcommaOutcome:
        """What the loop ends with."""
        with torch.no_grad():
            final_w2c = self.current_w2c().numpy()
        c = self.counts
        match_counts = {
            "stage1_iterations": self.stage1_iters,
            "compare_alone_steps": self.n_compare_alone,
            "first": c[0] if c else None,
            "last": c[-1] if c else None,
            "mean": float(np.mean(c)) if c else None,
            "min": int(min(c)) if c else None,
            "max": int(max(c)) if c else None,
        }
        if self.use_matching:
            sw = self.switch_iteration if self.stage == STAGE_COMPARE else None
        else:
            sw = 0
        return IcommaOutcome(final_w2c, iterations, stop_reason, sw, match_counts,
                             self.last_loss, self.scene_depth)


def run_icomma(
    state: LocalizationState, init_w2c: np.ndarray, cfg: LocalizerConfig
) -> IcommaOutcome:
    """The paper's loop from ``init_w2c`` (module docstring); appends to ``state.trace``."""
    loop = _PaperLoop(state, init_w2c, cfg)
    it = 0
    for it in range(cfg.max_iterations):
        loop.step(it)
        if loop.stopped_moving(it):
            return loop.outcome(it + 1, "converged")
    return loop.outcome(it + 1, "max_iterations")
