"""The CUDA path of everything around the rasterizer, checked on a CPU (tests/helpers/fake_cuda.py).

Each test runs a whole job with the model "on the GPU" and fails on the first operation a CUDA
build would refuse (a GPU tensor meeting a CPU one, ``.numpy()`` of a GPU tensor, a CUDA
generator drawing a CPU tensor). The first real GPU run of the pipeline (tools/gpu_check.sh) hit
such operations in the refinement, the fitter's evaluation and the demo scene; these tests find
them where CI runs. The emulator itself is tested first: it must flag what a GPU refuses and
pass what a GPU allows.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.helpers.fake_cuda import fake_cuda, report
from tests.tools.test_audit import audit_tool, capture  # noqa: F401 - capture is a fixture

pytestmark = [pytest.mark.usefixtures("native_backend"),
              pytest.mark.filterwarnings("ignore::UserWarning")]


# ----------------------------------------------------------------------------- the emulator

def test_the_emulator_flags_what_a_gpu_refuses(monkeypatch):
    with fake_cuda(monkeypatch) as mode:
        a = torch.ones(4, 3, device="cuda")
        assert a.device.type == "cuda" and a.is_cuda
        _ = a + torch.ones(4, 3)  # 1: a CPU tensor of 2 dims
        _ = (a * 2).numpy()  # 2: numpy of a GPU tensor
        b = torch.zeros(6, 6, dtype=torch.float64).to("cuda") @ torch.eye(6, dtype=torch.float64)
        assert b.device.type == "cuda"  # 3: (the product's result is on the GPU)
        gen = torch.Generator(device="cuda")
        _ = torch.rand(3, generator=gen)  # 4: a CUDA generator, a CPU tensor
    assert len(mode.violations) == 4, report(mode)


def test_the_emulator_passes_what_a_gpu_allows(monkeypatch):
    with fake_cuda(monkeypatch) as mode:
        a = torch.arange(12.0, device="cuda").reshape(4, 3)
        _ = a * torch.tensor(2.0)  # a 0-dim CPU tensor is a scalar
        _ = a[torch.tensor([0, 2])]  # CPU indices
        c = a.cpu()
        assert c.device.type == "cpu" and c.numpy().shape == (4, 3)
        d = torch.zeros(3, device=a.device) + a[0]  # a factory on the tensor's device
        p = torch.nn.Parameter(a.clone())
        (p.sum() * 2).backward()
        assert p.grad.device.type == "cuda" and d.device.type == "cuda"
        gen = torch.Generator(device="cuda")
        _ = torch.rand(3, generator=gen, device="cuda") + a[0]
    assert not mode.violations, report(mode)


# ----------------------------------------------------------------------------- the localizer

def _query(scene):
    from icomma_plugin.localization.types import Query

    return Query(scene.load_query(), scene.intrinsics, name="query")


@pytest.mark.parametrize("start", ["perturbed", "none"])
def test_the_default_localizer_on_a_gpu_model(demo, xfeat, monkeypatch, tmp_path, start):
    from icomma_plugin.localization.candidates import CandidateConfig
    from icomma_plugin.localization.localizer import Localizer
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.pose.convert import perturb_pose

    scene, model, cams = demo
    init = perturb_pose(scene.gt_c2w, 25.0, 0.1, generator=3) if start == "perturbed" else None
    cfg = RobustConfig(candidates=CandidateConfig(num_sampled=4))
    with fake_cuda(monkeypatch) as mode:
        loc = Localizer(model, xfeat, cfg, cameras=cams, backend="cuda", cache_dir=tmp_path)
        assert loc.model.means.device.type == "cuda"  # backend="cuda" moves a CPU model
        res = loc.localize(_query(scene), init_c2w=init, gt_c2w=scene.gt_c2w)
        if start == "none":  # and a second localizer reads the candidate index from disk
            again = Localizer(model, xfeat, cfg, cameras=cams, backend="cuda", cache_dir=tmp_path)
            res2 = again.localize(_query(scene), gt_c2w=scene.gt_c2w)
            assert again.candidate_builds == 0 and res2.rot_err_deg < 0.1
    assert not mode.violations, report(mode)
    assert res.verdict.status == "ok" and res.rot_err_deg < 0.1, res.verdict.reason


def test_the_papers_method_on_a_gpu_model(demo, xfeat, monkeypatch):
    from icomma_plugin.localization.icomma import LocalizerConfig
    from icomma_plugin.localization.localizer import Localizer
    from icomma_plugin.pose.convert import perturb_pose

    scene, model, cams = demo
    init = perturb_pose(scene.gt_c2w, 8.0, 0.05, generator=5)
    with fake_cuda(monkeypatch) as mode:
        loc = Localizer(model, xfeat, LocalizerConfig(max_iterations=40), cameras=cams,
                        backend="cuda", cache_dir=False)
        res = loc.localize(_query(scene), init_c2w=init, gt_c2w=scene.gt_c2w)
    assert not mode.violations, report(mode)
    assert res.rot_err_deg < res.init_rot_err_deg


# ----------------------------------------------------------------------------- the fitter

def test_a_fit_and_its_evaluation_on_a_gpu(monkeypatch, tmp_path):
    from icomma_plugin.fit import FitConfig, evaluate_model_folder, fit_scene
    from tests.icomma_plugin.test_fit import (_gt_model, _render_views, _ring_poses,
                                              _write_blender_dataset)

    rendered = _render_views(_gt_model(), _ring_poses(8), size=32)
    _write_blender_dataset(tmp_path / "data", rendered[:6], rendered[6:])
    cfg = FitConfig.scaled_schedule(60, sh_degree=1, num_random_points=300, backend="cuda")
    with fake_cuda(monkeypatch) as mode:
        res = fit_scene(tmp_path / "data", tmp_path / "m", cfg, white_background=False,
                        device="cuda")
        assert res.fit.model.means.device.type == "cuda"
        ev = evaluate_model_folder(tmp_path / "m", backend="cuda", grid=tmp_path / "grid.png")
    assert not mode.violations, report(mode)
    assert np.isfinite(ev["test_psnr"]) and Path(ev["grid"]).is_file()


# ----------------------------------------------------------------------------- the tools

def test_the_localize_tool_with_renderer_cuda(small_demo, monkeypatch, tmp_path):
    from tests.helpers.tools import compose, localize_tool

    tool = localize_tool()
    runs = {"robust": [], "icomma": ["optimizer=icomma", "optimizer.max_iterations=4",
                                     "output.gif=true", "output.gif_every=2"]}
    with fake_cuda(monkeypatch) as mode:
        for name, extra in runs.items():
            cfg = compose([f"data.path={small_demo}", "data.width=64", "data.height=64",
                           "renderer=cuda", "output.progress=false", *extra])
            tool.run(cfg, tmp_path / name)
    assert not mode.violations, report(mode)
    for name in runs:
        doc = json.loads((tmp_path / name / "result.json").read_text())
        assert np.asarray(doc["c2w"]).shape == (4, 4)
        assert (tmp_path / name / "overlay_final.png").is_file()


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """(model folder, a folder of 3 photos along a path around it, their true poses' JSON)."""
    from tests.helpers.demo import demo_model, orbit_c2w, save_photos

    root = tmp_path_factory.mktemp("frames")
    s, model = demo_model(root / "model", 80)
    folder = root / "frames"
    save_photos(model, s.intrinsics,
                {f"frame{i}.png": orbit_c2w(0.4 + 0.05 * i, 2.0) for i in range(3)},
                folder, root / "gt.json")
    return s.path, folder, root / "gt.json"


@pytest.mark.parametrize("kind", ["sequence", "queries"])
def test_tracking_and_batches_with_renderer_cuda(frames, monkeypatch, tmp_path, kind):
    from tests.helpers.tools import compose, localize_tool

    model, folder, gt = frames
    out = tmp_path / "out"
    extra = (["output.video=false"] if kind == "sequence" else
             ["output.photo_folders=true", "output.export=[cameras_json,colmap,nerfstudio]"])
    with fake_cuda(monkeypatch) as mode:
        doc = localize_tool().run(compose([
            "data=model_folder", f"data.model_path={model}", "data.intrinsics.camera=ring_000",
            f"data.gt.poses_file={gt}", f"data.{kind}={folder}", "data.init=none",
            f"output.dir={out}", "output.progress=false", "renderer=cuda", *extra]), out)
    assert not mode.violations, report(mode)
    assert doc["done"] == 3 and all(r["status"] != "failed" for r in doc["photos"]), doc["photos"]


def test_a_benchmark_protocol_with_backend_cuda(monkeypatch):
    from icomma_plugin.benchmark import ProtocolSpec, run_protocol, synthetic_scene
    from icomma_plugin.localization.icomma import LocalizerConfig
    from icomma_plugin.matchers import make_matcher

    scene = synthetic_scene(num_gaussians=400, width=64, height=64, num_queries=1)
    spec = ProtocolSpec.from_dict({
        "name": "t", "kind": "curves", "methods": ["robust", "icomma"], "num_queries": 1,
        "poses_per_query": 1, "max_iterations": 3,
        "intervals": [{"label": "r10-20", "rot_deg": [10, 20], "trans": [0, 0.05]}]})
    with fake_cuda(monkeypatch) as mode:
        recs = run_protocol(scene, spec, LocalizerConfig(), make_matcher("xfeat"), backend="cuda")
    assert not mode.violations, report(mode)
    assert len(recs) == 2 and all(np.isfinite(r["rot_err_deg"]) for r in recs)


@pytest.mark.parametrize("start", ["perturbed", "none"])
def test_photo_anchors_with_a_gpu_model(demo, xfeat, monkeypatch, start):
    from icomma_plugin.localization.anchors import SourcePhoto
    from icomma_plugin.localization.candidates import CandidateConfig
    from icomma_plugin.localization.localizer import Localizer
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.pose.convert import perturb_pose
    from tests.icomma_plugin.test_anchors import RenderedPhoto

    scene, model, cams = demo
    photos = [SourcePhoto(c.img_name, c.c2w, scene.intrinsics,
                          RenderedPhoto(model, scene.intrinsics, c.c2w, c.img_name))
              for c in cams]
    init = None
    if start == "perturbed":
        init = perturb_pose(scene.gt_c2w, 20.0, 0.1, 3, pivot=scene.scene_centre)
    cfg = RobustConfig(candidates=CandidateConfig(num_sampled=4))
    with fake_cuda(monkeypatch) as mode:
        loc = Localizer(model, xfeat, cfg, cameras=cams, photos=photos, backend="cuda",
                        cache_dir=False)
        res = loc.localize(_query(scene), init, scene.gt_c2w)
    assert not mode.violations, report(mode)
    assert res.rot_err_deg < 0.1 and res.verdict.status == "ok", res.verdict.reason


def test_an_audit_with_renderer_cuda(capture, monkeypatch, tmp_path):  # noqa: F811
    from tests.helpers.tools import compose

    out = tmp_path / "audit"
    cfg = compose([f"model_path={capture['model']}", "sample=3", "starts=1", "threads=1",
                   f"output.dir={out}", "output.progress=false", f"cache.dir={tmp_path}",
                   "renderer=cuda"], name="audit")
    with fake_cuda(monkeypatch) as mode:
        doc = audit_tool().run(cfg, out)
    assert not mode.violations, report(mode)
    assert (out / "audit.json").is_file() and doc


def test_cuda_where_it_cannot_run_is_refused_at_once_naming_the_argument(demo, xfeat, tmp_path):
    from gaussian_renderer_pose import available_backends
    from icomma_plugin.fit import FitConfig, evaluate_model_folder, fit_scene
    from icomma_plugin.localization.localizer import Localizer

    if available_backends()["cuda"] is None:
        pytest.skip("the CUDA backend runs here")
    scene, model, cams = demo
    with pytest.raises(ValueError, match=r"backend='cuda' cannot run here: .*use auto, or cpu"):
        Localizer(model, xfeat, cameras=cams, backend="cuda")
    with pytest.raises(ValueError, match=r"FitConfig.backend='cuda' cannot run here"):
        fit_scene(tmp_path / "nowhere", tmp_path / "m", FitConfig(iterations=1, backend="cuda"))
    with pytest.raises(ValueError, match=r"device='cuda' cannot run here"):
        fit_scene(tmp_path / "nowhere", tmp_path / "m", FitConfig(iterations=1), device="cuda")
    with pytest.raises(ValueError, match=r"backend='cuda' cannot run here"):
        evaluate_model_folder(scene.path, backend="cuda")


def test_the_tools_say_when_a_gpu_they_do_not_use_is_here(monkeypatch, caplog):
    import logging

    import gaussian_renderer_pose
    from tools import _common

    monkeypatch.setattr(gaussian_renderer_pose, "available_backends",
                        lambda: {"reference": None, "cpu": None, "cuda": None})
    with caplog.at_level(logging.INFO, logger="icomma"):
        assert _common.check_backend("auto") == "auto"
        assert _common.check_backend("cpu") == "cpu"
    hints = [r for r in caplog.records if "renderer=cuda runs on the GPU" in r.getMessage()]
    assert len(hints) == 1
