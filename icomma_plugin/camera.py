"""Pinhole intrinsics in the 3DGS pixel convention (pixel centres at integers, centre (W-1)/2)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Dict, Optional

import torch
from .checks import check_int, check_real


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera. `cx, cy` None means the image centre ((W-1)/2, (H-1)/2), as 3DGS assumes."""

    width: int
    height: int
    fx: float
    fy: float
    cx: Optional[float] = None
    cy: Optional[float] = None

    def __post_init__(self):
        for name in ("width", "height"):
            check_int(getattr(self, name), f"Intrinsics.{name}", 1)
        for name in ("fx", "fy"):
            check_real(getattr(self, name), f"Intrinsics.{name}", 0.0, lo_open=True)
        for name in ("cx", "cy"):
            check_real(getattr(self, name), f"Intrinsics.{name}", optional=True)

    @property
    def cx_px(self) -> float:
        """Principal point x [px]: ``cx``, or the image centre ``(W - 1) / 2`` when None."""
        return (self.width - 1) / 2.0 if self.cx is None else float(self.cx)

    @property
    def cy_px(self) -> float:
        """Principal point y [px]: ``cy``, or the image centre ``(H - 1) / 2`` when None."""
        return (self.height - 1) / 2.0 if self.cy is None else float(self.cy)

    @property
    def fov_x(self) -> float:
        """Horizontal field of view [rad]."""
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    @property
    def fov_y(self) -> float:
        """Vertical field of view [rad]."""
        return 2.0 * math.atan(self.height / (2.0 * self.fy))

    @classmethod
    def from_fov(
        cls, width: int, height: int, fov_x: float, fov_y: Optional[float] = None
    ) -> "Intrinsics":
        """From the horizontal (and optionally vertical) field of view in radians.

        Square pixels when ``fov_y`` is not given.
        """
        fx = width / (2.0 * math.tan(fov_x / 2.0))
        fy = fx if fov_y is None else height / (2.0 * math.tan(fov_y / 2.0))
        return cls(width, height, fx, fy)

    def scaled(self, scale: float) -> "Intrinsics":
        """Intrinsics of the image resized by `scale`.

        Sizes are rounded; the focal lengths are scaled by the real ratio.
        """
        return self.resized_to(max(1, int(round(self.width * scale))),
                               max(1, int(round(self.height * scale))))

    def with_focal_scale(self, scale: float) -> "Intrinsics":
        """The same image seen through both focal lengths times ``scale`` (principal point kept)."""
        return self if scale == 1.0 else replace(self, fx=self.fx * scale, fy=self.fy * scale)

    def centred(self) -> "Intrinsics":
        """The same camera with its principal point at the image centre (upstream 3DGS's)."""
        return self if self.cx is None and self.cy is None else replace(self, cx=None, cy=None)

    def resized_to(self, width: int, height: int) -> "Intrinsics":
        """Intrinsics of the image resized to ``width x height`` (each axis by its own ratio).

        Pixel centres sit at integers, so a principal point scales about the image's corner
        (-0.5, -0.5).
        """
        sx, sy = width / self.width, height / self.height
        cx = None if self.cx is None else (self.cx + 0.5) * sx - 0.5
        cy = None if self.cy is None else (self.cy + 0.5) * sy - 0.5
        return replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                       cx=cx, cy=cy)

    def scale_to_side(self, side: int, enlarge: bool = False) -> float:
        """The scale that brings the longer image side to ``side`` px.

        Never above 1 unless ``enlarge``: the one rule of the project for a working resolution
        given as a side length.
        """
        s = float(side) / max(self.width, self.height)
        return s if enlarge else min(1.0, s)

    def to_json(self) -> Dict[str, Any]:
        """The one JSON encoding of intrinsics: size, focal lengths and the principal point [px].

        The principal point is always written out (``cx_px``, ``cy_px``), so a reader needs no
        convention for a missing one.
        """
        return {"width": self.width, "height": self.height, "fx": float(self.fx),
                "fy": float(self.fy), "cx": self.cx_px, "cy": self.cy_px}

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "Intrinsics":
        """Intrinsics from :meth:`to_json`'s mapping (``cx``/``cy`` may be absent or None)."""
        if not isinstance(d, dict):
            raise ValueError(f"intrinsics must be a mapping, got {type(d).__name__}")
        missing = [k for k in ("width", "height", "fx", "fy") if k not in d]
        if missing:
            raise ValueError(f"intrinsics lacks {missing}; got keys {sorted(d)}")
        return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]),
                   d.get("cx"), d.get("cy"))

    def K(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """3x3 calibration matrix."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx_px], [0.0, self.fy, self.cy_px], [0.0, 0.0, 1.0]],
            dtype=dtype,
            device=device,
        )
