"""The Localizer's level of detail: a reduced model for the geometric stage and the candidates."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.localization.candidates import CandidateConfig
from icomma_plugin.localization.level_of_detail import (
    LOD_AUTO_GAUSSIANS,
    lod_config,
    lod_intrinsics,
)
from icomma_plugin.localization.localizer import Localizer
from icomma_plugin.localization.robust import RobustConfig
from icomma_plugin.localization.types import Query
from icomma_plugin.lod import LodConfig

#: A small candidate search: the demo's ring cameras and 4 sampled views.
SMALL = RobustConfig(candidates=CandidateConfig(num_sampled=4))


@pytest.fixture(scope="module")
def capped(demo):
    """A cap at 60 % of the demo model's Gaussians (the merge threshold must grow to meet it)."""
    return LodConfig(max_gaussians=int(0.6 * demo[1].num_gaussians))


def _query(scene):
    return Query(scene.load_query(), scene.intrinsics, name="query")


def _start(scene):
    from icomma_plugin.pose.convert import perturb_pose

    return perturb_pose(scene.gt_c2w, 10.0, 0.05, np.random.default_rng(3))


def test_auto_leaves_a_small_model_bit_identical(demo, xfeat):
    scene, model, cams = demo
    assert model.num_gaussians <= LOD_AUTO_GAUSSIANS
    init = _start(scene)
    auto = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=False)
    off = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=False, lod=None)
    assert auto.reduced is None and auto.lod_mode == "auto" and off.lod_mode == "off"
    for init_c2w in (init, None):
        torch.manual_seed(0)
        a = auto.localize(_query(scene), init_c2w=init_c2w, gt_c2w=scene.gt_c2w)
        torch.manual_seed(0)
        b = off.localize(_query(scene), init_c2w=init_c2w, gt_c2w=scene.gt_c2w)
        assert np.array_equal(a.c2w, b.c2w)
        assert a.verdict.status == b.verdict.status and a.iterations == b.iterations
        stages = a.details["lod"]["stages"]
        assert all(not s["reduced"] and s["gaussians"] == [model.num_gaussians]
                   for s in stages.values()), stages
        assert a.details["lod"]["reduced_models"] == []


@pytest.mark.parametrize("refine_reduced", [True, False])
def test_a_capped_config_serves_the_geometric_stage_and_candidates(demo, xfeat, capped,
                                                                    refine_reduced):
    import dataclasses

    scene, model, cams = demo
    method = dataclasses.replace(SMALL, refine_reduced=refine_reduced)
    loc = Localizer(model, xfeat, method, cameras=cams, cache_dir=False, lod=capped)
    res = loc.localize(_query(scene), gt_c2w=scene.gt_c2w)  # no start: candidates first
    lod = res.details["lod"]
    stages, full = lod["stages"], model.num_gaussians
    assert lod["mode"] == "config" and lod["full_gaussians"] == full
    # the refinement's finite-difference Hessian is the reduced model's either way
    reduced = ("candidates", "geometric", "hessian") + (("refine",) if refine_reduced else ())
    for name in reduced:
        assert stages[name]["reduced"], name
        assert max(stages[name]["gaussians"]) <= capped.max_gaussians < full, stages
    assert {"refine", "hessian"} <= set(stages) <= {"candidates", "geometric", "hessian",
                                                     "refine", "verify"}
    # the verdict is always the full model's: its check renders it again after a refinement on
    # the reduced model, and reuses the refinement's last render otherwise (or renders again)
    assert ("verify" in stages) if refine_reduced else True
    for name in set(stages) - set(reduced):
        assert not stages[name]["reduced"] and stages[name]["gaussians"] == [full], stages
    # one per working resolution (the demo's 96 px photo is below the candidates' 128 px: one)
    assert lod["build_seconds"] > 0 and len(lod["reduced_models"]) == loc.reduced.builds == 1
    if refine_reduced:  # this cap renders the demo at ~28 dB: refined on it, ~0.45 deg off
        assert res.rot_err_deg < 1.0
    else:
        assert res.verdict.status == "ok" and res.rot_err_deg < 0.5, res.verdict.reason
    again = loc.localize(_query(scene), init_c2w=_start(scene), gt_c2w=scene.gt_c2w)
    assert again.details["lod"]["reduced_models"] == [] and loc.reduced.builds == 1
    assert again.details["lod"]["build_seconds"] == 0.0


@pytest.mark.parametrize("bad", ["fast", 3, True, 0.5, {"max_gaussians": 0}, {"nope": 1}])
def test_bad_lod_values_raise_naming_lod(demo, xfeat, bad):
    scene, model, cams = demo
    with pytest.raises(ValueError, match="lod"):
        Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=False, lod=bad)


def test_lod_accepts_its_spellings():
    assert lod_config("off", 10**7) == ("off", None)
    assert lod_config("auto", LOD_AUTO_GAUSSIANS) == ("auto", None)
    mode, cfg = lod_config("auto", LOD_AUTO_GAUSSIANS + 1)
    assert mode == "auto" and cfg is not None and cfg.max_gaussians is not None
    assert lod_config({"max_gaussians": 5}, 10) == ("config", LodConfig(max_gaussians=5))


def test_working_resolutions_share_rungs():
    a = Intrinsics(200, 200, 300.0, 300.0)
    b = Intrinsics(200, 200, 302.0, 302.0)  # a per-image camera 0.7 % off
    ra, rb = lod_intrinsics(a), lod_intrinsics(b)
    assert ra == rb and 302.0 <= ra.fx < 302.0 * 2 ** 0.25
    assert ra.width % 16 == 0 and ra.width >= 200 * ra.fx / 300.0
    assert lod_intrinsics(ra) == ra
    assert lod_intrinsics(Intrinsics(100, 100, 150.0, 150.0)).fx < ra.fx


def test_a_second_localizer_loads_the_reduced_models_from_disk(demo, xfeat, capped, tmp_path):
    scene, model, cams = demo
    first = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path, lod=capped)
    a = first.localize(_query(scene), gt_c2w=scene.gt_c2w)
    stored = sorted((tmp_path / "candidates").glob("lod-*.pt"))
    assert first.reduced.builds == len(stored) == 1
    second = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path, lod=capped)
    intr = first.reduced.events[0]["intrinsics"]
    m1, m2 = (loc.reduced.model_at(Intrinsics.from_json(intr))[0] for loc in (first, second))
    assert second.reduced.builds == 0 and second.reduced.events[0]["source"] == "disk"
    assert torch.equal(m1.means, m2.means) and torch.equal(m1.opacity_logit, m2.opacity_logit)
    b = second.localize(_query(scene), gt_c2w=scene.gt_c2w)
    assert second.reduced.builds == 0 and second.candidate_builds == 0
    assert np.array_equal(a.c2w, b.c2w)
    other = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=tmp_path,
                      lod=LodConfig(max_gaussians=capped.max_gaussians - 1))
    other.reduced.model_at(Intrinsics.from_json(intr))
    assert other.reduced.builds == 1  # another config: another key


def test_the_hessian_from_the_reduced_model_keeps_the_full_model_precision(demo, xfeat, capped):
    """The default renders only the finite-difference Jacobian from the reduced model.

    Steps are judged on the full model's loss, so a coarse reduction (~28 dB of the full render)
    costs no precision.
    """
    import dataclasses

    from icomma_plugin.localization.refine import RefineConfig
    from icomma_plugin.pose.convert import perturb_pose

    scene, model, cams = demo
    errors = {}
    for reduced in (False, True):
        method = dataclasses.replace(SMALL, refine=RefineConfig(hessian_reduced=reduced))
        loc = Localizer(model, xfeat, method, cameras=cams, cache_dir=False, lod=capped)
        errors[reduced] = []
        for seed in range(3):
            init = perturb_pose(scene.gt_c2w, 10.0, 0.05, np.random.default_rng(seed))
            res = loc.localize(_query(scene), init_c2w=init, gt_c2w=scene.gt_c2w)
            errors[reduced].append(res.rot_err_deg)
            assert ("hessian" in res.details["lod"]["stages"]) == reduced
    assert max(errors[True]) < 0.1 and max(errors[False]) < 0.1, errors


def test_extra_refinement_steps_only_without_a_level_of_detail(demo, xfeat, capped):
    """``RefineConfig.extra_iterations`` are taken only where no reduced model serves."""
    import dataclasses

    from icomma_plugin.localization.refine import RefineConfig

    scene, model, cams = demo
    # every step taking anything off the loss goes on; none is small enough to end the level
    refine = RefineConfig(iterations=(2,), extra_iterations=2, extra_min_gain=0.0,
                          stop_rot_deg=0.0, stop_trans_rel=0.0)
    method = dataclasses.replace(SMALL, refine=refine)
    steps = {}
    for name, lod in (("lod", capped), ("full", None)):
        loc = Localizer(model, xfeat, method, cameras=cams, cache_dir=False, lod=lod)
        res = loc.localize(_query(scene), init_c2w=_start(scene), gt_c2w=scene.gt_c2w)
        steps[name] = [r["accepted"] for r in res.trace if r["stage_name"] == "refine"]
    assert len(steps["lod"]) == 2, steps
    # past its own 2 steps, the level goes on only while a step is accepted (lowers the loss)
    full = steps["full"]
    assert len(full) == 4 or (len(full) in (2, 3) and not full[-1]), steps
    with pytest.raises(ValueError, match="RefineConfig.extra_iterations"):
        RefineConfig(extra_iterations=-1)


def test_near_the_answer_the_geometric_stage_renders_the_full_model_and_the_verdict_reads_it(
        demo, xfeat, capped):
    """``geometric.full_model_within_deg``: the full model near the answer, read by the verdict.

    The rounds after a PnP step under it are the full model's, so the verdict may read the
    stage's last render (``verify_near``); without it every round is the reduced model's and the
    verdict renders the full model again.
    """
    import dataclasses

    scene, model, cams = demo
    full = model.num_gaussians
    runs = {}
    for within in (30.0, None):  # (30: every round after the first, from this start)
        geo = dataclasses.replace(SMALL.geometric, full_model_within_deg=within)
        method = dataclasses.replace(SMALL, geometric=geo)
        loc = Localizer(model, xfeat, method, cameras=cams, cache_dir=False, lod=capped)
        runs[within] = loc.localize(_query(scene), init_c2w=_start(scene), gt_c2w=scene.gt_c2w)
    near, reduced = runs[30.0], runs[None]
    geo_near = near.details["lod"]["stages"]["geometric"]
    geo_reduced = reduced.details["lod"]["stages"]["geometric"]
    assert full in geo_near["gaussians"] and min(geo_near["gaussians"]) < full, geo_near
    assert geo_reduced["gaussians"] == [min(geo_near["gaussians"])], geo_reduced
    assert near.details["verified_on"] == "geometric", near.details
    assert reduced.details["verified_on"] == "final"
    assert "verify" not in near.details["lod"]["stages"]  # no render of the full model again
    for res in (near, reduced):
        assert res.verdict.status == "ok" and res.rot_err_deg < 0.5, res.verdict.reason


def test_an_observation_says_whether_the_reduced_model_rendered_it(demo, xfeat, capped):
    """``Observation.reduced`` (the verdict never reads a reduced render) follows the model."""
    from icomma_plugin.localization.state import LocalizationState

    scene, model, cams = demo
    loc = Localizer(model, xfeat, SMALL, cameras=cams, cache_dir=False, lod=capped)
    state = LocalizationState(model, _query(scene), torch.zeros(3),
                              reduced=loc._reduced_scene(None))
    w2c = np.linalg.inv(scene.gt_c2w)
    with state.serving("geometric", reduced=True):
        small = state.observe(w2c, match=False)
        with state.full_model():
            whole = state.observe(w2c, match=False)
        again = state.observe(w2c, match=False)
    outside = state.observe(w2c, match=False)
    assert small.reduced and again.reduced and not whole.reduced and not outside.reduced
    assert not torch.equal(small.color, whole.color)  # (the cap renders another image)
    seen = state.rendered["geometric"]
    assert sorted(seen["gaussians"]) == sorted({model.num_gaussians, seen["gaussians"][0]})
    assert seen["renders"] == 3
