"""The 3DGS optimisation loop (upstream `train.py::training`), on in-memory posed images.

One random training view per step (drawn without replacement from a reshuffled stack, as
upstream), loss (1 - l) L1 + l (1 - SSIM), Adam with upstream per-parameter learning rates, SH
degree raised progressively, densification / pruning / opacity reset on a schedule
(`FitConfig`). The rasterizer is `gaussian_renderer_pose` (backend "auto": the native CPU kernel
when built). No printing: progress goes to an optional callback and to `logging`.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch

from gaussian_renderer_pose import (
    GaussianRasterizationSettings,
    camera_matrices,
    rasterize_gaussians,
)

from ..camera import Intrinsics
from ..gaussians import GaussianModel
from ..heap import retain_freed_memory
from .config import UPSTREAM_ITERATIONS, FitConfig
from .exposure import ExposureState
from .losses import photometric_loss_and_grad, psnr
from .state import GaussianTrainState, expon_lr

log = logging.getLogger(__name__)

ProgressFn = Callable[[int, int, Dict[str, float]], None]
SaveFn = Callable[[int, GaussianModel], None]

# Re-planning the run's tail (FitConfig.time_budget): the step time is measured over the last
# REPLAN_WINDOW steps before densification ends (its Gaussians are then nearly all there), and
# the tail after it may shrink to REPLAN_TAIL[0] or grow to REPLAN_TAIL[1] times its plan (up to
# upstream's 30000 steps): a machine that has grown slow still ends the learning rates' decay.
REPLAN_WINDOW = 300
REPLAN_TAIL = (0.25, 4.0)
# ... and looked at once more REPLAN_CHECK_SHARE of the way through the new tail: the step time
# of its last REPLAN_WINDOW steps then sets the rest, within REPLAN_CHECK_RANGE times the rest as
# planned (fox's tail ran at 64.5 ms a step where 61.2 had been measured: 22 s over 10 minutes).
REPLAN_CHECK_SHARE = 0.75
REPLAN_CHECK_RANGE = (0.5, 2.0)


def _steps_that_fit(seconds_left: float, step_seconds: float, planned: int,
                    bounds: Tuple[float, float], cap: int) -> int:
    """Steps that take ``seconds_left`` at ``step_seconds``.

    Within ``bounds`` times ``planned`` (the steps as planned), and at most ``cap``.
    """
    fits = int(max(seconds_left, 0.0) / step_seconds) if step_seconds > 0 else planned
    return min(max(fits, math.ceil(bounds[0] * planned)), int(bounds[1] * planned), cap)


@dataclass
class FitView:
    """A posed image in memory: rgb [3, H, W] in [0, 1] (composited over the background).

    valid: [1, H, W] in {0, 1}, 1 where the pixel is real image content (`ViewImage.valid`);
    None: every pixel. Losses and PSNR count only the valid pixels.
    """

    name: str
    image: torch.Tensor
    intrinsics: Intrinsics
    w2c: torch.Tensor  # [4, 4]
    alpha: Optional[torch.Tensor] = None  # [1, H, W]; lets random backgrounds re-composite
    valid: Optional[torch.Tensor] = None  # [1, H, W]
    _mats: object = field(default=None, repr=False)

    def __post_init__(self):
        i = self.intrinsics
        hw = (i.height, i.width)
        if self.image.ndim != 3 or self.image.shape[0] != 3 or tuple(self.image.shape[1:]) != hw:
            raise ValueError(
                f"FitView {self.name!r}: image must be [3, {i.height}, {i.width}] to match its "
                f"intrinsics, got {list(self.image.shape)}"
            )
        if tuple(self.w2c.shape) != (4, 4):
            raise ValueError(
                f"FitView {self.name!r}: w2c must be [4, 4], got {list(self.w2c.shape)}"
            )
        for what in ("alpha", "valid"):
            t = getattr(self, what)
            if t is not None and tuple(t.shape) != (1,) + hw:
                raise ValueError(
                    f"FitView {self.name!r}: {what} must be [1, {i.height}, {i.width}] "
                    f"or None, got {list(t.shape)}"
                )
        if self.valid is not None and not bool(self.valid.any()):
            raise ValueError(f"FitView {self.name!r}: valid mask has no valid pixel")

    def downsampled(self, factor: int) -> "FitView":
        """This view at 1/`factor` of its size (area-averaged image, scaled intrinsics).

        A pixel of the valid mask stays valid only if all of its source pixels were.
        """
        if factor == 1:
            return self
        intr = self.intrinsics.scaled(1.0 / factor)
        size = (intr.height, intr.width)

        def area(t):
            if t is None:
                return None
            return torch.nn.functional.interpolate(t[None], size=size, mode="area")[0]

        valid = area(self.valid)
        if valid is not None:
            valid = (valid >= 0.999).to(self.valid.dtype)
            if not bool(valid.any()):
                valid = None
        return FitView(self.name, area(self.image).contiguous(), intr, self.w2c,
                       alpha=area(self.alpha), valid=valid)

    def matrices(self, dtype: torch.dtype, device: torch.device):
        """Rasterizer matrices (cached; the pose is fixed during fitting)."""
        if (
            self._mats is None
            or self._mats.viewmatrix.dtype != dtype
            or self._mats.viewmatrix.device != device
        ):
            i = self.intrinsics
            self._mats = camera_matrices(
                self.w2c.to(dtype=dtype, device=device), i.fx, i.fy, i.width, i.height, i.cx, i.cy
            )
        return self._mats


@dataclass
class FitResult:
    """The fitted model, its size, timings, test PSNR and per-step history."""

    model: GaussianModel
    iterations: int
    num_gaussians: int
    seconds_train: float
    test_psnr: Optional[float]
    test_views: int
    history: List[Dict[str, float]]
    timings: Dict[str, float]
    seconds_cpu: Optional[float] = None  # process CPU time of the loop (incl. evaluations)
    removed_non_finite: int = 0  # Gaussians removed because a parameter went NaN / infinite
    replan: Optional[Dict[str, float]] = None  # the tail's new plan (`Trainer.replan`)


def render_state(state: GaussianTrainState, view: FitView, bg: torch.Tensor, backend: str = "auto",
                 means2D: Optional[torch.Tensor] = None, sh_degree: Optional[int] = None,
                 validate: bool = True):
    """Render the trainable Gaussians into `view`.

    Differentiable; ``means2D`` gets the screen-space gradients. ``validate``: the rasterizer's
    NaN/Inf scans of every per-Gaussian tensor (a host sync each).
    """
    means = state.get("means")
    m = view.matrices(means.dtype, means.device)
    i = view.intrinsics
    settings = GaussianRasterizationSettings(
        image_height=i.height, image_width=i.width, tanfovx=m.tanfovx, tanfovy=m.tanfovy, bg=bg,
        scale_modifier=1.0, viewmatrix=m.viewmatrix, projmatrix=m.projmatrix,
        sh_degree=state.active_sh_degree if sh_degree is None else sh_degree, campos=m.campos,
        prefiltered=False, debug=False, antialiasing=False, backend=backend,
    )
    return rasterize_gaussians(
        means, state.opacities(), settings, means2D=means2D, shs=state.get("sh_dc"),
        shs_rest=state.get("sh_rest"), scales=state.scales(), rotations=state.rotations(),
        validate=validate,
    )


#: Steps between the rasterizer's NaN/Inf scans of the Gaussians (the first step is scanned).
_SCAN_EVERY = 100
#: At those scans a Gaussian with a non-finite parameter (one bad gradient and its Adam moments
#: stay NaN) is removed and the fit goes on, up to this share of the Gaussians at once; more is
#: a fit that diverged. (Bird at 30000 steps lost one Gaussian's mean at step ~23,700, and the
#: whole 15-minute fit with it.)
MAX_NON_FINITE_SHARE = 0.01


class Trainer:
    """Fits `init` to `train` views; `run()` does the whole schedule, `train_step()` one step."""

    def __init__(
        self,
        init: GaussianModel,
        train: Sequence[FitView],
        scene_extent: float,
        config: FitConfig,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        test: Sequence[FitView] = (),
        progress: Optional[ProgressFn] = None,
        on_save: Optional[SaveFn] = None,
        progress_every: int = 10,
        scene_centre: Optional[Sequence[float]] = None,
        exposure: bool = False,
    ):
        """Set up the optimisation.

        Args:
            init: the initial Gaussians.
            train: the training views.
            scene_extent: the scene's scale (upstream: 1.1 x the cameras' radius).
            config: every constant of the fit.
            background: the RGB the renders are composited over.
            test: views to measure test PSNR on.
            progress: called every `progress_every` iterations with (iteration, total, info).
            on_save: called with (iteration, model) at the save iterations and at the end.
            progress_every: see `progress`.
            scene_centre: the cameras' centre; with `config.distance_scaled_thresholds`, the
                size thresholds of densification grow with the distance from it.
            exposure: optimise an affine colour transform per training view (`ExposureState`).
        """
        if not train:
            raise ValueError("train must contain at least one view, got none")
        if not (
            isinstance(scene_extent, (int, float))
            and math.isfinite(scene_extent)
            and scene_extent > 0
        ):
            raise ValueError(f"scene_extent must be a positive finite number, got {scene_extent!r}")
        if init.num_gaussians < 1:
            raise ValueError("init must contain at least one Gaussian")
        self.config = config
        self.train_views = list(train)
        self.test_views = list(test)
        self.extent = float(scene_extent)
        self.progress = progress
        self.on_save = on_save
        self.progress_every = max(1, int(progress_every))
        init = init.with_sh_degree(config.sh_degree) if init.sh_degree != config.sh_degree else init
        self.state = GaussianTrainState(
            init, self.extent, position_lr=config.position_lr_init, feature_lr=config.feature_lr,
            opacity_lr=config.opacity_lr, scaling_lr=config.scaling_lr,
            rotation_lr=config.rotation_lr, eps=config.adam_eps,
            percent_dense=config.percent_dense, seed=config.seed,
        )
        self.device = init.device
        self.dtype = init.dtype
        self.background = torch.as_tensor(background, dtype=self.dtype, device=self.device).reshape(
            3
        )
        self.white_background = bool(self.background.min() >= 1.0)
        self.rng = torch.Generator().manual_seed(config.seed)
        # the random backgrounds' own stream: a fit is repeatable from config.seed alone (the
        # global RNG is seeded at random in each process) and the view order does not move
        self.background_rng = torch.Generator().manual_seed(config.seed + 1)
        self._stack: List[int] = []
        self.iteration = 0
        self.removed_non_finite = 0  # Gaussians removed for non-finite parameters
        self.history: List[Dict[str, float]] = []
        self.timings = dict.fromkeys(
            ("render", "loss", "backward", "stats", "densify", "adam", "exposure"), 0.0)
        self.max_steps = config.position_lr_max_steps or config.iterations
        # the run's length: config.iterations until a time budget's re-plan (`_replan_tail`)
        self.total_iterations = config.iterations
        self.replan: Optional[Dict[str, float]] = None
        pixels = sum(v.intrinsics.width * v.intrinsics.height for v in self.train_views)
        self.max_gaussians = min(config.max_gaussians, max(1, int(
            config.max_gaussians_per_pixel * pixels / len(self.train_views))))
        self._setup_capture_parts(scene_centre, exposure)
        # every step frees and allocates the same image-sized tensors: keep them in the heap
        # (fox at 540x960: 177 -> 135 ms a step; icomma_plugin.heap)
        retain_freed_memory()

    def _setup_capture_parts(self, scene_centre: Optional[Sequence[float]], exposure: bool):
        """The centre of the distance-scaled thresholds, exposures, the coarse-level cache."""
        c = self.config
        self.centre = None
        if scene_centre is not None and c.distance_scaled_thresholds:
            self.centre = torch.as_tensor(scene_centre, dtype=self.dtype, device=self.device)
        self.exposure = ExposureState(len(self.train_views), c.exposure_lr_init,
                                      c.exposure_lr_final, self.max_steps, self.dtype,
                                      self.device, sparse=c.exposure_sparse) if exposure else None
        self._levels: Dict[int, List[FitView]] = {1: self.train_views}

    # ------------------------------------------------------------------ helpers
    def _next_index(self) -> int:
        if not self._stack:
            self._stack = torch.randperm(len(self.train_views), generator=self.rng).tolist()
        return self._stack.pop()

    def downsample_factor(self, iteration: int) -> int:
        """The image size divisor at `iteration` (`FitConfig.coarse_to_fine`)."""
        ends = self.config.coarse_to_fine
        t = iteration / self.config.iterations
        level = next((k for k, end in enumerate(ends) if t <= end), len(ends))
        factor = 2 ** (len(ends) - level)
        small = min(min(v.intrinsics.width, v.intrinsics.height) for v in self.train_views)
        while factor > 1 and small // factor < 32:
            factor //= 2
        return factor

    def _view_at(self, index: int, factor: int) -> FitView:
        if factor not in self._levels:
            self._levels[factor] = [v.downsampled(factor) for v in self.train_views]
        return self._levels[factor][index]

    def schedule_step(self, iteration: int) -> float:
        """Where `iteration` falls on the planned run's learning-rate schedules.

        `iteration` itself, except in a re-planned tail (`_replan_tail`): there the steps from
        the re-plan to `total_iterations` are stretched (or squeezed) onto the planned ones, so
        the learning rates go on from where they were and end where the plan ended them.
        """
        r = self.replan
        if r is None or iteration <= r["at"]:
            return iteration
        at, pos, end = r["at"], float(r["at"]), r["iterations"]
        check = r.get("check")
        if check is not None and iteration > check["at"]:  # (the rest planned once more)
            at, pos, end = check["at"], check["schedule_at"], check["iterations"]
        return pos + (iteration - at) * (r["planned"] - pos) / (end - at)

    def _update_lr(self, iteration: int) -> None:
        c = self.config
        self.state.set_lr(
            "means",
            expon_lr(self.schedule_step(iteration), c.position_lr_init * self.extent,
                     c.position_lr_final * self.extent, self.max_steps, 0,
                     c.position_lr_delay_mult),
        )

    def _loss_and_grad(self, index: int, color: torch.Tensor, gt: torch.Tensor,
                       valid: Optional[torch.Tensor]):
        """(loss, d loss / d render, the render as compared) of training view `index`.

        With exposure, the render goes through the view's colour transform first.
        """
        c = self.config
        if self.exposure is None:
            loss, grad = photometric_loss_and_grad(color, gt, c.lambda_dssim, valid)
            return loss, grad, color
        shown = self.exposure.apply(index, color)
        loss, dshown = photometric_loss_and_grad(shown, gt, c.lambda_dssim, valid)
        return loss, self.exposure.backward(index, color, dshown), shown

    def _remove_non_finite(self, it: int) -> None:
        """Remove the Gaussians whose parameters went NaN or infinite (a few; more: raise)."""
        bad, counts = self.state.non_finite()
        n = int(bad.sum())
        if not n:
            return
        what = ", ".join(f"{k} {v}" for k, v in counts.items())
        if n > MAX_NON_FINITE_SHARE * self.state.num_gaussians:
            raise FloatingPointError(
                f"the fit diverged by step {it}: {n} of {self.state.num_gaussians} Gaussians have "
                f"non-finite parameters ({what}); lower the learning rates")
        self.state.prune(bad)
        self.removed_non_finite += n
        log.warning("iteration %d: %d Gaussian(s) with non-finite parameters (%s) removed; the "
                    "fit goes on", it, n, what)

    def _densify(self, it: int) -> None:
        """Densification, pruning and opacity reset due at iteration `it` (upstream schedule)."""
        c = self.config
        if it > c.densify_from_iter and it % c.densification_interval == 0:
            size = c.max_screen_size if it > c.opacity_reset_interval else None
            d = self.state.densify_and_prune(c.densify_grad_threshold, c.min_opacity, self.extent,
                                             size, self.max_gaussians, centre=self.centre)
            log.debug("iteration %d densify: %s", it, d)
        if it % c.opacity_reset_interval == 0 or (
            self.white_background and it == c.densify_from_iter
        ):
            self.state.reset_opacity()
            log.debug("iteration %d: opacity reset", it)

    # ------------------------------------------------------------------ one step
    def train_step(self) -> Dict[str, float]:
        """One iteration: learning rates, render, loss, backward, densification, Adam.

        Returns:
            ``loss`` and ``num_gaussians``, and ``psnr`` (train view) every ``progress_every``
            iterations and at the last.
        """
        c = self.config
        st = self.state
        self.iteration += 1
        it = self.iteration
        tm = self.timings
        self._update_lr(it)
        if it % c.sh_increase_interval == 0:
            st.oneup_sh_degree()
        index = self._next_index()
        view = self._view_at(index, self.downsample_factor(it))
        bg = (
            torch.rand(3, generator=self.background_rng, dtype=self.dtype).to(self.device)
            if c.random_background
            else self.background
        )
        # the rasterizer's NaN scans (a host sync per tensor) every _SCAN_EVERY steps, not every
        # step: a bad parameter is named within that many steps (a non-finite loss at once,
        # below), and a few bad Gaussians are removed there first
        scan = it % _SCAN_EVERY == 1
        if scan and it > 1:
            self._remove_non_finite(it)
        t0 = time.perf_counter()
        means2D = torch.zeros(
            (st.num_gaussians, 3), dtype=self.dtype, device=self.device, requires_grad=True
        )
        out = render_state(st, view, bg, c.backend, means2D=means2D, validate=scan)
        t1 = time.perf_counter()
        gt = view.image
        if c.random_background and view.alpha is not None:
            gt = gt + (bg - self.background).view(3, 1, 1) * (1.0 - view.alpha)  # re-composite
        # loss and its image gradient in closed form (no autograd graph for L1 / SSIM)
        loss, dloss, shown = self._loss_and_grad(index, out.color.detach(), gt, view.valid)
        t2 = time.perf_counter()
        out.color.backward(dloss)
        t3 = time.perf_counter()
        info = {"loss": float(loss.item())}
        if not math.isfinite(info["loss"]):
            render_state(st, view, bg, c.backend)  # names the non-finite tensor, if one is
            raise FloatingPointError(f"the fit diverged at step {it}: its loss is {info['loss']} "
                                     "(the Gaussians are finite; lower the learning rates)")
        with torch.no_grad():
            if it < c.densify_until_iter:
                st.add_densification_stats(means2D.grad, out.radii)
                t4 = time.perf_counter()
                tm["stats"] += t4 - t3
                self._densify(it)
                tm["densify"] += time.perf_counter() - t4
            t5 = time.perf_counter()
            st.step()
            st.zero_grad()
            t6 = time.perf_counter()
            tm["adam"] += t6 - t5
            if self.exposure is not None:
                self.exposure.step(self.schedule_step(it))
                tm["exposure"] += time.perf_counter() - t6
            if it % self.progress_every == 0 or it == self.total_iterations:
                info["psnr"] = psnr(shown, gt, view.valid)
        tm["render"] += t1 - t0
        tm["loss"] += t2 - t1
        tm["backward"] += t3 - t2
        info["num_gaussians"] = float(st.num_gaussians)
        return info

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def evaluate(
        self, views: Optional[Sequence[FitView]] = None, sh_degree: Optional[int] = None
    ) -> float:
        """Mean PSNR (dB) over `views` (default: the test views).

        Each view is rendered over the background and measured on its valid pixels.
        """
        views = self.test_views if views is None else list(views)
        if not views:
            raise ValueError("evaluate: no views to evaluate on")
        vals = []
        for v in views:
            out = render_state(
                self.state, v, self.background, self.config.backend, sh_degree=sh_degree
            )
            vals.append(psnr(out.color, v.image, v.valid))
        return float(sum(vals) / len(vals))

    # ------------------------------------------------------------------ the schedule
    def _replan_step(self) -> int:
        """Where a time budget's tail is planned again: where densification ends (or half-way)."""
        c = self.config
        end = c.densify_until_iter
        return end if 0 < end < c.iterations else max(1, c.iterations // 2)

    def _replan_tail(self, iteration: int, step_seconds: float, seconds_left: float) -> None:
        """Set `total_iterations` so that the steps left take ``seconds_left`` at ``step_seconds``.

        The tail's learning rates follow (`schedule_step`); `replan` records the new plan.
        """
        planned = self.config.iterations
        tail = planned - iteration
        fits = _steps_that_fit(seconds_left, step_seconds, tail, REPLAN_TAIL,
                               max(planned, UPSTREAM_ITERATIONS) - iteration)
        fits = max(1, fits // 100 * 100 if fits >= 100 else fits)
        self.total_iterations = iteration + fits
        self.replan = {"at": iteration, "planned": planned, "iterations": self.total_iterations,
                       "step_seconds": step_seconds, "seconds_left": seconds_left}
        log.info("time budget: steps take %.1f ms here when densification ends (step %d), %.0f s "
                 "of the budget left: the run ends at step %d (planned %d)", 1e3 * step_seconds,
                 iteration, seconds_left, self.total_iterations, planned)

    def _check_tail(self, iteration: int, step_seconds: float, seconds_left: float) -> None:
        """Plan the rest of a re-planned tail once more (``replan["check"]``).

        As `_replan_tail`, with the steps left bounded by REPLAN_CHECK_RANGE times those planned
        and the end rounded down to a multiple of 100 steps.
        """
        r = self.replan
        fits = max(1, _steps_that_fit(seconds_left, step_seconds,
                                      self.total_iterations - iteration, REPLAN_CHECK_RANGE,
                                      max(r["planned"], UPSTREAM_ITERATIONS) - iteration))
        end = (iteration + fits) // 100 * 100
        end = end if end > iteration else iteration + fits
        r["check"] = {"at": iteration, "schedule_at": self.schedule_step(iteration),
                      "step_seconds": step_seconds, "seconds_left": seconds_left,
                      "iterations": end}
        log.info("time budget: steps take %.1f ms at step %d, %.0f s left: the run ends at step "
                 "%d (was %d)", 1e3 * step_seconds, iteration, seconds_left, end,
                 self.total_iterations)
        self.total_iterations = end

    def _replan_window(self) -> Tuple[int, int]:
        """The steps ``(from, to)`` whose time sets a budget's tail (`_replan_tail`)."""
        at = self._replan_step()
        return at - min(REPLAN_WINDOW, max(1, at // 4)), at

    def _check_window(self, at: int) -> Optional[Tuple[int, int]]:
        """The second look's steps ``(from, to)`` in the tail re-planned at step ``at``.

        REPLAN_CHECK_SHARE into that tail (`_check_tail`); None when the tail is too short.
        """
        look = at + math.ceil(REPLAN_CHECK_SHARE * (self.total_iterations - at))
        if look - at < 2 or look >= self.total_iterations:
            return None
        return look - min(REPLAN_WINDOW, (look - at) // 2), look

    def run(self) -> FitResult:
        """The whole schedule, from the current iteration to ``total_iterations``.

        With ``config.time_budget``, the steps after densification are planned again where it
        ends (`_replan_tail`), and their rest once more three quarters of the way (`_check_tail`).
        """
        c = self.config
        t_start = time.perf_counter()
        cpu_start = time.process_time()  # this process's CPU time: wall time on a busy machine
        t_eval = 0.0
        last = {}
        # the budget's next measuring window (from, to), and the seconds of steps at its start
        window = self._replan_window() if c.time_budget is not None else None
        measured = None
        while self.iteration < self.total_iterations:
            info = self.train_step()
            it = self.iteration
            if window is not None and it in window:
                spent = time.perf_counter() - t_start - t_eval
                if it == window[0]:
                    measured = spent
                elif measured is not None:
                    pace, left = (spent - measured) / (window[1] - window[0]), c.time_budget - spent
                    measured = None
                    if self.replan is None:
                        self._replan_tail(it, pace, left)
                        window = self._check_window(it)
                    else:
                        self._check_tail(it, pace, left)
                        window = None
            total = self.total_iterations
            if "psnr" in info:
                last = info
            if self.progress is not None and (it % self.progress_every == 0 or it == total):
                self.progress(
                    it,
                    total,
                    dict(last, num_gaussians=info["num_gaussians"], loss=info["loss"]),
                )
            if (
                c.eval_interval
                and it % c.eval_interval == 0
                and self.test_views
                and it != total
            ):
                te = time.perf_counter()
                p = self.evaluate()
                t_eval += time.perf_counter() - te
                self.history.append(
                    {
                        "iteration": it,
                        "test_psnr": p,
                        "num_gaussians": self.state.num_gaussians,
                        "seconds": time.perf_counter() - t_start - t_eval,
                    }
                )
                log.info(
                    "iteration %d: test PSNR %.2f dB, %d Gaussians", it, p, self.state.num_gaussians
                )
            if self.on_save is not None and it in c.save_iterations and it != total:
                self.on_save(it, self.state.to_model())
        seconds = time.perf_counter() - t_start - t_eval
        seconds_cpu = time.process_time() - cpu_start
        test_psnr = None
        if self.test_views:
            test_psnr = self.evaluate()
            self.history.append({"iteration": self.iteration, "test_psnr": test_psnr,
                                 "num_gaussians": self.state.num_gaussians, "seconds": seconds})
            log.info("final: test PSNR %.2f dB over %d views, %d Gaussians, %.1f s",
                     test_psnr, len(self.test_views), self.state.num_gaussians, seconds)
        model = self.state.to_model()
        if self.on_save is not None:
            self.on_save(self.iteration, model)
        return FitResult(
            model=model, iterations=self.iteration, num_gaussians=self.state.num_gaussians,
            seconds_train=seconds, test_psnr=test_psnr, test_views=len(self.test_views),
            history=self.history, timings=dict(self.timings), seconds_cpu=seconds_cpu,
            removed_non_finite=self.removed_non_finite, replan=self.replan,
        )
