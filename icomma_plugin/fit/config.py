"""Every constant of the CPU 3DGS fit, in one dataclass.

Learning rates, loss weights and densification thresholds are upstream 3DGS's
(`arguments/__init__.py::OptimizationParams`, newer upstream opacity lr 2.5e-2). The iteration
schedule is upstream's (30k iterations, densify 500..15k every 100, opacity reset every 3k,
SH degree +1 every 1k) compressed for a CPU budget: see `FitConfig.scaled_schedule`,
tools/fit_scene.py and docs/FITTING.md (the comparison with upstream, measured).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Optional, Tuple

from ..checks import check_bool, check_real
from ..io.datasets import PRINCIPAL_POINTS


@dataclass
class FitConfig:
    """Every constant of the fit (module docstring); the fields are checked on construction."""

    # schedule
    iterations: int = 5000
    # seconds of steps on the machine that fits (``icomma-fit --minutes``), None: no budget.
    # The run is planned from a predicted step time; when densification ends the rest of the
    # run is planned again at the step time measured there, so that the steps take about this
    # long (`Trainer`, "Re-planning the run's tail"; the schedule's fractions keep `iterations`).
    time_budget: Optional[float] = None
    sh_degree: int = 3
    # active SH degree +1 every this many iterations (upstream 1000)
    sh_increase_interval: int = 500
    # Adam learning rates (upstream); position lr is multiplied by the scene extent and decays
    # log-linearly from init to final over `position_lr_max_steps` (None: `iterations`).
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    position_lr_delay_mult: float = 0.01
    position_lr_max_steps: Optional[int] = None
    feature_lr: float = 2.5e-3  # f_dc; f_rest uses feature_lr / 20
    opacity_lr: float = 2.5e-2
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    adam_eps: float = 1e-15
    # loss
    lambda_dssim: float = 0.2
    # densification (upstream semantics, CPU schedule)
    percent_dense: float = 0.01
    densify_from_iter: int = 200
    densify_until_iter: int = 2500
    densification_interval: int = 100
    opacity_reset_interval: int = 1500
    densify_grad_threshold: float = 2e-4
    min_opacity: float = 0.005
    max_screen_size: float = 20.0  # pixels; applied after the first opacity reset (as upstream)
    max_gaussians: int = 300_000  # densification budget (top screen-space gradients win)
    # ... and at most this many per pixel of a training image (CPU time per step grows with
    # the count; upstream's real scenes end near 1-3 per pixel of their ~1 Mpx images)
    max_gaussians_per_pixel: float = 2.0
    # initialisation
    num_random_points: int = 10_000  # when the dataset has no point cloud (Blender)
    random_points_half_extent: float = 1.3  # upstream: cube [-1.3, 1.3]^3
    # a capture without a point cloud whose reader gives a camera box (SceneData.init_box):
    # "views" places num_sweep_points by a coarse plane sweep over the training views
    # (init.plane_sweep_points), "random" draws num_random_points uniformly in the box
    box_init: str = "views"
    num_sweep_points: int = 20_000
    max_init_points: int = 200_000  # a bigger dataset cloud is subsampled
    init_opacity: float = 0.1
    # initial scales at most this many pixels seen from the nearest camera, at the fitted
    # resolution (init.init_scale_limits; None: upstream's nearest-neighbour scales as they are)
    init_max_pixels: Optional[float] = None
    # far field (photographed captures only): this many points on a shell beyond the cameras,
    # coloured by the photos (init.far_field_points); its radius is the LLFF far bound, else
    # far_field_factor x the largest camera distance from the scene centre. 0: none.
    far_field_points: int = 10_000
    far_field_factor: float = 2.0
    # size thresholds of densification and pruning (percent_dense, 0.1 x extent) grow with a
    # Gaussian's distance from the cameras' centre beyond the extent (room-scale scenes)
    distance_scaled_thresholds: bool = True
    # per-photo exposure (exposure.py; upstream --train_test_exp): None = on for photographed
    # captures, off for synthetic object renders
    exposure: Optional[bool] = None
    exposure_lr_init: float = 1e-2
    exposure_lr_final: float = 1e-3
    # Adam steps only the photos seen since the last step (exposure.ExposureState.sparse);
    # False: upstream's dense Adam
    exposure_sparse: bool = False
    # coarse-to-fine: where the coarse levels end, as fractions of the run, coarsest first:
    # (0.1, 0.3) trains at 1/4 size until 10 %, at 1/2 until 30 %, at full size after; (0.3,)
    # at 1/2 until 30 %; () at full size throughout. A level that would make an image side
    # shorter than 32 px is trained at the next finer one.
    coarse_to_fine: Tuple[float, ...] = ()
    # rendering / data
    backend: str = "auto"
    # a random background colour at every step (upstream --random_background; the capture recipe)
    random_background: bool = False
    # the views' principal point: "dataset" (their files' cx, cy) or "centre" (the image centre,
    # as upstream 3DGS fits every capture); written to cfg_args, where the localizer reads it
    principal_point: str = "dataset"
    # evaluation / saving
    eval_interval: int = 0  # 0: evaluate on the test split only at the end
    eval_views: int = 0  # 0: all test views, else this many evenly spaced
    save_iterations: Tuple[int, ...] = ()
    seed: int = 0

    def __post_init__(self):
        ints = {
            "iterations": 1,
            "sh_increase_interval": 1,
            "densification_interval": 1,
            "opacity_reset_interval": 1,
            "max_gaussians": 1,
            "num_random_points": 1,
            "max_init_points": 1,
            "num_sweep_points": 1,
            "far_field_points": 0,
            "densify_from_iter": 0,
            "densify_until_iter": 0,
            "eval_interval": 0,
            "eval_views": 0,
        }
        for name, lo in ints.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"FitConfig.{name} must be an int >= {lo}, got {v!r}")
        check_real(self.time_budget, "FitConfig.time_budget", 0.0, lo_open=True, optional=True)
        if not (isinstance(self.sh_degree, int) and 0 <= self.sh_degree <= 3):
            raise ValueError(f"FitConfig.sh_degree must be an int in 0..3, got {self.sh_degree!r}")
        if not (isinstance(self.max_gaussians_per_pixel, (int, float))
                and self.max_gaussians_per_pixel > 0):
            raise ValueError(f"FitConfig.max_gaussians_per_pixel must be > 0, got "
                             f"{self.max_gaussians_per_pixel!r}")
        if not 0.0 <= self.lambda_dssim <= 1.0:
            raise ValueError(f"FitConfig.lambda_dssim must be in [0, 1], got {self.lambda_dssim!r}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(f"FitConfig.init_opacity must be in (0, 1), got {self.init_opacity!r}")
        if self.box_init not in ("views", "random"):
            raise ValueError(f"FitConfig.box_init must be 'views' or 'random', got "
                             f"{self.box_init!r}")
        if self.principal_point not in PRINCIPAL_POINTS:
            raise ValueError(f"FitConfig.principal_point must be 'dataset' or 'centre', got "
                             f"{self.principal_point!r}")
        if self.backend not in ("auto", "reference", "cpu", "cuda"):
            raise ValueError(
                f"FitConfig.backend must be auto|reference|cpu|cuda, got {self.backend!r}"
            )
        if not (isinstance(self.far_field_factor, (int, float)) and self.far_field_factor > 1.0):
            raise ValueError(f"FitConfig.far_field_factor must be > 1 (beyond the cameras), got "
                             f"{self.far_field_factor!r}")
        if self.init_max_pixels is not None and not (
                isinstance(self.init_max_pixels, (int, float)) and self.init_max_pixels > 0):
            raise ValueError(f"FitConfig.init_max_pixels must be None or > 0, got "
                             f"{self.init_max_pixels!r}")
        if self.exposure not in (None, True, False):
            raise ValueError(f"FitConfig.exposure must be None (auto), True or False, got "
                             f"{self.exposure!r}")
        check_bool(self.exposure_sparse, "FitConfig.exposure_sparse")
        self.coarse_to_fine = tuple(float(f) for f in self.coarse_to_fine)
        if len(self.coarse_to_fine) > 2 or any(
                not 0.0 <= f <= 1.0 for f in self.coarse_to_fine) or list(
                self.coarse_to_fine) != sorted(self.coarse_to_fine):
            raise ValueError(f"FitConfig.coarse_to_fine must be at most 2 increasing fractions in "
                             f"[0, 1] (where the coarse levels end, coarsest first), got "
                             f"{self.coarse_to_fine!r}")
        self.save_iterations = tuple(int(i) for i in self.save_iterations)
        for i in self.save_iterations:
            if i < 1:
                raise ValueError(
                    f"FitConfig.save_iterations must be positive, got {self.save_iterations!r}"
                )

    @classmethod
    def scaled_schedule(cls, iterations: int, **overrides) -> "FitConfig":
        """A config whose densification / SH / reset schedule is scaled to `iterations`.

        Fractions of the run (defaults tuned on CPU for lego at 200x200, 5000 iterations):
        densify from 4 % to 50 % of the run every 2 %, opacity reset every 30 %, SH degree +1
        every 10 %. Explicit keyword overrides win.
        """
        it = int(iterations)
        sched = dict(
            iterations=it,
            densify_from_iter=max(1, round(0.04 * it)),
            densify_until_iter=max(1, round(0.5 * it)),
            densification_interval=max(1, round(0.02 * it)),
            opacity_reset_interval=max(1, round(0.3 * it)),
            sh_increase_interval=max(1, round(0.1 * it)),
        )
        sched.update(overrides)
        return cls(**sched)

    @classmethod
    def for_capture(cls, num_views: int, width: int, height: int, object_render: bool = False,
                    iterations: Optional[int] = None, seconds: Optional[float] = None,
                    **overrides) -> "FitConfig":
        """The CPU recipe for `num_views` training images of `width` x `height` (as fitted).

        `scaled_schedule` of `iterations` (None: `auto_iterations`, with the time budget
        `seconds` when given), plus, for photographed captures (not `object_render`),
        `CAPTURE_RECIPE`. Explicit keyword overrides win.
        """
        if iterations is None:
            iterations = auto_iterations(num_views, width * height, seconds)
        extra = {} if object_render else dict(CAPTURE_RECIPE)
        extra.update(overrides)
        return cls.scaled_schedule(iterations, **extra)

    def to_dict(self) -> dict:
        """The fields as a JSON-friendly dict (``save_iterations`` as a list)."""
        d = asdict(self)
        d["save_iterations"] = list(self.save_iterations)
        d["coarse_to_fine"] = list(self.coarse_to_fine)
        return d

    @classmethod
    def field_names(cls) -> Tuple[str, ...]:
        """The names of the fields, in declaration order."""
        return tuple(f.name for f in fields(cls))


# What a photographed capture adds to `FitConfig.scaled_schedule` (docs/FITTING.md measures each):
# initial Gaussians no wider than 3 px seen from the nearest camera (the nearest-neighbour
# scales of a plane sweep, SfM outliers or the far field cover much of each image: 7x the time
# of the first steps on goldcape), coarse-to-fine (1/4 size until 10 % of the run, 1/2
# until 30 %) and a random background colour at every step (upstream's --random_background: a
# photo has no transparent pixel, so a model that leaves fog where it should be opaque is
# penalised; held-out PSNR raw / exposure-fitted, seeds 0 and 1: goldcape +0.32 / +0.24 dB (seed
# 0), fox +0.50, +0.73 / +0.01, +0.49, bird -0.17, -1.31 / +0.58, +0.05; localization moved within
# the scatter between seeds; on lego's white-background renders it cost 0.45 dB, so object
# renders keep theirs).
CAPTURE_RECIPE = {"init_max_pixels": 3.0, "coarse_to_fine": (0.1, 0.3), "random_background": True}

# auto_iterations: steps per training view, and the bounds of the count
STEPS_PER_VIEW = 100
MIN_ITERATIONS, MAX_ITERATIONS = 3000, 10_000
# ... and the time a run's steps may take, in seconds on two threads of the 2-core development
# machine, quiet (docs/FITTING.md, "The run's length as a time budget"). A step costs a fixed
# part (per-Gaussian work: ~100k Gaussians on a real capture) plus a part per pixel, fitted to
# the captures' whole fits with the channels-last SSIM filter: goldcape 228x228 0.063 s a step,
# fox 270x480 0.084, bird 272x480 0.087 (lego 200x200's 0.040 is overestimated, on the safe side).
FIT_SECONDS = 480.0
STEP_SECONDS_FIXED, STEP_SECONDS_PER_PIXEL = 0.045, 3.2e-7


def step_seconds(pixels: int) -> float:
    """The expected seconds of one step at `pixels` pixels a training image (two threads)."""
    return STEP_SECONDS_FIXED + STEP_SECONDS_PER_PIXEL * pixels


#: Upstream 3DGS's run length: the most steps a time budget of the user's asks for.
UPSTREAM_ITERATIONS = 30_000


def auto_iterations(num_views: int, pixels: int, seconds: Optional[float] = None) -> int:
    """Iterations for `num_views` training images of `pixels` pixels each.

    `STEPS_PER_VIEW` passes over every view (rounded to a multiple of 500), but no more steps
    than fit in `FIT_SECONDS` at `step_seconds(pixels)` each (rounded down to a multiple of
    500: a budget), within [`MIN_ITERATIONS`, `MAX_ITERATIONS`].

    `seconds`: a budget of the user's instead (``icomma-fit --minutes``): the steps that fit in
    it, up to upstream's `UPSTREAM_ITERATIONS` (goldcape at 30000 steps: +1.8 dB held out,
    localized twice as close to its records; docs/FITTING.md).
    """
    if num_views < 1 or pixels < 1:
        raise ValueError(f"num_views and pixels must be >= 1, got {num_views!r}, {pixels!r}")
    if seconds is not None:
        if not seconds > 0:
            raise ValueError(f"seconds must be > 0, got {seconds!r}")
        by_budget = int(seconds / step_seconds(pixels) // 500) * 500
        return int(min(max(by_budget, MIN_ITERATIONS), UPSTREAM_ITERATIONS))
    by_views = round(STEPS_PER_VIEW * num_views / 500.0) * 500
    by_time = int(FIT_SECONDS / step_seconds(pixels) // 500) * 500
    return int(min(max(min(by_views, by_time), MIN_ITERATIONS), MAX_ITERATIONS))
