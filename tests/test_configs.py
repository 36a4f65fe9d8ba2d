"""Hydra configs (conf/): every group option composes, and the optimizer group instantiates
into icomma_plugin.localize.LocalizerConfig."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from icomma_plugin.localize import LocalizerConfig

CONF = Path(__file__).resolve().parents[1] / "conf"


def _options(group: str):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def _compose(overrides=()):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="localize", overrides=list(overrides), return_hydra_config=False)


def test_groups_have_the_expected_options():
    assert _options("data") == ["demo", "model_folder"]
    assert _options("matcher") == sorted(
        ["xfeat", "aliked_lightglue", "disk_lightglue", "sift", "orb", "loftr", "none"])
    assert _options("optimizer") == ["compare_only", "icomma"]
    assert _options("renderer") == ["auto", "cpu", "cuda", "reference"]


def test_default_composition_is_the_demo():
    cfg = _compose()
    assert cfg.data.kind == "demo"
    assert cfg.matcher.name == "xfeat"
    assert cfg.renderer.backend == "auto"
    assert cfg.seed == 0
    LocalizerConfig.from_dict(OmegaConf.to_container(cfg.optimizer, resolve=True))


@pytest.mark.parametrize("group", ["data", "matcher", "optimizer", "renderer"])
def test_every_option_composes(group):
    for option in _options(group):
        cfg = _compose([f"{group}={option}"])
        node = cfg[group]
        assert node is not None
        if group == "renderer":
            assert node.backend == option
        if group == "matcher":
            assert node.name == option
        if group == "optimizer":
            lc = LocalizerConfig.from_dict(OmegaConf.to_container(node, resolve=True))
            assert isinstance(lc, LocalizerConfig)
            assert lc.use_matching == (option == "icomma")


def test_optimizer_defaults_match_localizer_config():
    """The icomma optimizer yaml holds every LocalizerConfig field, with the dataclass defaults."""
    cfg = _compose()
    node = OmegaConf.to_container(cfg.optimizer, resolve=True)
    fields = {f.name for f in dataclasses.fields(LocalizerConfig)} - {"record_trace"}
    assert fields <= set(node), sorted(fields - set(node))
    assert LocalizerConfig.from_dict(node) == LocalizerConfig()


def test_loftr_checkpoint_defaults_to_null():
    cfg = _compose(["matcher=loftr"])
    assert cfg.matcher.checkpoint is None


def test_model_folder_fields():
    cfg = _compose(["data=model_folder", "data.model_path=/x", "data.init.rot_deg=30"])
    d = cfg.data
    assert d.kind == "model_folder" and d.iteration is None
    for key in ("image", "camera", "dataset", "split", "index"):
        assert key in d.query
    for key in ("camera", "c2w_file", "rot_deg", "trans", "pivot", "seed"):
        assert key in d.init
    for key in ("camera", "fx", "fy", "cx", "cy"):
        assert key in d.intrinsics


def test_overrides_reach_localizer_config():
    cfg = _compose(["optimizer.lambda_match=0.5", "optimizer.switch_threshold=1e-2",
                    "optimizer.lr=0.02", "optimizer.gradient_mode=depth"])
    lc = LocalizerConfig.from_dict(OmegaConf.to_container(cfg.optimizer, resolve=True))
    assert (lc.lambda_match, lc.switch_threshold, lc.lr, lc.gradient_mode) == (0.5, 1e-2, 0.02, "depth")


def test_only_tools_import_hydra():
    import re

    pattern = re.compile(r"^\s*(import|from)\s+(hydra|omegaconf)\b", re.MULTILINE)
    root = Path(__file__).resolve().parents[1] / "icomma_plugin"
    offenders = [str(p) for p in root.rglob("*.py") if pattern.search(p.read_text())]
    assert not offenders, offenders
