"""The localizer's value types: the query, the per-step trace record, the verdict and the result.

Poses are float64 numpy ``[4, 4]`` matrices in OpenCV axes; every name says its frame.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, Dict, Iterator, List, Optional

import numpy as np
import torch

from ..camera import Intrinsics

__all__ = ["Query", "Stage", "TraceRecord", "Verdict", "VERDICTS", "LocalizationResult"]


class Stage(IntEnum):
    """Which stage produced a trace record. The paper's two stages keep their numbers (1, 2)."""

    MATCH = 1  # the paper's stage 1: matching + comparing loss
    COMPARE = 2  # the paper's stage 2: comparing loss alone, decaying learning rate
    GEOMETRIC = 3  # render, match, lift with the rendered depth, PnP
    REFINE = 4  # photometric refinement (comparing loss, Levenberg-Marquardt steps)
    CANDIDATES = 5  # ranking of candidate views
    VERIFY = 6  # the final check of a pose


@dataclass
class Query:
    """The photo to localize.

    rgb: ``[3, H, W]`` float in [0, 1] (RGBA photos composited over the scene background).
    intrinsics: its pinhole camera at ``W x H``.
    alpha: ``[1, H, W]`` foreground alpha of an RGBA photo, or None.
    valid: ``[1, H, W]`` pixels that are real image content (0 where undistortion filled the
        image from outside the source), or None when every pixel is.
    name: a name for reports.
    """

    rgb: torch.Tensor
    intrinsics: Intrinsics
    alpha: Optional[torch.Tensor] = None
    valid: Optional[torch.Tensor] = None
    name: str = "query"

    def __post_init__(self):
        if not isinstance(self.intrinsics, Intrinsics):
            raise ValueError(
                f"intrinsics must be an Intrinsics, got {type(self.intrinsics).__name__}"
            )
        rgb = self.rgb
        if not isinstance(rgb, torch.Tensor) or rgb.ndim != 3 or rgb.shape[0] != 3 \
                or not rgb.is_floating_point():
            got = list(rgb.shape) if isinstance(rgb, torch.Tensor) else type(rgb).__name__
            raise ValueError(f"query_rgb must be a float [3, H, W] tensor, got {got}")
        H, W = int(rgb.shape[1]), int(rgb.shape[2])
        if (self.intrinsics.width, self.intrinsics.height) != (W, H):
            raise ValueError(
                f"intrinsics size {self.intrinsics.width}x{self.intrinsics.height} (WxH) does not "
                f"match query_rgb {W}x{H}; scale the intrinsics with Intrinsics.scaled"
            )
        if not bool(torch.isfinite(rgb).all()):
            raise ValueError("query_rgb contains NaN or infinite values")
        for name in ("alpha", "valid"):
            m = getattr(self, name)
            if m is not None and (not isinstance(m, torch.Tensor) or tuple(m.shape) != (1, H, W)):
                got = list(m.shape) if isinstance(m, torch.Tensor) else type(m).__name__
                raise ValueError(f"query_{name} must be a [1, {H}, {W}] tensor or None, got {got}")

    @property
    def size(self):
        """(W, H) of the query."""
        return self.intrinsics.width, self.intrinsics.height


@dataclass
class TraceRecord:
    """One step of a localization (an optimiser iteration, a PnP round, a verification).

    Reads like a mapping too (``record["loss"]``), so code written for the JSON trace works on it.
    Errors against ground truth are filled only when one was given (never used by the method).
    """

    iteration: int
    stage: Stage
    seconds: float = 0.0
    lr: Optional[float] = None
    loss: Optional[float] = None
    loss_compare: Optional[float] = None
    loss_match: Optional[float] = None
    matches: int = 0
    matches_used: int = 0
    inliers: Optional[int] = None
    accepted: Optional[bool] = None
    hypothesis: Optional[int] = None
    scale: Optional[float] = None
    rot_err_deg: Optional[float] = None
    trans_err: Optional[float] = None
    # the paper's method: the twist rendered, w2c = exp(xi) @ w2c_0
    xi: Optional[List[float]] = None
    w2c: Optional[List[List[float]]] = None  # the pose this step rendered (other stages)

    def __getitem__(self, key: str) -> Any:
        if key == "stage_name":
            return self.stage.name.lower()
        if key not in self.__dataclass_fields__:
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key: str, default: Any = None) -> Any:
        """A field (or ``stage_name``) by name, as a dict's ``get``."""
        try:
            return self[key]
        except KeyError:
            return default

    def keys(self) -> List[str]:
        """The names of the fields, and ``stage_name``."""
        return list(self.to_dict())

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __contains__(self, key: object) -> bool:
        return key in self.to_dict()

    def to_dict(self) -> Dict[str, Any]:
        """The record as a dict (``stage`` as an int, plus ``stage_name``)."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["stage"] = int(self.stage)
        d["stage_name"] = self.stage.name.lower()
        return d


VERDICTS = ("ok", "uncertain", "failed")


@dataclass
class Verdict:
    """Whether a pose can be trusted, judged without ground truth.

    status: ``"ok"`` (trust it), ``"uncertain"`` (check it) or ``"failed"`` (do not use it).
    reason: one line saying why, and what to do when it is not ``ok``.
    signals: the measured numbers behind it (see ``verify.py``).
    """

    status: str
    reason: str
    signals: Dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if self.status not in VERDICTS:
            raise ValueError(f"Verdict.status must be one of {VERDICTS}, got {self.status!r}")

    def to_json(self) -> Dict[str, Any]:
        """The verdict as JSON (the signals made JSON-friendly)."""
        return {"status": self.status, "reason": self.reason, "signals": _jsonable(self.signals)}


@dataclass
class LocalizationResult:
    """Outcome of a localization. Poses are float64 numpy, OpenCV axes.

    ``stop_reason`` says how the optimisation ended (``"converged"``, ``"max_iterations"``, ...);
    it is NOT a statement that the pose is right: ``verdict`` is.
    """

    w2c: np.ndarray
    c2w: np.ndarray
    init_w2c: Optional[np.ndarray]
    iterations: int
    stop_reason: str
    switch_iteration: Optional[int]
    match_counts: Dict[str, Any]
    seconds: float
    gradient_mode: Optional[str]
    matcher: Optional[str]
    method: str = "icomma"
    verdict: Optional[Verdict] = None
    initial_rotation_error_deg: Optional[float] = None
    initial_translation_error: Optional[float] = None
    final_rotation_error_deg: Optional[float] = None
    final_translation_error: Optional[float] = None
    final_loss: Optional[float] = None
    scene_depth: Optional[float] = None
    stage_seconds: Dict[str, float] = field(default_factory=dict)
    hypotheses: List[Dict[str, Any]] = field(default_factory=list)
    trace: List[TraceRecord] = field(default_factory=list)
    config: Dict[str, Any] = field(default_factory=dict)

    def to_json(self, include_trace: bool = True) -> Dict[str, Any]:
        """A JSON-serialisable dict (numbers, lists, None)."""
        d = {
            "method": self.method,
            "verdict": None if self.verdict is None else self.verdict.to_json(),
            "w2c": self.w2c.tolist(),
            "c2w": self.c2w.tolist(),
            "init_w2c": None if self.init_w2c is None else self.init_w2c.tolist(),
            "iterations": self.iterations,
            "stop_reason": self.stop_reason,
            "switch_iteration": self.switch_iteration,
            "match_counts": self.match_counts,
            "seconds": self.seconds,
            "stage_seconds": self.stage_seconds,
            "gradient_mode": self.gradient_mode,
            "matcher": self.matcher,
            "initial_rotation_error_deg": self.initial_rotation_error_deg,
            "initial_translation_error": self.initial_translation_error,
            "final_rotation_error_deg": self.final_rotation_error_deg,
            "final_translation_error": self.final_translation_error,
            "final_loss": self.final_loss,
            "scene_depth": self.scene_depth,
            "hypotheses": self.hypotheses,
            "config": self.config,
        }
        if include_trace:
            d["trace"] = [r.to_dict() for r in self.trace]
        return _jsonable(d)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, torch.Tensor):
        return o.detach().cpu().tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _jsonable(d: Any) -> Any:
    return json.loads(json.dumps(d, default=_json_default))
