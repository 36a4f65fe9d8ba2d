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
import torch.nn.functional as F

from ..camera import Intrinsics
from ..checks import check_tensor

__all__ = [
    "LocalizationResult",
    "MethodOutcome",
    "Query",
    "ROW_FIELDS",
    "Stage",
    "TraceRecord",
    "VERDICTS",
    "Verdict",
    "blank_row",
    "resize_image",
]


class Stage(IntEnum):
    """Which stage produced a trace record. The paper's two stages keep their numbers (1, 2)."""

    MATCH = 1  # the paper's stage 1: matching + comparing loss
    COMPARE = 2  # the paper's stage 2: comparing loss alone, decaying learning rate
    GEOMETRIC = 3  # render, match, lift with the rendered depth, PnP
    REFINE = 4  # photometric refinement (comparing loss, Levenberg-Marquardt steps)
    CANDIDATES = 5  # ranking of candidate views
    VERIFY = 6  # the final check of a pose


def resize_image(img: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """``[C, H, W]`` resized to ``h x w`` (bilinear, antialiased when shrinking)."""
    if tuple(img.shape[-2:]) == (h, w):
        return img
    return F.interpolate(img[None], size=(h, w), mode="bilinear", align_corners=False,
                         antialias=True)[0]


@dataclass
class Query:
    """The photo to localize.

    rgb: ``[3, H, W]`` float in [0, 1] (RGBA photos composited over the scene background).
    intrinsics: its pinhole camera at ``W x H``.
    alpha: ``[1, H, W]`` foreground alpha of an RGBA photo, or None.
    valid: ``[1, H, W]`` pixels that are real image content (0 where undistortion filled the
        image from outside the source), or None when every pixel is.
    name: a name for reports.

    A query also keeps the matcher's features of itself once computed (``state.query_features``),
    so that localizing it again (another start, tracking's fallback) or having them computed
    ahead in another thread (``Localizer.prepare``) saves the extraction.
    """

    rgb: torch.Tensor
    intrinsics: Intrinsics
    alpha: Optional[torch.Tensor] = None
    valid: Optional[torch.Tensor] = None
    name: str = "query"
    memo: Dict[Any, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if not isinstance(self.intrinsics, Intrinsics):
            raise ValueError(
                f"intrinsics must be an Intrinsics, got {type(self.intrinsics).__name__}"
            )
        check_tensor(self.rgb, "query_rgb", (3, "H", "W"), floating=True, finite=True)
        H, W = int(self.rgb.shape[1]), int(self.rgb.shape[2])
        if (self.intrinsics.width, self.intrinsics.height) != (W, H):
            raise ValueError(
                f"intrinsics size {self.intrinsics.width}x{self.intrinsics.height} (WxH) does not "
                f"match query_rgb {W}x{H}; scale the intrinsics with Intrinsics.scaled"
            )
        check_tensor(self.alpha, "query_alpha", (1, H, W), optional=True)
        check_tensor(self.valid, "query_valid", (1, H, W), optional=True)

    @classmethod
    def from_view(cls, view, bg: torch.Tensor, scale: float = 1.0) -> "Query":
        """The query of a dataset view (``io.datasets.View``) at ``scale``, its masks included."""
        im = view.load_image(scale=scale, background=bg)
        intr = view.intrinsics if scale == 1.0 else view.intrinsics.scaled(scale)
        return cls(im.rgb, intr, im.alpha, im.valid, str(view.name))

    def fresh(self) -> "Query":
        """The same photo without what earlier localizations kept (``memo``).

        A benchmark times each run as if it were the photo's first.
        """
        return dataclasses.replace(self)

    def resized(self, side: Optional[int]) -> "Query":
        """This query with its longer side at ``side`` px (intrinsics follow); as is for None."""
        if not side or max(self.size) == side:
            return self
        q = self.at(self.intrinsics.scaled(self.intrinsics.scale_to_side(side, enlarge=True)))
        return Query(q.rgb.contiguous(), q.intrinsics, q.alpha, q.valid, q.name)

    def at(self, intrinsics: Intrinsics, device=None, dtype=None) -> "Query":
        """This query resized to ``intrinsics``' size (on ``device`` / ``dtype`` when given).

        The masks stay conservative: a pixel of ``valid`` stays valid only if all of its source
        was.
        """
        H, W = intrinsics.height, intrinsics.width
        rgb = resize_image(self.rgb.detach().to(device, dtype), H, W).clamp(0.0, 1.0)
        alpha = valid = None
        if self.alpha is not None:
            alpha = resize_image(self.alpha.detach().to(device, dtype), H, W).clamp(0.0, 1.0)
        if self.valid is not None:
            dt = dtype or self.valid.dtype
            valid = (resize_image(self.valid.detach().to(device, dtype), H, W) > 0.999).to(dt)
        return Query(rgb, intrinsics, alpha, valid, self.name)

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
class MethodOutcome:
    """What a method's ``run(state, init_w2c)`` ends with (the Localizer makes the result).

    w2c: the pose found. verdict: whether to trust it. score: the render-and-match behind the
    verdict (None when it could not be checked). iterations: steps taken. stop_reason: how the
    optimisation ended (not whether the pose is right). details: what only this method has
    (documented by each method's config).
    """

    w2c: np.ndarray
    verdict: Verdict
    score: Any
    iterations: int
    stop_reason: str
    details: Dict[str, Any] = field(default_factory=dict)


#: The one row of a localization, in result.json, poses.json / poses.csv and the benchmark's
#: records alike (docs/CONTRACTS.md, "Result rows"). Poses are camera-to-world, OpenCV axes.
ROW_FIELDS = (
    "name",
    "image",
    "status",
    "reason",
    "error",
    "method",
    "matcher",
    "c2w",
    "init_c2w",
    "gt_c2w",
    "rot_err_deg",
    "trans_err",
    "trans_err_rel",
    "init_rot_err_deg",
    "init_trans_err",
    "init_trans_err_rel",
    "inliers",
    "matches",
    "iterations",
    "stop_reason",
    "seconds",
    "scene_scale",
    "intrinsics",
)


def blank_row(**values: Any) -> Dict[str, Any]:
    """A row with every field of `ROW_FIELDS` (None unless given), plus any extra ``values``."""
    row: Dict[str, Any] = dict.fromkeys(ROW_FIELDS)
    row.update(values)
    return row


def _list(T: Optional[np.ndarray]) -> Optional[list]:
    return None if T is None else np.asarray(T).tolist()


@dataclass
class LocalizationResult:
    """Outcome of a localization. Poses are float64 numpy camera-to-world, OpenCV axes.

    ``stop_reason`` says how the optimisation ended (``"converged"``, ``"max_iterations"``, ...);
    it is NOT a statement that the pose is right: ``verdict`` is. Errors (``rot_err_deg``,
    ``trans_err``: camera-centre distance in world units) are filled only when the truth was
    given, and only for reports. ``inliers`` / ``matches``: the matches agreeing with the final
    pose and all matches there (the verdict's), for every method. ``stage_seconds`` /
    ``stage_cpu_seconds``: wall / process CPU seconds per kind of work. ``details``: what only
    the method has (the paper's: ``switch_iteration``, ``gradient_mode``, ``final_loss``,
    ``scene_depth``, ``match_counts``; the default's: ``hypotheses``, ``refine_iterations``,
    ``rolled_back``, ...).
    """

    name: str
    c2w: np.ndarray
    verdict: Verdict
    method: str
    matcher: Optional[str]
    iterations: int
    stop_reason: str
    seconds: float
    intrinsics: Optional[Intrinsics] = None
    init_c2w: Optional[np.ndarray] = None
    gt_c2w: Optional[np.ndarray] = None
    rot_err_deg: Optional[float] = None
    trans_err: Optional[float] = None
    init_rot_err_deg: Optional[float] = None
    init_trans_err: Optional[float] = None
    inliers: Optional[int] = None
    matches: Optional[int] = None
    stage_seconds: Dict[str, float] = field(default_factory=dict)
    stage_cpu_seconds: Dict[str, float] = field(default_factory=dict)
    details: Dict[str, Any] = field(default_factory=dict)
    trace: List[TraceRecord] = field(default_factory=list)
    config: Dict[str, Any] = field(default_factory=dict)

    @property
    def w2c(self) -> np.ndarray:
        """The estimated world-to-camera (the inverse of ``c2w``)."""
        from ..pose.convert import invert_rigid

        return invert_rigid(self.c2w)

    def row(self, scene_scale: Optional[float] = None, **extra: Any) -> Dict[str, Any]:
        """The result as a row of `ROW_FIELDS` (JSON-friendly), plus ``extra`` fields.

        ``scene_scale``: the unit of ``trans_err_rel`` and ``init_trans_err_rel`` (``trans_err /
        scene_scale``; the 3DGS scene radius of the model's cameras in the tools, the benchmark's
        translation unit).
        """
        v = self.verdict
        def rel(t: Optional[float]) -> Optional[float]:
            return t / scene_scale if scene_scale and t is not None else None

        row = blank_row(
            name=self.name, status=v.status, reason=v.reason, method=self.method,
            matcher=self.matcher, c2w=_list(self.c2w), init_c2w=_list(self.init_c2w),
            gt_c2w=_list(self.gt_c2w), rot_err_deg=self.rot_err_deg, trans_err=self.trans_err,
            trans_err_rel=rel(self.trans_err), init_rot_err_deg=self.init_rot_err_deg,
            init_trans_err=self.init_trans_err, init_trans_err_rel=rel(self.init_trans_err),
            inliers=self.inliers, matches=self.matches,
            iterations=self.iterations, stop_reason=self.stop_reason, seconds=self.seconds,
            scene_scale=scene_scale,
            intrinsics=None if self.intrinsics is None else self.intrinsics.to_json(),
            signals=v.to_json()["signals"], stage_seconds=self.stage_seconds,
            stage_cpu_seconds=self.stage_cpu_seconds,
            details=self.details,
        )
        row.update(extra)
        return _jsonable(row)

    def to_json(self, include_trace: bool = True, scene_scale: Optional[float] = None
                ) -> Dict[str, Any]:
        """The row (:meth:`row`) with the config and, unless left out, the trace."""
        d = self.row(scene_scale, config=self.config)
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
