"""The CPU recipe of a fit: iterations from the capture, what a photographed capture adds."""
from __future__ import annotations

import pytest

from icomma_plugin.fit import FitConfig
from icomma_plugin.fit.config import (
    CAPTURE_RECIPE,
    MAX_ITERATIONS,
    MIN_ITERATIONS,
    PIXEL_STEPS,
    STEPS_PER_VIEW,
    auto_iterations,
)
from icomma_plugin.fit.scene import CaptureInfo


def test_auto_iterations():
    assert auto_iterations(1, 100) == MIN_ITERATIONS
    assert auto_iterations(10_000, 100) == MAX_ITERATIONS
    n = (MIN_ITERATIONS + MAX_ITERATIONS) // 2 // STEPS_PER_VIEW  # between the bounds
    assert auto_iterations(n, 1) == round(STEPS_PER_VIEW * n / 500) * 500
    # large images: the pixel-step budget decides
    big = int(PIXEL_STEPS / 6000)
    assert auto_iterations(10_000, big) == 6000
    for v in (auto_iterations(43, 270 * 480), auto_iterations(161, 272 * 480)):
        assert v % 500 == 0 and MIN_ITERATIONS <= v <= MAX_ITERATIONS
    with pytest.raises(ValueError, match="num_views"):
        auto_iterations(0, 100)


def test_for_capture():
    photo = FitConfig.for_capture(100, 200, 200)
    render = FitConfig.for_capture(100, 200, 200, object_render=True)
    assert photo.iterations == render.iterations == auto_iterations(100, 200 * 200)
    for k, v in CAPTURE_RECIPE.items():
        assert getattr(photo, k) == v
    assert render.coarse_to_fine == () and render.init_max_pixels is None
    fixed = FitConfig.for_capture(100, 200, 200, iterations=1234, coarse_to_fine=())
    assert fixed.iterations == 1234 and fixed.coarse_to_fine == ()
    assert fixed.densify_until_iter == round(0.5 * 1234)  # the scaled schedule


def test_tool_builds_the_recipe_of_the_capture():
    from tools.fit_scene import build_config, parse_args

    cap = CaptureInfo(train_views=104, width=228, height=228, object_render=False)
    cfg = build_config(parse_args(["-m", "x"]), cap)
    assert cfg.iterations == auto_iterations(104, 228 * 228)
    assert cfg.coarse_to_fine == CAPTURE_RECIPE["coarse_to_fine"]
    cfg = build_config(parse_args(["-m", "x", "--iterations", "700", "--set",
                                   "coarse_to_fine=(0.2,)"]), cap)
    assert cfg.iterations == 700 and cfg.coarse_to_fine == (0.2,)
    cfg = build_config(parse_args(["-m", "x", "--recipe", "scaled"]), cap)
    assert cfg.iterations == 5000 and cfg.coarse_to_fine == ()
    with pytest.raises(ValueError, match="unknown FitConfig field"):
        build_config(parse_args(["-m", "x", "--set", "nope=1"]), cap)
