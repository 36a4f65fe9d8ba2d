"""Hydra configs (conf/): every group option composes and builds the object it describes.

Matchers and optimizers are built through ``_target_``; overrides reach the built objects, the
YAML defaults do not drift from the code's, and only tools/ imports Hydra.
"""
from __future__ import annotations

import dataclasses

import pytest

from icomma_plugin.localize import LocalizerConfig, RobustConfig
from icomma_plugin.matchers import Matcher, available_matchers
from tests.helpers.paths import CONF, REPO
from tests.helpers.tools import compose


def _tools_common():
    import sys

    sys.path.insert(0, str(REPO))
    from tools import _common

    return _common


def _options(group: str):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_default_composition_builds_the_default_localizer():
    common = _tools_common()
    cfg = compose()  # its data is the demo: test_demo_converges_from_20_degrees runs it
    assert isinstance(common.build_optimizer(cfg.optimizer), RobustConfig)
    matcher, name = common.build_matcher(cfg.matcher)
    assert isinstance(matcher, Matcher) and name == "xfeat"


@pytest.mark.parametrize("option", _options("optimizer"))
def test_every_optimizer_builds_its_config(option):
    built = _tools_common().build_optimizer(compose([f"optimizer={option}"]).optimizer)
    if option == "robust":
        assert isinstance(built, RobustConfig)
    else:
        assert isinstance(built, LocalizerConfig) and built.use_matching == (option == "icomma")


@pytest.mark.parametrize("option", _options("matcher"))
def test_every_matcher_builds_or_says_why_not(option):
    common = _tools_common()
    node = compose([f"matcher={option}"]).matcher
    if option == "none":
        assert common.build_matcher(node) == (None, None)
    elif option == "loftr":  # needs a user checkpoint: a one-line error naming the key
        with pytest.raises(ValueError, match="matcher.checkpoint"):
            common.build_matcher(node)
    elif available_matchers().get(option) is None:
        matcher, name = common.build_matcher(node)
        assert isinstance(matcher, Matcher) and name == option


@pytest.mark.parametrize("option", _options("renderer"))
def test_every_renderer_names_a_backend(option):
    import gaussian_renderer_pose as grp

    assert compose([f"renderer={option}"]).renderer.backend in set(grp.available_backends()) | {
        "auto"
    }


def test_yaml_defaults_are_the_code_defaults():
    """What the YAML documents is what the dataclasses do (no silent drift)."""
    common = _tools_common()
    assert common.build_optimizer(compose(["optimizer=icomma"]).optimizer) == LocalizerConfig()
    assert common.build_optimizer(compose(["optimizer=robust"]).optimizer) == RobustConfig()


def test_overrides_reach_the_built_configs():
    common = _tools_common()
    lc = common.build_optimizer(compose([
        "optimizer=icomma", "optimizer.lambda_match=0.5", "optimizer.switch_threshold=1e-2",
        "optimizer.lr=0.02", "optimizer.gradient_mode=depth"]).optimizer)
    assert (lc.lambda_match, lc.switch_threshold, lc.lr, lc.gradient_mode) == (
        0.5,
        1e-2,
        0.02,
        "depth",
    )
    rc = common.build_optimizer(
        compose(
            [
                "optimizer.geometric.max_rounds=2",
                "optimizer.refine.iterations=[5]",
                "optimizer.refine.blur=[0]",
                "optimizer.refine.scales=[1]",
                "optimizer.verdict.ok_inliers=7",
            ]
        ).optimizer
    )
    assert (
        rc.geometric.max_rounds == 2 and rc.refine.iterations == (5,) and rc.verdict.ok_inliers == 7
    )


def test_bad_optimizer_value_is_a_user_error_naming_the_field():
    common = _tools_common()
    with pytest.raises(ValueError, match="lambda_match"):
        common.build_optimizer(compose(["optimizer=icomma", "optimizer.lambda_match=2"]).optimizer)
    with pytest.raises(ValueError, match="hessian"):
        common.build_optimizer(compose(["optimizer.refine.hessian=newton"]).optimizer)


def test_data_init_none_reaches_the_problem(tmp_path):
    from icomma_plugin.app.problem import load_problem

    cfg = compose(
        [f"data.path={tmp_path / 'demo'}", "data.width=48", "data.height=48", "data.init=none"]
    )
    problem = load_problem(_tools_common().container(cfg.data))
    assert problem.init_c2w is None and problem.gt_c2w is not None
    assert len(problem.candidate_c2ws()) == len(problem.cameras) > 0


def test_only_tools_import_hydra():
    import re

    pattern = re.compile(r"^\s*(import|from)\s+(hydra|omegaconf)\b", re.MULTILINE)
    for pkg in ("icomma_plugin", "gaussian_renderer_pose"):
        offenders = [str(p) for p in (REPO / pkg).rglob("*.py") if pattern.search(p.read_text())]
        assert not offenders, offenders


def test_robust_config_round_trips_through_a_mapping():
    rc = RobustConfig()
    assert RobustConfig.from_dict(dataclasses.asdict(rc)) == rc
    with pytest.raises(ValueError, match="unknown RobustConfig.refine keys"):
        RobustConfig.from_dict({"refine": {"no_such_key": 1}})
