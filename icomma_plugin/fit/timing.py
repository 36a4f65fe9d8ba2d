"""How fast this machine runs the fitter's step, against the machine `step_seconds` describes.

`auto_iterations` turns a time budget into steps at `config.step_seconds`, a model of two
threads of the 2-core development machine. A user's ``icomma-fit --minutes M`` on a laptop with
8 cores, or beside other jobs, would get the wrong count from it. `step_time_factor` times a
few steps of a fixed synthetic fit here (the fitter's own `Trainer.train_step`: render, loss,
backward, Adam) and divides by that fit's time on the development machine: 0.5 means steps
here take half as long, so a budget buys twice the steps.
"""
from __future__ import annotations

import math
import time
from typing import Callable, Optional

import torch

from ..camera import Intrinsics
from ..gaussians import GaussianModel
from .config import FitConfig
from .trainer import FitView, Trainer

#: Seconds a step of `_probe_trainer`'s fit would take on the machine `step_seconds` models.
#: On the development machine (2 threads, quiet, 2026-12-07) the probe took 67-72 ms a step while
#: whole goldcape fits took 47.6 and 46.0 ms a step (10000 and 19000 steps) where `step_seconds`
#: says 61.6 (the fitter has grown faster than the model since it was fitted): 70 x 61.6 / 46.8.
#: Larger photos (fox, bird: 40-50 ms a step against 87) stay on the safe side.
REFERENCE_PROBE_SECONDS = 0.092
#: The factor is kept within these bounds (a probe disturbed by a burst of other work).
FACTOR_BOUNDS = (0.05, 20.0)


def _probe_trainer(num_gaussians: int = 100_000, side: int = 228) -> Trainer:
    """A fixed synthetic fit: Gaussians of a fitted capture's sizes in front of one camera."""
    g = torch.Generator().manual_seed(0)
    P = num_gaussians
    means = torch.rand(P, 3, generator=g) * torch.tensor([2.0, 2.0, 1.0]) - torch.tensor(
        [1.0, 1.0, -2.5])  # a slab 2.5-3.5 units in front of a camera at the origin
    opacity = 0.05 + 0.5 * torch.rand(P, 1, generator=g)
    model = GaussianModel(
        means, torch.rand(P, 1, 3, generator=g), 0.1 * torch.randn(P, 15, 3, generator=g),
        torch.log(opacity / (1 - opacity)), torch.log(0.004 + 0.02 * torch.rand(P, 3, generator=g)),
        torch.nn.functional.normalize(torch.randn(P, 4, generator=g), dim=-1), 3)
    intr = Intrinsics(side, side, 1.1 * side, 1.1 * side)
    view = FitView("probe", torch.rand(3, side, side, generator=g), intr, torch.eye(4))
    cfg = FitConfig(iterations=10**6, densify_until_iter=0, opacity_reset_interval=10**9,
                    sh_increase_interval=10**9)
    trainer = Trainer(model, [view], 1.0, cfg)
    trainer.state.active_sh_degree = trainer.state.max_sh_degree  # as tools/bench_fit.py
    return trainer


def step_time_factor(steps: int = 5, warmup: int = 3,
                     clock: Callable[[], float] = time.perf_counter,
                     trainer: Optional[Trainer] = None) -> float:
    """This machine's step time over the development machine's, at the current thread count.

    Times ``steps`` steps of a fixed synthetic fit (100k Gaussians at 228x228, SH degree 3;
    about 2 s in all on the development machine) after ``warmup`` steps (the first three of a
    process took 0.5 s each in the loss there) and returns the median over
    `REFERENCE_PROBE_SECONDS`, within `FACTOR_BOUNDS`. ``trainer`` and ``clock`` are for tests.
    """
    if steps < 1 or warmup < 0:
        raise ValueError(f"steps must be >= 1 and warmup >= 0, got {steps}, {warmup}")
    trainer = trainer if trainer is not None else _probe_trainer()
    for _ in range(warmup):
        trainer.train_step()
    times = []
    for _ in range(steps):
        t0 = clock()
        trainer.train_step()
        times.append(clock() - t0)
    times.sort()
    factor = times[len(times) // 2] / REFERENCE_PROBE_SECONDS
    if not math.isfinite(factor):
        return 1.0
    return float(min(max(factor, FACTOR_BOUNDS[0]), FACTOR_BOUNDS[1]))
