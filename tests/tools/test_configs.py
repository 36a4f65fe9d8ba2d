"""Hydra configs (conf/): every group option composes and builds the object it describes.

Matchers and optimizers are built through ``_target_``; overrides reach the built objects, the
YAML defaults do not drift from the code's, and only tools/ imports Hydra.
"""
from __future__ import annotations

import dataclasses
import sys

import pytest
import torch

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


def _matches(matcher, image0, image1):
    m = matcher.match(image0, image1)
    return m.kpts0.numpy().tobytes(), m.kpts1.numpy().tobytes(), m.confidence.numpy().tobytes()


@pytest.mark.parametrize("option", _options("matcher"))
def test_every_matcher_builds_or_says_why_not(option, no_network, one_torch_thread):
    """Each option builds the class it names, the same through the tools and Hydra's instantiate.

    An option whose weights or modules are missing here is skipped with the reason (the weights
    packages are pinned in requirements-weights.txt); none and loftr are checked as such.
    """
    from hydra.utils import instantiate

    from icomma_plugin.matchers import matcher_from_config

    common = _tools_common()
    node = compose([f"matcher={option}"]).matcher
    if option == "none":
        assert common.build_matcher(node) == (None, None)
        assert matcher_from_config(common.container(node)) is None
        return
    if option == "loftr":  # needs a user checkpoint: a one-line error naming the key
        with pytest.raises(ValueError, match=r"^matcher\.checkpoint: .*outdoor_ds\.ckpt"):
            common.build_matcher(node)
        return
    reason = available_matchers()[option]
    if reason is not None:
        pytest.skip(f"matcher={option} cannot be built here: {reason}")
    matcher, name = common.build_matcher(node)
    assert isinstance(matcher, Matcher) and name == option
    assert f"{type(matcher).__module__}.{type(matcher).__name__}" == node._target_
    by_hydra = instantiate(node)
    assert type(by_hydra) is type(matcher)
    from tests.icomma_plugin.test_matchers import texture

    pair = texture(128, 160), texture(128, 160, (3.0, -2.0))
    assert _matches(by_hydra, *pair) == _matches(matcher, *pair)


def test_matcher_overrides_reach_the_class():
    common = _tools_common()
    sift, _ = common.build_matcher(compose(["matcher=sift", "+matcher.ratio=0.6"]).matcher)
    assert sift.ratio == 0.6
    with pytest.raises(ValueError, match=r"^matcher\.ratio: ratio must be in"):
        common.build_matcher(compose(["matcher=sift", "+matcher.ratio=1.5"]).matcher)
    with pytest.raises(ValueError, match=r"^matcher\.checkpoint: checkpoint '/nonexistent/x.ckpt'"):
        common.build_matcher(compose(["matcher=loftr", "matcher.checkpoint=/nonexistent/x.ckpt"])
                             .matcher)
    with pytest.raises(ValueError, match=r"^matcher\._target_: cannot import icomma_no_such"):
        common.build_matcher(compose(["matcher=sift", "matcher._target_=icomma_no_such.M"])
                             .matcher)


#: A matcher in one module: a grid of image1 matched to the same points moved by `shift`.
SHIFT_MATCHER_MODULE = '''
import torch

from icomma_plugin.matchers import Matcher, Matches


class ShiftMatcher(Matcher):
    name = "shift"

    def __init__(self, shift=(0.0, 0.0), step=12, **kwargs):
        super().__init__(**kwargs)
        self.shift = torch.tensor([float(v) for v in shift])
        self.step = int(step)

    def _match(self, image0, image1):
        h, w = image1.shape[1:]
        ys, xs = torch.meshgrid(torch.arange(16, h - 16, self.step),
                                torch.arange(16, w - 16, self.step), indexing="ij")
        kpts1 = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).float()
        return Matches(kpts1 + self.shift, kpts1, torch.ones(len(kpts1)))
'''


def test_a_new_matcher_is_one_module_and_one_yaml(tmp_path, monkeypatch, one_torch_thread):
    """A matcher module and its yaml, nothing else: the tools and Hydra build and run it.

    Nothing in the package or conf/ is edited: the module is on sys.path, the yaml on the config
    search path; the tools, matcher_from_config and Hydra's instantiate build the same matcher.
    """
    from hydra.utils import instantiate

    from icomma_plugin.matchers import matcher_from_config
    from tests.icomma_plugin.test_matchers import texture

    module = "icomma_test_shift_matcher"
    (tmp_path / f"{module}.py").write_text(SHIFT_MATCHER_MODULE)
    (tmp_path / "conf" / "matcher").mkdir(parents=True)
    (tmp_path / "conf" / "matcher" / "shift.yaml").write_text(
        f"_target_: {module}.ShiftMatcher\nshift: [2, -1]\nstep: 12\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, module, raising=False)
    node = compose([f"hydra.searchpath=[file://{tmp_path / 'conf'}]", "matcher=shift"]).matcher
    matcher, name = _tools_common().build_matcher(node)
    assert name == "shift" and type(matcher).__module__ == module
    query = texture(128, 128)
    render = texture(128, 128, (2.4, -1.3)).requires_grad_(True)
    m = matcher.match(render, query)
    assert len(m) == 64 and torch.equal(m.kpts0 - m.kpts1, torch.tensor([2.0, -1.0]).expand(64, 2))
    # the base class gives it the differentiable refinement: the true sub-pixel shift, gradients
    md = matcher.match(render, query, differentiable=True)
    assert float((md.kpts0.detach() - md.kpts1 - torch.tensor([2.4, -1.3])).abs().max()) < 0.1
    md.kpts0.sum().backward()
    assert float(render.grad.abs().sum()) > 0
    for other in (matcher_from_config(_tools_common().container(node)), instantiate(node)):
        assert type(other) is type(matcher) and torch.equal(other.shift, matcher.shift)
    monkeypatch.delitem(sys.modules, module)


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
    from icomma_plugin.pose.convert import same_pose

    # every model camera is a candidate view: none sits at the query's own pose
    assert len(problem.cameras) > 0
    assert not any(same_pose(e.c2w, problem.gt_c2w) for e in problem.cameras)


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


def test_every_tools_set_reads_values_one_way():
    """bench_localize's and fit_scene's ``--set`` share one parser.

    YAML values, Python literals where YAML reads only a string, dotted keys that must exist.
    """
    common = _tools_common()
    apply_overrides, parse_overrides = common.apply_overrides, common.parse_overrides

    got = dict(parse_overrides(["a=0.5", "b=[1, 2]", "c=null", "d=None", "e=(0.2,)", "f=true",
                                "g=True", "h=text", " i = 3", "j=1e-4", "k=[1, 2"]))
    assert got == {"a": 0.5, "b": [1, 2], "c": None, "d": None, "e": (0.2,), "f": True,
                   "g": True, "h": "text", "i": 3, "j": 1e-4, "k": "[1, 2"}
    cfg = {"x": 1, "sub": {"y": [0.1], "z": None}}
    out = apply_overrides(cfg, ["sub.y=[2, 3]", "x=4"], "the config")
    assert out == {"x": 4, "sub": {"y": [2, 3], "z": None}} and cfg["x"] == 1  # a copy
    for bad, words in (("sub.w=1", "the config has no key 'sub.w'"), ("x.y=1", "no key 'x.y'"),
                       ("=1", "expected key=value"), ("x", "expected key=value")):
        with pytest.raises(ValueError, match=words):
            apply_overrides(cfg, [bad], "the config")


def test_a_passive_openmp_wait_is_named_where_it_costs(monkeypatch, caplog):
    """torch_threads says when OMP_WAIT_POLICY=PASSIVE slows the matcher (2+ threads only)."""
    import logging

    common = _tools_common()
    passive_wait_note, thread_env = common.passive_wait_note, common.thread_env
    torch_threads = common.torch_threads
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert passive_wait_note(2) is None and "OMP_WAIT_POLICY" not in thread_env()
    monkeypatch.setenv("OMP_WAIT_POLICY", "passive")
    assert passive_wait_note(1) is None  # one thread has nobody to wait for
    assert "OMP_WAIT_POLICY=PASSIVE" in passive_wait_note(2)
    assert thread_env()["OMP_WAIT_POLICY"] == "passive"
    before = torch.get_num_threads()
    with caplog.at_level(logging.INFO, logger="icomma"):
        with torch_threads(2) as n:
            assert n == 2
    assert any("OMP_WAIT_POLICY=PASSIVE" in r.getMessage() for r in caplog.records)
    assert torch.get_num_threads() == before
    caplog.clear()
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    with caplog.at_level(logging.INFO, logger="icomma"):
        with torch_threads(2):
            pass
    assert not any("OMP_WAIT_POLICY" in r.getMessage() for r in caplog.records)


def test_automatic_threads_follow_the_cores_busy_now_not_a_stale_load(monkeypatch, tmp_path):
    """A load average left by a run that has ended does not cost the next tool its threads.

    The cores busy now come from two readings of /proc/stat; a busy process still counts.
    """
    import itertools
    import os

    common = _tools_common()
    stat = tmp_path / "stat"

    def readings(*pairs):  # successive (all, idle) jiffies of the aggregate cpu line
        lines = itertools.cycle(f"cpu  {a - i} 0 0 {i} 0 0 0 0 0 0\n" for a, i in pairs)
        real_open = open

        def fake_open(path, *args, **kw):
            if str(path) == "/proc/stat":
                stat.write_text(next(lines))
                return real_open(stat, *args, **kw)
            return real_open(path, *args, **kw)

        monkeypatch.setattr("builtins.open", fake_open)

    monkeypatch.setattr(common.time, "sleep", lambda s: None)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "getloadavg", lambda: (1.4, 1.0, 0.9))
    readings((1000, 500), (1200, 700))  # the last 200 jiffies all idle
    assert common.busy_cores_now() == 0.0
    assert common.choose_threads() == 2  # the load average alone gave 1
    readings((1000, 500), (1200, 600))  # one of two cores busy now
    assert common.busy_cores_now() == pytest.approx(1.0)
    assert common.choose_threads() == 1
    assert common.choose_threads(3) == 3  # asked for: as asked
    monkeypatch.setattr(common, "_cpu_times", lambda *a: (_ for _ in ()).throw(OSError()))
    assert common.busy_cores_now() is None and common.choose_threads() == 1  # the load average
    monkeypatch.setattr(os, "getloadavg", lambda: (0.2, 0.2, 0.2))
    assert common.choose_threads() == 2


def test_a_process_pinned_to_some_cores_looks_at_those_cores_only(tmp_path, monkeypatch):
    """A cluster slot of 4 cores on a busy 16-core machine takes its 4 threads."""
    import os

    common = _tools_common()
    stat = tmp_path / "stat"

    def write(busy_of):  # jiffies per CPU: 100 a reading, busy_of[cpu] of them busy
        write.n += 1
        busy = [busy_of.get(c, 100) * write.n for c in range(16)]
        idle = [write.n * 100 - b for b in busy]
        rows = [f"cpu  {sum(busy)} 0 0 {sum(idle)} 0 0 0 0 0 0"]
        rows += [f"cpu{c} {b} 0 0 {i} 0 0 0 0 0 0" for c, (b, i) in enumerate(zip(busy, idle))]
        stat.write_text("\n".join(rows) + "\n")
    write.n = 0
    real_open = open

    def fake_open(path, *args, **kw):
        if str(path) == "/proc/stat":
            write(fake_open.busy)
            return real_open(stat, *args, **kw)
        return real_open(path, *args, **kw)

    monkeypatch.setattr("builtins.open", fake_open)
    monkeypatch.setattr(common.time, "sleep", lambda s: None)
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {4, 5, 6, 7}, raising=False)
    monkeypatch.setattr(os, "getloadavg", lambda: (15.0, 15.0, 15.0))  # the other jobs
    fake_open.busy = {4: 0, 5: 0, 6: 0, 7: 0}  # every other core busy, ours idle
    assert common.busy_cores_now(cpus=[4, 5, 6, 7]) == pytest.approx(0.0)
    assert common.busy_cores_now() == pytest.approx(12.0)
    assert common.choose_threads() == 4  # the machine's load average alone gave 1
    fake_open.busy = {4: 100, 5: 0, 6: 0, 7: 0}  # one of our cores taken by another process
    assert common.choose_threads() == 3
    monkeypatch.setattr(common, "_cpu_times", lambda *a: (_ for _ in ()).throw(OSError()))
    assert common.choose_threads() == 4  # unreadable: the slot is ours
