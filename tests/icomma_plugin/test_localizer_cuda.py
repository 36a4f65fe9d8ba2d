"""The whole pipeline on the GPU: the default localizer, the paper's method and the fitter.

Runs where ``torch.cuda.is_available()`` and the extension has CUDA (the ``cuda_backend`` fixture
skips with the reason elsewhere, as in CI). The kernels themselves are checked against the CPU
kernel and the float64 reference in tests/gaussian_renderer_pose/test_cuda.py; these tests check
that every stage around them (matcher, PnP, refinement, verdict, candidates, fitter) runs with the
model on the GPU and lands where the CPU run lands.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from icomma_plugin.localization.candidates import CandidateConfig
from icomma_plugin.localization.localizer import Localizer
from icomma_plugin.localization.robust import RobustConfig
from icomma_plugin.localization.types import Query
from icomma_plugin.pose.convert import perturb_pose

pytestmark = [pytest.mark.cuda, pytest.mark.usefixtures("cuda_backend")]

SMALL = RobustConfig(candidates=CandidateConfig(num_sampled=4))


def _rotation_between_deg(a_c2w: np.ndarray, b_c2w: np.ndarray) -> float:
    r = a_c2w[:3, :3].T @ b_c2w[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


@pytest.fixture
def on_both(demo, xfeat, cuda_backend):
    """(scene, CPU localizer, CUDA localizer) of the demo scene, no disk cache."""
    scene, model, cams = demo
    cpu = Localizer(model, xfeat, SMALL, cameras=cams, backend="cpu", cache_dir=False)
    gpu = Localizer(model.to("cuda"), xfeat, SMALL, cameras=cams, backend="cuda", cache_dir=False)
    return scene, cpu, gpu


@pytest.mark.parametrize("start", ["perturbed", "none"])
def test_the_default_localizer_on_the_gpu_lands_where_the_cpu_one_does(on_both, start):
    scene, cpu, gpu = on_both
    init = None
    if start == "perturbed":
        init = perturb_pose(scene.gt_c2w, 25.0, 0.1, generator=3)
    query = Query(scene.load_query(), scene.intrinsics, name="query")
    a = cpu.localize(query, init_c2w=init, gt_c2w=scene.gt_c2w)
    b = gpu.localize(Query(scene.load_query(), scene.intrinsics, name="query"), init_c2w=init,
                     gt_c2w=scene.gt_c2w)
    assert b.verdict.status == "ok", b.verdict.reason
    assert b.rot_err_deg < 0.1 and a.rot_err_deg < 0.1
    c2w_a = np.asarray(a.c2w, dtype=np.float64)
    c2w_b = np.asarray(b.c2w, dtype=np.float64)
    assert _rotation_between_deg(c2w_a, c2w_b) < 0.05
    assert np.linalg.norm(c2w_a[:3, 3] - c2w_b[:3, 3]) < 0.01


def test_the_papers_method_on_the_gpu(demo, xfeat):
    from icomma_plugin.localization.icomma import LocalizerConfig

    scene, model, cams = demo
    cfg = LocalizerConfig(max_iterations=120)
    loc = Localizer(model.to("cuda"), xfeat, cfg, cameras=cams, backend="cuda", cache_dir=False)
    init = perturb_pose(scene.gt_c2w, 8.0, 0.05, generator=5)
    res = loc.localize(Query(scene.load_query(), scene.intrinsics, name="query"), init_c2w=init,
                       gt_c2w=scene.gt_c2w)
    assert res.rot_err_deg < 1.0, res.rot_err_deg


def test_a_fit_on_the_gpu_writes_a_model_that_renders_the_same_on_the_cpu(tmp_path):
    from icomma_plugin.camera import Intrinsics
    from icomma_plugin.fit import FitConfig, fit_scene
    from icomma_plugin.io.model_folder import load_model_folder
    from icomma_plugin.render import render
    from tests.icomma_plugin.test_fit import (_gt_model, _render_views, _ring_poses,
                                              _write_blender_dataset)

    src = tmp_path / "data"
    rendered = _render_views(_gt_model(), _ring_poses(8), size=32)
    _write_blender_dataset(src, rendered[:6], rendered[6:])
    cfg = FitConfig.scaled_schedule(80, sh_degree=1, num_random_points=300, backend="cuda")
    res = fit_scene(src, tmp_path / "m", cfg, white_background=False, device="cuda")
    assert res.fit.model.means.device.type == "cuda"
    folder = load_model_folder(tmp_path / "m")
    assert folder.model.num_gaussians == res.fit.num_gaussians
    cam = folder.cameras[0]
    intr = Intrinsics(cam.width, cam.height, cam.fx, cam.fy)
    w2c = torch.as_tensor(cam.w2c, dtype=torch.float32)
    a = render(folder.model, intr, w2c, torch.zeros(3), backend="cpu").color
    b = render(folder.model.to("cuda"), intr, w2c.cuda(), torch.zeros(3, device="cuda"),
               backend="cuda").color.cpu()
    assert torch.isfinite(a).all() and a.abs().sum() > 0
    assert (a - b).abs().max() < 1e-3
