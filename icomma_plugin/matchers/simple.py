"""The `none` and `fake` matchers.

`none`: no matches (the localizer then uses the photometric term only); `fake`: deterministic
correspondences from a known mapping, for tests of the optimiser.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from .base import Matcher, Matches, check_image
from ..checks import check_int, check_real


class NoneMatcher(Matcher):
    """Returns zero matches, also with `differentiable=True` (nothing to differentiate)."""

    name = "none"
    supports_image_gradient = False

    def match(self, image0, image1, differentiable: bool = False) -> Matches:
        """No matches (the images are still checked)."""
        check_image(image0, "image0")
        check_image(image1, "image1")
        return Matches.empty(image0.device, image0.dtype)

    def _match(self, image0, image1) -> Matches:
        return Matches.empty(image0.device)


def _as_tensor(value, name: str, shape) -> torch.Tensor:
    try:
        t = torch.as_tensor(value, dtype=torch.float64)
    except Exception as exc:  # noqa: BLE001 - re-raised as a ValueError naming the argument
        raise ValueError(
            f"{name} must be array-like of shape {shape}, got {type(value).__name__}"
        ) from exc
    ok = t.ndim == len(shape) and all(s is None or t.shape[i] == s for i, s in enumerate(shape))
    if not ok:
        raise ValueError(f"{name} must have shape {tuple('N' if s is None else s for s in shape)}, "
                         f"got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must be finite")
    return t


class FakeMatcher(Matcher):
    """Deterministic matches from known correspondences or a known mapping (image1 -> image0).

    Exactly one source (or none, meaning the identity mapping):
        kpts0, kpts1: fixed correspondences [N, 2] (image0 = render, image1 = query pixels).
        homography: 3x3 array mapping image1 pixels to image0 pixels (integer-centre convention).
        mapping: callable taking query pixels [N, 2] (float64 tensor) and returning render pixels
            [N, 2]; it may close over state that a test changes (e.g. the current pose).
    With a mapping, the query keypoints are a regular grid of step `grid_step` px on image1, at
    least `border` px from its edges; correspondences landing outside image0 (less `border`) are
    dropped.

    Perturbations (deterministic: a generator seeded with `seed` at every call):
        noise: Gaussian noise (sigma, px) added to kpts0.
        outlier_fraction: that fraction of kpts0 replaced by uniform positions in image0.
    confidence: the confidence of every match.
    """

    name = "fake"

    def __init__(
        self,
        kpts0=None,
        kpts1=None,
        homography=None,
        mapping: Optional[Callable] = None,
        grid_step: int = 16,
        border: int = 4,
        noise: float = 0.0,
        outlier_fraction: float = 0.0,
        seed: int = 0,
        confidence: float = 1.0,
        **kwargs,
    ):
        kwargs.setdefault("min_detect_side", 0)  # its correspondences are in the images' own pixels
        super().__init__(**kwargs)
        given = [
            kpts0 is not None or kpts1 is not None,
            homography is not None,
            mapping is not None,
        ]
        if sum(given) > 1:
            raise ValueError("give at most one of (kpts0, kpts1), homography and mapping")
        self.kpts0 = self.kpts1 = self.homography = None
        if given[0]:
            if kpts0 is None or kpts1 is None:
                raise ValueError("kpts0 and kpts1 must be given together")
            self.kpts0 = _as_tensor(kpts0, "kpts0", (None, 2))
            self.kpts1 = _as_tensor(kpts1, "kpts1", (None, 2))
            if self.kpts0.shape[0] != self.kpts1.shape[0]:
                raise ValueError(f"kpts0 and kpts1 must have the same length, got "
                                 f"{self.kpts0.shape[0]} and {self.kpts1.shape[0]}")
        if homography is not None:
            self.homography = _as_tensor(homography, "homography", (3, 3))
        if mapping is not None and not callable(mapping):
            raise ValueError(f"mapping must be callable, got {type(mapping).__name__}")
        self.mapping = mapping
        for nm, v, lo in (("grid_step", grid_step, 1), ("border", border, 0), ("seed", seed, 0)):
            check_int(v, nm, lo)
        check_real(noise, "noise", 0.0)
        check_real(outlier_fraction, "outlier_fraction", 0.0, 1.0)
        self.grid_step, self.border, self.seed = grid_step, border, seed
        self.noise, self.outlier_fraction, self.confidence = (
            float(noise),
            float(outlier_fraction),
            float(confidence),
        )

    def _correspondences(self, h0, w0, h1, w1):
        if self.kpts0 is not None:
            return self.kpts0.clone(), self.kpts1.clone()
        b, s = self.border, self.grid_step
        xs = torch.arange(b, w1 - b, s, dtype=torch.float64)
        ys = torch.arange(b, h1 - b, s, dtype=torch.float64)
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")
        k1 = torch.stack([xx.reshape(-1), yy.reshape(-1)], -1)
        if self.homography is not None:
            hom = torch.cat([k1, torch.ones_like(k1[:, :1])], -1) @ self.homography.T
            k0 = hom[:, :2] / hom[:, 2:3]
        elif self.mapping is not None:
            k0 = torch.as_tensor(self.mapping(k1.clone()), dtype=torch.float64).detach().cpu()
            if k0.shape != k1.shape:
                raise ValueError(
                    f"mapping must return an [N, 2] array for [N, 2] input, got {tuple(k0.shape)}"
                )
        else:
            k0 = k1.clone()
        ok = torch.isfinite(k0).all(-1) & (k0[:, 0] >= b) & (k0[:, 0] <= w0 - 1 - b) \
            & (k0[:, 1] >= b) & (k0[:, 1] <= h0 - 1 - b)
        return k0[ok], k1[ok]

    def _match(self, image0, image1) -> Matches:
        h0, w0 = image0.shape[1:]
        h1, w1 = image1.shape[1:]
        k0, k1 = self._correspondences(h0, w0, h1, w1)
        n = k0.shape[0]
        gen = torch.Generator().manual_seed(self.seed)
        if self.noise > 0 and n:
            k0 = k0 + self.noise * torch.randn(k0.shape, generator=gen, dtype=torch.float64)
        n_out = int(round(self.outlier_fraction * n))
        if n_out:
            idx = torch.randperm(n, generator=gen)[:n_out]
            k0[idx] = torch.rand((n_out, 2), generator=gen, dtype=torch.float64) \
                * torch.tensor([w0 - 1, h0 - 1], dtype=torch.float64)
        dev = image0.device
        return Matches(k0.float().to(dev), k1.float().to(dev),
                       torch.full((n,), self.confidence, dtype=torch.float32, device=dev))
