"""icomma_plugin.fit.distillation: a split model fitted back to its parent's image."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.fit.distillation import distill
from icomma_plugin.fit.losses import psnr
from icomma_plugin.gaussians import GaussianModel
from icomma_plugin.lod import split_gaussians
from icomma_plugin.pose.convert import look_at_c2w
from icomma_plugin.render import render

INTR = Intrinsics(40, 40, 48.0, 48.0)


def _faint_model(P: int = 300, degree: int = 0) -> GaussianModel:
    """Faint Gaussians (opacity 0.05-0.3): a stack of 40 copies of each loses its tails."""
    g = torch.Generator().manual_seed(0)
    op = 0.05 + 0.25 * torch.rand(P, 1, generator=g)
    K = (degree + 1) ** 2 - 1
    return GaussianModel((torch.rand(P, 3, generator=g) - 0.5) * 1.6,
                         torch.rand(P, 1, 3, generator=g) * 2 - 0.5, torch.zeros(P, K, 3),
                         torch.log(op / (1 - op)),
                         torch.log(0.05 + 0.1 * torch.rand(P, 3, generator=g)),
                         torch.nn.functional.normalize(torch.randn(P, 4, generator=g), dim=-1),
                         degree)


def _w2c(azimuth: float, height: float) -> torch.Tensor:
    eye = np.array([3.5 * np.cos(azimuth), 3.5 * np.sin(azimuth), height])
    c2w = look_at_c2w(eye, np.zeros(3), up=(0.0, 0.0, 1.0))
    return torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32)


def _psnr_vs(model, reference, w2cs):
    with torch.no_grad():
        return [psnr(render(model, INTR, w, torch.zeros(3)).color,
                     render(reference, INTR, w, torch.zeros(3)).color.clamp(0, 1)) for w in w2cs]


def test_distillation_brings_back_the_parents_image_on_other_views():
    model = _faint_model()
    split = split_gaussians(model, factor=40)
    train = [(INTR, _w2c(a, h)) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)
             for h in (-1.0, 1.5)]
    held_out = [_w2c(a, 0.3) for a in (0.3, 2.0, 4.1)]  # between the fitted views
    before = _psnr_vs(split, model, held_out)
    fitted = distill(split, model, train, steps=60)
    after = _psnr_vs(fitted, model, held_out)
    assert fitted.num_gaussians == split.num_gaussians == 40 * model.num_gaussians
    assert max(before) < 20.0  # the faint stacks lost their tails ...
    assert min(a - b for a, b in zip(after, before)) > 8.0  # ... and the fit gives them back
    assert distill(split, model, train, steps=0) is split


def test_distill_bad_arguments():
    model = _faint_model(20)
    cams = [(INTR, _w2c(0.0, 1.0))]
    with pytest.raises(ValueError, match="cameras"):
        distill(model, model, [], steps=5)
    with pytest.raises(ValueError, match="steps"):
        distill(model, model, cams, steps=-1)
    with pytest.raises(ValueError, match="SH degree"):
        distill(_faint_model(20, degree=1), model, cams, steps=5)
