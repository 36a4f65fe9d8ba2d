"""A time budget's tail: planned again at the step time measured where densification ends."""
from __future__ import annotations

import math
import time
import types

import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.fit import FitConfig
from icomma_plugin.fit import trainer as trainer_mod
from icomma_plugin.fit.state import expon_lr
from icomma_plugin.fit.trainer import (REPLAN_CHECK_RANGE, REPLAN_CHECK_SHARE, REPLAN_TAIL,
                                       FitView, Trainer)
from icomma_plugin.gaussians import GaussianModel


def _trainer(**cfg) -> Trainer:
    g = torch.Generator().manual_seed(0)
    P, side = 40, 16
    means = torch.rand(P, 3, generator=g) - torch.tensor([0.5, 0.5, -2.5])
    model = GaussianModel(means, torch.rand(P, 1, 3, generator=g), torch.zeros(P, 0, 3),
                          torch.zeros(P, 1), torch.full((P, 3), math.log(0.05)),
                          torch.nn.functional.normalize(torch.randn(P, 4, generator=g), dim=-1), 0)
    view = FitView("v", torch.rand(3, side, side, generator=g),
                   Intrinsics(side, side, 1.1 * side, 1.1 * side), torch.eye(4))
    config = FitConfig(**{"iterations": 40, "sh_degree": 0, "densify_from_iter": 1000,
                          "densify_until_iter": 20, **cfg})
    return Trainer(model, [view], 1.0, config, exposure=True)


class _Clock:
    """perf_counter that moves by ``dt`` at every training step (`install`) and at nothing else."""

    def __init__(self, dt: float):
        self.now, self.dt = 0.0, dt

    def perf_counter(self) -> float:
        return self.now

    def install(self, monkeypatch) -> None:
        monkeypatch.setattr(trainer_mod, "time", types.SimpleNamespace(
            perf_counter=self.perf_counter, process_time=time.process_time))
        step = Trainer.train_step

        def timed_step(tr):
            self.now += self.dt
            return step(tr)
        monkeypatch.setattr(Trainer, "train_step", timed_step)


def _run(monkeypatch, budget: float, dt: float = 1e-3, **cfg):
    _Clock(dt).install(monkeypatch)
    tr = _trainer(time_budget=budget, **cfg)
    seen = []
    tr.progress = lambda it, total, info: seen.append((it, total))
    return tr, tr.run(), seen


def test_the_tail_takes_what_the_budget_leaves(monkeypatch):
    tr, res, seen = _run(monkeypatch, budget=0.056)  # 36 steps left: within the bounds
    r = res.replan
    assert r is not None and r["at"] == 20 and r["planned"] == 40
    fits = int(r["seconds_left"] / r["step_seconds"])  # fewer than 100: not rounded
    assert math.ceil(REPLAN_TAIL[0] * 20) < fits < int(REPLAN_TAIL[1] * 20)
    assert r["iterations"] == 20 + fits
    # the steps keep their pace: the second look, 3/4 into the tail, keeps the end (to a step)
    check = r["check"]
    assert check["at"] == 20 + math.ceil(REPLAN_CHECK_SHARE * fits)
    assert check["step_seconds"] == pytest.approx(r["step_seconds"], rel=1e-6)
    assert abs(check["iterations"] - r["iterations"]) <= 1
    assert check["iterations"] == res.iterations == tr.iteration
    assert seen[-1] == (res.iterations, res.iterations)  # the progress counts to the new end
    assert seen[0][1] == 40  # ... and to the planned one before the re-plan


def test_a_tail_that_slows_down_is_cut_at_the_second_look(monkeypatch):
    clock = _Clock(1e-3)
    clock.install(monkeypatch)
    tr = _trainer(time_budget=0.056)  # 36 steps after the re-plan at 20
    tr.progress_every = 1

    def slow_down(it, total, info):
        if it == 22:  # the steps take twice as long from here, after the first re-plan
            clock.dt = 2e-3
    tr.progress = slow_down
    res = tr.run()
    r = res.replan
    left = r["iterations"] - r["check"]["at"]
    assert r["check"]["step_seconds"] == pytest.approx(2 * r["step_seconds"], rel=1e-6)
    assert res.iterations == r["check"]["iterations"] == r["check"]["at"] + math.ceil(
        REPLAN_CHECK_RANGE[0] * left)  # half the rest or less would fit: its lower bound
    assert res.iterations < r["iterations"]


@pytest.mark.parametrize("budget, tail", [(1e-6, math.ceil(REPLAN_TAIL[0] * 20)),
                                          (1e6, int(REPLAN_TAIL[1] * 20))])
def test_the_tail_stays_within_its_bounds(monkeypatch, budget, tail):
    _, res, _ = _run(monkeypatch, budget=budget)
    assert res.iterations == 20 + tail


def test_no_budget_no_replan(monkeypatch):
    _Clock(1e-3).install(monkeypatch)
    res = _trainer().run()
    assert res.replan is None and res.iterations == 40


def test_the_learning_rates_go_on_and_end_where_the_plan_ended_them():
    tr = _trainer(iterations=10_000, densify_until_iter=5000)
    tr._replan_tail(5000, 0.05, 400.0)  # 8000 steps fit in 400 s at 50 ms
    assert tr.total_iterations == 13_000
    assert tr.schedule_step(5000) == 5000 and tr.schedule_step(13_000) == 10_000
    steps = [tr.schedule_step(i) for i in range(4990, 13_001)]
    assert all(b > a for a, b in zip(steps, steps[1:]))
    c = tr.config
    lr = [expon_lr(tr.schedule_step(i), c.position_lr_init, c.position_lr_final, tr.max_steps)
          for i in (5000, 5001, 13_000)]
    assert lr[0] == pytest.approx(expon_lr(5000, c.position_lr_init, c.position_lr_final,
                                           10_000))
    assert lr[1] == pytest.approx(lr[0], rel=1e-3)  # continuous
    assert lr[2] == pytest.approx(c.position_lr_final)
    # the second look stretches the rest onto the rest of the plan, from where it stood
    tr._check_tail(11_000, 0.06, 60.0)  # 1000 steps fit in 60 s: the run ends at 12_000
    assert tr.total_iterations == 12_000 and tr.replan["iterations"] == 13_000
    at_check = tr.schedule_step(11_000)
    assert tr.replan["check"]["schedule_at"] == at_check == pytest.approx(5000 + 6000 * 5 / 8)
    assert tr.schedule_step(12_000) == pytest.approx(10_000)
    steps = [tr.schedule_step(i) for i in range(10_990, 12_001)]
    assert all(b > a for a, b in zip(steps, steps[1:]))
    assert tr.schedule_step(11_001) - at_check == pytest.approx(
        (10_000 - at_check) / 1000)  # continuous at the look, then the new, steeper slope
    # the tail rounded down to 100 steps, capped at upstream's 30000 in all
    tr = _trainer(iterations=10_000, densify_until_iter=5000)
    tr._replan_tail(5000, 0.05, 10_000.0)
    assert tr.total_iterations == 25_000  # 4x the planned tail
    tr = _trainer(iterations=20_000, densify_until_iter=10_000)
    tr._replan_tail(10_000, 0.05, 10_000.0)
    assert tr.total_iterations == 30_000
    tr._replan_tail(10_000, 0.0437, 211.0)
    assert tr.total_iterations == 14_800  # 4828 steps -> 4800


def test_time_budget_is_checked():
    for bad in (0, -1.0, float("nan"), True, "10"):
        with pytest.raises(ValueError, match="time_budget"):
            FitConfig(time_budget=bad)
