"""icomma_plugin.fit.timing: this machine's fitter step against the reference machine's."""
from __future__ import annotations

import pytest

from icomma_plugin.fit.timing import (
    FACTOR_BOUNDS,
    REFERENCE_PROBE_SECONDS,
    _probe_trainer,
    step_time_factor,
)


class _Clock:
    """Each timed step takes the next of ``durations`` seconds."""

    def __init__(self, durations):
        self.durations, self.now, self.calls = list(durations), 0.0, 0

    def __call__(self):
        self.calls += 1
        if self.calls % 2 == 0:  # the second reading of a step: its duration has passed
            self.now += self.durations.pop(0)
        return self.now


@pytest.fixture(scope="module")
def small_probe():
    return _probe_trainer(num_gaussians=500, side=32)


def test_factor_is_the_median_step_over_the_reference(small_probe):
    ref = REFERENCE_PROBE_SECONDS
    clock = _Clock([3 * ref, 0.5 * ref, 0.5 * ref, 10 * ref, 0.5 * ref])
    assert step_time_factor(steps=5, warmup=0, clock=clock, trainer=small_probe) == \
        pytest.approx(0.5)
    assert small_probe.iteration == 5  # the steps were taken
    slow = _Clock([1000 * ref] * 3)
    assert step_time_factor(steps=3, warmup=1, clock=slow, trainer=small_probe) == FACTOR_BOUNDS[1]


def test_probe_runs_the_fitters_step(small_probe):
    factor = step_time_factor(steps=1, warmup=0, trainer=small_probe)
    assert FACTOR_BOUNDS[0] <= factor <= FACTOR_BOUNDS[1]
    assert small_probe.state.num_gaussians == 500  # no densification in the probe
    with pytest.raises(ValueError, match="steps must be >= 1"):
        step_time_factor(steps=0, trainer=small_probe)
