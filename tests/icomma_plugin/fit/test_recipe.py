"""The CPU recipe of a fit: iterations from the capture, what a photographed capture adds."""
from __future__ import annotations

import pytest

from icomma_plugin.fit import FitConfig
from icomma_plugin.fit.config import (
    CAPTURE_RECIPE,
    MAX_ITERATIONS,
    MIN_ITERATIONS,
    FIT_SECONDS,
    STEP_SECONDS_FIXED,
    STEP_SECONDS_PER_PIXEL,
    STEPS_PER_VIEW,
    auto_iterations,
    step_seconds,
)
from icomma_plugin.fit.scene import CaptureInfo


def test_auto_iterations():
    assert auto_iterations(1, 100) == MIN_ITERATIONS
    assert auto_iterations(10_000, 100) == MAX_ITERATIONS
    n = (MIN_ITERATIONS + MAX_ITERATIONS) // 2 // STEPS_PER_VIEW  # between the bounds
    assert auto_iterations(n, 1) == round(STEPS_PER_VIEW * n / 500) * 500
    # large images: the time budget decides, rounded down (a budget is not exceeded)
    pixels = int((FIT_SECONDS / 6200 - STEP_SECONDS_FIXED) / STEP_SECONDS_PER_PIXEL)
    assert auto_iterations(10_000, pixels) == 6000
    assert 6000 * step_seconds(pixels) <= FIT_SECONDS
    # the lengths docs/FITTING.md measured: fox and goldcape by their photo count, bird by time
    assert auto_iterations(43, 270 * 480) == 4500
    assert auto_iterations(161, 272 * 480) == 5500
    assert auto_iterations(104, 228 * 228) == 7500
    with pytest.raises(ValueError, match="num_views"):
        auto_iterations(0, 100)


def test_a_time_budget_of_the_users_gives_as_many_steps_as_fit_up_to_upstreams():
    from icomma_plugin.fit.config import UPSTREAM_ITERATIONS

    # goldcape: 40 minutes hold upstream's 30000 steps; bird's larger photos fewer
    assert auto_iterations(104, 228 * 228, seconds=2400) == UPSTREAM_ITERATIONS
    bird = auto_iterations(161, 272 * 480, seconds=2400)
    assert bird == 27500 and bird * step_seconds(272 * 480) <= 2400
    # past the recipe's own cap of 100 steps a photo and MAX_ITERATIONS, not below the floor
    assert auto_iterations(43, 270 * 480, seconds=1800) > max(MAX_ITERATIONS, 100 * 43)
    assert auto_iterations(104, 228 * 228, seconds=10) == MIN_ITERATIONS
    for bad in (0, -5.0):
        with pytest.raises(ValueError, match="seconds"):
            auto_iterations(104, 100, seconds=bad)
    assert FitConfig.for_capture(104, 228, 228, seconds=2400).iterations == UPSTREAM_ITERATIONS


def test_for_capture():
    photo = FitConfig.for_capture(100, 200, 200)
    render = FitConfig.for_capture(100, 200, 200, object_render=True)
    assert photo.iterations == render.iterations == auto_iterations(100, 200 * 200)
    for k, v in CAPTURE_RECIPE.items():
        assert getattr(photo, k) == v
    assert render.coarse_to_fine == () and render.init_max_pixels is None
    assert photo.random_background and not render.random_background
    fixed = FitConfig.for_capture(100, 200, 200, iterations=1234, coarse_to_fine=())
    assert fixed.iterations == 1234 and fixed.coarse_to_fine == ()
    assert fixed.densify_until_iter == round(0.5 * 1234)  # the scaled schedule


def test_tool_builds_the_recipe_of_the_capture(monkeypatch):
    from icomma_plugin.fit import timing
    from tools.fit_scene import build_config, parse_args

    monkeypatch.setattr(timing, "step_time_factor", lambda: 1.0)  # the reference machine

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
    # a time budget instead of the recipe's length, with either recipe
    cfg = build_config(parse_args(["-m", "x", "--minutes", "40"]), cap)
    assert cfg.iterations == 30000 and cfg.coarse_to_fine == CAPTURE_RECIPE["coarse_to_fine"]
    assert cfg.densify_until_iter == 15000  # the schedule scaled to the run, as upstream's
    cfg = build_config(parse_args(["-m", "x", "--minutes", "40", "--recipe", "scaled"]), cap)
    assert cfg.iterations == 30000 and cfg.coarse_to_fine == ()
    # a machine whose steps take twice as long gets half the steps (10 minutes: 9500 at 1x)
    assert build_config(parse_args(["-m", "x", "--minutes", "10"]), cap).iterations == 9500
    monkeypatch.setattr(timing, "step_time_factor", lambda: 2.0)
    assert build_config(parse_args(["-m", "x", "--minutes", "10"]), cap).iterations == 4500
    with pytest.raises(ValueError, match="needs the capture's photos"):
        build_config(parse_args(["-m", "x", "--minutes", "10"]), None)
    with pytest.raises(ValueError, match="give one"):
        build_config(parse_args(["-m", "x", "--minutes", "40", "--iterations", "700"]), cap)
    with pytest.raises(ValueError, match="--minutes must be > 0"):
        build_config(parse_args(["-m", "x", "--minutes", "0"]), cap)


def fit_tiny_capture(tmp_path, iterations: int):
    """tools/fit_scene.py on a tiny LLFF capture written under ``tmp_path``: the model folder."""
    from tests.icomma_plugin.fit.test_capture_fit import _write_llff
    from tools.fit_scene import main

    _write_llff(tmp_path / "data", n=8, size=64)
    model = tmp_path / "model"
    assert main(["-s", str(tmp_path / "data"), "-m", str(model), "--iterations", str(iterations),
                 "--threads", "1", "--no-progress", "--set", "num_sweep_points=300",
                 "--set", "far_field_points=300"]) == 0
    return model


def test_tool_fits_then_evaluates_with_a_grid(tmp_path, capsys):
    """tools/fit_scene.py end to end on a tiny capture: the capture recipe, then --evaluate."""
    import json

    from tools.fit_scene import main

    model = fit_tiny_capture(tmp_path, 20)
    fitted = json.loads(capsys.readouterr().out)
    assert fitted["iterations"] == 20 and fitted["test_psnr_right_half_exposure"] is not None
    metrics = json.loads((model / "metrics.json").read_text())
    assert metrics["config"]["coarse_to_fine"] == [0.1, 0.3]  # the capture recipe
    assert metrics["config"]["init_max_pixels"] == 3.0
    assert main(["-m", str(model), "--evaluate", "--threads", "1"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["test_psnr"] == pytest.approx(fitted["test_psnr"], abs=1e-3)
    grid = model / "eval_test_grid.png"
    assert ev["grid"] == str(grid) and grid.is_file()
    assert main(["-m", str(tmp_path / "nowhere"), "--evaluate", "--threads", "1"]) == 2


def test_without_a_bar_the_fit_logs_a_line_a_minute_with_the_time_left(caplog):
    """``--no-progress``: a log line every ``log_seconds`` of the clock, and at the end."""
    import logging

    from tools.fit_scene import make_progress

    now = [0.0]
    progress = make_progress(None, 0, log_seconds=60.0, clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="fit_scene"):
        for it in range(1, 101):  # 2 s a step, then 3 s from step 30 on
            now[0] = 2.0 * it if it <= 30 else 60.0 + 3.0 * (it - 30)
            progress(it, 100, {"loss": 0.5, "num_gaussians": 1000})
    lines = [r.getMessage() for r in caplog.records if "iteration" in r.getMessage()]
    assert [line.split()[1] for line in lines] == ["30/100", "50/100", "70/100", "90/100",
                                                   "100/100"]
    # the time left at the last minute's rate: 2 s a step, then 3
    assert "about 140 s left" in lines[0] and "about 150 s left" in lines[1]
    assert "about 0 s left" in lines[-1]
    # with --log-every the steps say when, and the clock adds nothing
    caplog.clear()
    every = make_progress(None, 25, log_seconds=60.0, clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="fit_scene"):
        for it in range(1, 101):
            now[0] = 2.0 * it
            every(it, 100, {"loss": 0.5, "num_gaussians": 1000})
    assert len([r for r in caplog.records if "iteration" in r.getMessage()]) == 4
