"""A 3DGS model in the raw (trainable) parametrisation of the graphdeco-inria codebase.

Activations follow `GaussianModel.setup_functions` upstream: opacity = sigmoid(logit),
scale = exp(log-scale), rotation = normalise(quaternion w, x, y, z), colour from SH with
RGB = SH_C0 * f_dc + 0.5 + higher bands.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Optional

import torch

from gaussian_renderer_pose.reference.projection import quat_to_rotmat_unnormalised

SH_C0 = 0.28209479177387814


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [P, 3, 3] of quaternions (w, x, y, z) [P, 4], normalised first.

    The rasterizer's formula, which takes quaternions as stored.
    """
    return quat_to_rotmat_unnormalised(torch.nn.functional.normalize(q, dim=-1))


def num_sh_coeffs(degree: int) -> int:
    """SH coefficients per colour channel at ``degree``: (degree + 1)^2."""
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """The DC coefficient that renders as ``rgb`` (upstream RGB2SH)."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh: torch.Tensor) -> torch.Tensor:
    """The colour of a DC coefficient (upstream SH2RGB)."""
    return sh * SH_C0 + 0.5


class GaussianTensors:
    """What a set of Gaussians says about itself through its ``means`` [P, 3]."""

    means: torch.Tensor

    @property
    def num_gaussians(self) -> int:
        """The number of Gaussians P."""
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        """The device of the tensors."""
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the tensors."""
        return self.means.dtype


@dataclass
class GaussianModel(GaussianTensors):
    """Raw Gaussian parameters; P Gaussians, SH degree D (K = (D+1)^2 - 1 rest coefficients)."""

    means: torch.Tensor  # [P, 3] world units
    sh_dc: torch.Tensor  # [P, 1, 3]
    sh_rest: torch.Tensor  # [P, K, 3]
    opacity_logit: torch.Tensor  # [P, 1]
    scale_log: torch.Tensor  # [P, 3]
    quat: torch.Tensor  # [P, 4] (w, x, y, z), not necessarily normalised
    sh_degree: int

    def __post_init__(self):
        P = self.means.shape[0] if self.means.ndim == 2 else -1
        K = num_sh_coeffs(self.sh_degree) - 1 if 0 <= self.sh_degree <= 3 else None
        expected = {
            "means": (P, 3),
            "sh_dc": (P, 1, 3),
            "sh_rest": (P, K, 3),
            "opacity_logit": (P, 1),
            "scale_log": (P, 3),
            "quat": (P, 4),
        }
        if K is None:
            raise ValueError(f"GaussianModel.sh_degree must be 0..3, got {self.sh_degree!r}")
        for name, shape in expected.items():
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor):
                raise ValueError(
                    f"GaussianModel.{name} must be a torch.Tensor, got {type(t).__name__}"
                )
            if tuple(t.shape) != shape:
                raise ValueError(
                    f"GaussianModel.{name} must have shape {list(shape)}, got {list(t.shape)}"
                )

    def opacities(self) -> torch.Tensor:
        """Opacities [P, 1] in (0, 1) (sigmoid of the logits)."""
        return torch.sigmoid(self.opacity_logit)

    def scales(self) -> torch.Tensor:
        """Scales [P, 3] (exp of the log scales)."""
        return torch.exp(self.scale_log)

    def rotations(self) -> torch.Tensor:
        """Unit quaternions [P, 4] (w, x, y, z)."""
        return torch.nn.functional.normalize(self.quat, dim=-1)

    def shs(self) -> torch.Tensor:
        """[P, (D+1)^2, 3] SH coefficients, DC first (the rasterizer's `shs` input)."""
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def tensors(self) -> dict:
        """The tensor fields by name (every field but ``sh_degree``)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "sh_degree"}

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> "GaussianModel":
        """A copy with every tensor moved to ``device`` / cast to ``dtype``."""
        return GaussianModel(
            **{k: v.to(device=device, dtype=dtype) for k, v in self.tensors().items()},
            sh_degree=self.sh_degree,
        )

    def detach(self) -> "GaussianModel":
        """The same tensors, detached from autograd."""
        out = GaussianModel(
            **{k: v.detach() for k, v in self.tensors().items()}, sh_degree=self.sh_degree
        )
        if "_zero_sh" in self.__dict__:  # same storage and version counter: the scan holds
            out.__dict__["_zero_sh"] = self.__dict__["_zero_sh"]
        return out

    def index(self, mask: torch.Tensor) -> "GaussianModel":
        """Subset by boolean mask or index tensor over the P Gaussians."""
        return GaussianModel(
            **{k: v[mask] for k, v in self.tensors().items()}, sh_degree=self.sh_degree
        )

    @staticmethod
    def concatenate(models: "list[GaussianModel]") -> "GaussianModel":
        """One model with the Gaussians of all ``models``, at the highest SH degree among them.

        Raises:
            ValueError: an empty list.
        """
        if not models:
            raise ValueError("models must be a non-empty list")
        degree = max(m.sh_degree for m in models)
        padded = [m.with_sh_degree(degree) for m in models]
        return GaussianModel(
            **{k: torch.cat([getattr(m, k) for m in padded], 0) for k in padded[0].tensors()},
            sh_degree=degree,
        )

    def with_sh_degree(self, degree: int) -> "GaussianModel":
        """Same model with SH truncated or zero-padded to `degree`."""
        K = num_sh_coeffs(degree) - 1
        rest = self.sh_rest[:, :K]
        if rest.shape[1] < K:
            pad = rest.new_zeros(rest.shape[0], K - rest.shape[1], 3)
            rest = torch.cat([rest, pad], 1)
        return GaussianModel(
            self.means, self.sh_dc, rest, self.opacity_logit, self.scale_log, self.quat, degree
        )

    def without_zero_sh(self) -> "GaussianModel":
        """This model, or the same at SH degree 0 when its higher bands are all zero.

        Such a model renders the same image (and gradients) at degree 0, faster. The scan of
        ``sh_rest`` is remembered on this object until ``sh_rest`` changes (its version counter,
        which in-place changes and those of tensors it was detached from advance), so a caller
        that asks once a localization does not scan the model each time.
        """
        if self.sh_degree == 0:
            return self
        try:
            key = (self.sh_rest.data_ptr(), self.sh_rest._version)
        except RuntimeError:  # an inference-mode tensor has no version counter: scan each time
            key = None
        known = self.__dict__.get("_zero_sh")
        if key is None or known is None or known[0] != key:
            known = (key, not bool(self.sh_rest.any()))
            self.__dict__["_zero_sh"] = known
        return self.with_sh_degree(0) if known[1] else self

    @classmethod
    def empty(cls, sh_degree: int = 3, dtype=torch.float32, device=None) -> "GaussianModel":
        """A model with no Gaussians."""
        K = num_sh_coeffs(sh_degree) - 1
        z = lambda *s: torch.zeros(*s, dtype=dtype, device=device)  # noqa: E731
        return cls(z(0, 3), z(0, 1, 3), z(0, K, 3), z(0, 1), z(0, 3), z(0, 4), sh_degree)
