"""Random Gaussian models for the file-format tests (values, not a picture)."""
from __future__ import annotations

import torch

from icomma_plugin.gaussians import GaussianModel


def random_gaussians(P: int, degree: int = 3, seed: int = 0) -> GaussianModel:
    """``P`` Gaussians of SH degree ``degree`` with standard normal raw parameters."""
    g = torch.Generator().manual_seed(seed)
    K = (degree + 1) ** 2 - 1
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return GaussianModel(r(P, 3), r(P, 1, 3), r(P, K, 3), r(P, 1), r(P, 3), r(P, 4), degree)
