"""Fit one model to another model's renders (distillation).

Used after :func:`icomma_plugin.lod.split_gaussians`: a split model whose children were placed by
a rule alone loses the tails of faint Gaussians to the rasterizer's 1/255 alpha cut (lego split
to 1M Gaussians rendered its parent's image at 31-34 dB). Upstream's densification is followed by
more optimisation, and so is this: the split model (the student) is fitted for a few steps to the
original model's renders (the teacher) from the model's cameras, with densification, pruning and
opacity resets off, so the count stays the one asked for.
"""
from __future__ import annotations

import dataclasses
from typing import Optional, Sequence, Tuple

import torch

from ..camera import Intrinsics
from ..checks import check_int
from ..gaussians import GaussianModel
from ..pose.convert import cameras_extent
from ..render import prepare_scene, render
from .config import FitConfig
from .trainer import FitView, ProgressFn, Trainer

#: The schedule of a distillation: no densification / pruning / opacity reset, every SH degree
#: from the start, learning rates a tenth (positions) to a half of upstream's (the student starts
#: near its answer), L1 only (the teacher's image is exact: there is no noise for SSIM to see).
DISTILL_CONFIG = FitConfig(
    iterations=100, densify_until_iter=0, opacity_reset_interval=10**9,
    sh_increase_interval=10**9, position_lr_init=1.6e-5, position_lr_final=1.6e-6,
    feature_lr=1e-3, opacity_lr=1e-2, scaling_lr=2e-3, rotation_lr=5e-4, lambda_dssim=0.0,
    min_opacity=0.0,
)


def distill(student: GaussianModel, teacher: GaussianModel,
            cameras: Sequence[Tuple[Intrinsics, torch.Tensor]], steps: int,
            background: Sequence[float] = (0.0, 0.0, 0.0), config: Optional[FitConfig] = None,
            progress: Optional[ProgressFn] = None) -> GaussianModel:
    """``student`` fitted for ``steps`` steps to ``teacher``'s renders from ``cameras``.

    Args:
        student: the model to fit (CPU); its Gaussian count is kept.
        teacher: the model whose image the student should render; the same SH degree.
        cameras: (intrinsics, w2c [4, 4]) pairs, the views fitted to (one a step, reshuffled).
        steps: optimisation steps (0 returns the student unchanged).
        background: the RGB both are composited over.
        config: the schedule (default ``DISTILL_CONFIG``; its ``iterations`` is set to ``steps``).
        progress: ``Trainer``'s callback, every 10 steps.

    Returns:
        A new model with the student's Gaussian count (less any Gaussian whose parameters went
        NaN, removed as in a fit: ``Trainer``).

    Raises:
        ValueError: no cameras, a negative ``steps``, or SH degrees that differ.
    """
    steps = check_int(steps, "steps", 0)
    cameras = list(cameras)
    if not cameras:
        raise ValueError("cameras must hold at least one (intrinsics, w2c) pair, got none")
    if student.sh_degree != teacher.sh_degree:
        raise ValueError(f"student and teacher must have the same SH degree, got "
                         f"{student.sh_degree} and {teacher.sh_degree}")
    if steps == 0:
        return student
    cfg = dataclasses.replace(config or DISTILL_CONFIG, iterations=steps,
                              sh_degree=student.sh_degree)
    bg = torch.as_tensor(background, dtype=torch.float32).reshape(3)
    scene = prepare_scene(teacher)
    views = []
    for k, (intr, w2c) in enumerate(cameras):
        w2c = torch.as_tensor(w2c, dtype=torch.float32)
        with torch.no_grad():
            image = render(scene, intr, w2c, bg).color.clamp(0.0, 1.0)
        views.append(FitView(f"camera_{k}", image, intr, w2c))
    # upstream's spatial learning-rate scale: the cameras' radius
    extent = cameras_extent([torch.linalg.inv(v.w2c) for v in views])
    trainer = Trainer(student, views, max(extent, 1e-6), cfg, background=tuple(bg.tolist()),
                      progress=progress)
    trainer.state.active_sh_degree = trainer.state.max_sh_degree  # as tools/bench_fit.py
    return trainer.run().model
