"""Per-model verdict calibration: the verdict's thresholds measured on the model's right poses.

The global thresholds of :class:`~.verify.VerdictConfig` were calibrated on the benchmark; a
weak model (foggy renders, few matches) and a strong one share them. An audit of the model
(``icomma-audit``, docs/AUDIT.md) localizes the model's own photos against their recorded poses;
its *right* poses (within ``right_rot_deg`` / ``right_trans`` scene radii of the record, on
cameras the audit did not flag, called ``ok`` by the global verdict) show what a right pose looks
like on this model. The calibrated thresholds sit at the tail of those poses' signals:

- lower bounds (``ok_inliers``, ``ok_ratio``, ``ok_spread``, ``ok_coverage``): the
  ``percentile``-th percentile of the right poses' values x ``margin``;
- upper bounds (``ok_median_px``, ``ok_mean_px``): the ``100 - percentile``-th percentile
  / ``margin``, never below ``min_px``;

and each is never looser than the global threshold (the floor). A calibration can only turn an
``ok`` into ``uncertain``; the ``fail_*`` thresholds and ``inlier_px`` stay global.

A calibration is stored as JSON (the VerdictConfig's fields, the model's fingerprint, the audit it
came from, the counts and the measured percentiles) in
``<cache dir>/calibration/<model fingerprint>.json`` (``candidate_cache.default_cache_dir()``
unless a cache folder is given) or at a path the user gives; :func:`load_calibration` reads it
back for a model (``Localizer(..., verdict=load_calibration(model))``).

    cal = calibrate(audit_rows, VerdictConfig(), flagged={"IMG_0042"})
    save_calibration(cal, model, source={"audit": "outputs/audit/.../audit.json"})
    verdict = load_calibration(model)          # None when the model has none
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Collection, Dict, List, Mapping, Optional, Sequence, Union

import numpy as np

from ..checks import check_choice, check_int, check_real, config_from_dict
from ..gaussians import GaussianModel
from ..io.atomic import write_json_atomic
from .candidate_cache import default_cache_dir, model_fingerprint
from .types import VERDICTS, Verdict
from .verify import PoseScore, VerdictConfig, decide

logger = logging.getLogger(__name__)

__all__ = [
    "CALIBRATION_FORMAT",
    "Calibration",
    "CalibrationConfig",
    "CalibrationError",
    "calibrate",
    "calibration_path",
    "load_calibration",
    "model_key",
    "redecide",
    "right_poses",
    "save_calibration",
    "stricter",
]

#: The ``format`` of a stored calibration (a file of another format is not read).
CALIBRATION_FORMAT = "icomma-calibration/1"

#: Thresholds that bound a signal from below, and from above (``VerdictConfig`` field: signal).
LOWER_BOUNDS = {"ok_inliers": "inliers", "ok_ratio": "inlier_ratio", "ok_spread": "spread",
                "ok_coverage": "coverage"}
UPPER_BOUNDS = {"ok_median_px": "median_px", "ok_mean_px": "mean_px"}

#: The signals a ``PoseScore`` is made of (the rest of a verdict's signals are its extras).
SCORE_FIELDS = tuple(f.name for f in dataclasses.fields(PoseScore))

PathLike = Union[str, Path]


class CalibrationError(ValueError):
    """A calibration that cannot be made (too few right poses) or read (a bad or foreign file)."""


@dataclass
class CalibrationConfig:
    """How thresholds are drawn from the right poses (module docstring).

    percentile: the tail [%] of the right poses a threshold sits at (1: the 1st percentile of a
        lower bound, the 99th of an upper bound).
    margin: lower bounds are multiplied by it, upper bounds divided by it (in (0, 1]).
    min_px: the displacement thresholds are never set below this [px].
    min_right: fewer right poses than this give no calibration (a percentile of a handful of poses
        says nothing).
    right_rot_deg, right_trans: a pose is right when it is within these of its recorded pose
        (degrees; scene radii).
    poses: ``ok``: the right poses the global verdict calls ok (the calibration then costs at most
        about ``percentile`` % of the global verdict's right ``ok`` poses per threshold); ``all``:
        every right pose (looser: right poses the global verdict doubts pull the tails down).
    """

    percentile: float = 1.0
    margin: float = 0.8
    min_px: float = 0.25
    min_right: int = 20
    right_rot_deg: float = 5.0
    right_trans: float = 0.05
    poses: str = "ok"

    def __post_init__(self):
        n = "CalibrationConfig."
        check_real(self.percentile, n + "percentile", 0.0, 50.0)
        check_real(self.margin, n + "margin", 0.0, 1.0, lo_open=True)
        check_real(self.min_px, n + "min_px", 0.0, lo_open=True)
        check_int(self.min_right, n + "min_right", 1)
        check_real(self.right_rot_deg, n + "right_rot_deg", 0.0, lo_open=True)
        check_real(self.right_trans, n + "right_trans", 0.0, lo_open=True)
        check_choice(self.poses, n + "poses", ("ok", "all"))

    @classmethod
    def from_dict(cls, d: Optional[Mapping[str, Any]]) -> "CalibrationConfig":
        """From a plain mapping (a Hydra group); unknown keys raise ValueError naming them."""
        return config_from_dict(cls, d or {}, "calibration")


@dataclass
class Calibration:
    """A model's verdict thresholds and where they came from.

    verdict: the calibrated thresholds. base: the global ones (the floor). measured: the right
    poses' percentiles behind each threshold. counts: rows, right poses, poses used, cameras.
    settings: the :class:`CalibrationConfig`. source: what it was made from (the audit's path...).
    """

    verdict: VerdictConfig
    base: VerdictConfig
    measured: Dict[str, float] = field(default_factory=dict)
    counts: Dict[str, int] = field(default_factory=dict)
    settings: Dict[str, Any] = field(default_factory=dict)
    source: Dict[str, Any] = field(default_factory=dict)

    def to_json(self, model_id: Optional[str] = None) -> Dict[str, Any]:
        """The stored form (module docstring); ``model_id`` is the model's :func:`model_key`."""
        return {"format": CALIBRATION_FORMAT, "model": model_id,
                "verdict": dataclasses.asdict(self.verdict),
                "global": dataclasses.asdict(self.base), "measured": self.measured,
                "counts": self.counts, "settings": self.settings, "source": self.source}

    def changed(self) -> Dict[str, List[Any]]:
        """``{field: [global, calibrated]}`` of the thresholds the calibration moved."""
        a, b = dataclasses.asdict(self.base), dataclasses.asdict(self.verdict)
        return {k: [a[k], b[k]] for k in a if a[k] != b[k]}


# ---------------------------------------------------------------------------------- the rows


def _finite(v: Any) -> Optional[float]:
    """``v`` as a finite float, else None."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _is_right(row: Mapping[str, Any], cfg: CalibrationConfig) -> bool:
    rot, trans = _finite(row.get("rot_err_deg")), _finite(row.get("trans_err_rel"))
    return rot is not None and trans is not None and rot < cfg.right_rot_deg \
        and trans < cfg.right_trans


def right_poses(rows: Sequence[Mapping[str, Any]], cfg: CalibrationConfig,
                flagged: Collection[str] = ()) -> List[Mapping[str, Any]]:
    """The rows the calibration learns from.

    Right poses (``rot_err_deg`` and ``trans_err_rel`` under ``cfg``'s bounds) with signals, on
    cameras not in ``flagged`` (a row's camera is its ``camera``, else its ``name``), called
    ``ok`` when ``cfg.poses == "ok"``.
    """
    out = []
    for r in rows:
        if r.get("error") or not isinstance(r.get("signals"), Mapping):
            continue
        if str(r.get("camera", r.get("name"))) in flagged or not _is_right(r, cfg):
            continue
        if cfg.poses == "ok" and r.get("status") != "ok":
            continue
        if r["signals"].get("inliers") is None:
            continue  # the pose could not be checked (no matcher)
        out.append(r)
    return out


def _signal(rows: Sequence[Mapping[str, Any]], key: str) -> np.ndarray:
    """The finite values of signal ``key`` over ``rows`` (``inlier_ratio`` computed if absent)."""
    vals = []
    for r in rows:
        s = r["signals"]
        v = s.get(key)
        if v is None and key == "inlier_ratio" and s.get("matches"):
            v = float(s.get("inliers") or 0) / float(s["matches"])
        f = _finite(v)
        if f is not None:
            vals.append(f)
    return np.asarray(vals, np.float64)


# ---------------------------------------------------------------------------------- calibrate


def calibrate(rows: Sequence[Mapping[str, Any]], base: Optional[VerdictConfig] = None,
              cfg: Optional[CalibrationConfig] = None, flagged: Collection[str] = (),
              source: Optional[Mapping[str, Any]] = None) -> Calibration:
    """The thresholds of a model from an audit's rows (module docstring).

    Args:
        rows: the audit's rows (the one row schema with ``signals``, ``rot_err_deg``,
            ``trans_err_rel``, ``status`` and ``camera``).
        base: the global thresholds, the floor (default: ``VerdictConfig()``).
        cfg: how the thresholds are drawn (default: ``CalibrationConfig()``).
        flagged: cameras the audit flagged (their rows are not learnt from).
        source: what the rows came from, stored with the calibration.

    Raises:
        CalibrationError: fewer than ``cfg.min_right`` right poses.
    """
    base = VerdictConfig() if base is None else base
    cfg = CalibrationConfig() if cfg is None else cfg
    if not isinstance(base, VerdictConfig):
        raise ValueError(f"base must be a VerdictConfig, got {type(base).__name__}")
    used = right_poses(rows, cfg, set(flagged))
    counts = {"rows": len(rows), "right": sum(1 for r in rows if _is_right(r, cfg)),
              "used": len(used), "cameras": len({str(r.get("camera", r.get("name")))
                                                 for r in rows}),
              "flagged_cameras": len(set(flagged))}
    if len(used) < cfg.min_right:
        raise CalibrationError(
            f"only {len(used)} right poses to calibrate from (calibration.min_right = "
            f"{cfg.min_right}): audit more photos or more starts (sample, starts)")
    values: Dict[str, Any] = {}
    measured: Dict[str, float] = {}
    for name, key in LOWER_BOUNDS.items():
        p = float(np.percentile(_signal(used, key), cfg.percentile))
        measured[f"{key}_p{cfg.percentile:g}"] = p
        value = max(float(getattr(base, name)), p * cfg.margin)
        values[name] = int(math.floor(value)) if name == "ok_inliers" else min(value, 1.0)
    for name, key in UPPER_BOUNDS.items():
        q = 100.0 - cfg.percentile
        p = float(np.percentile(_signal(used, key), q))
        measured[f"{key}_p{q:g}"] = p
        values[name] = min(float(getattr(base, name)), max(p / cfg.margin, cfg.min_px))
    verdict = dataclasses.replace(base, **values)
    return Calibration(verdict, base, measured, counts, dataclasses.asdict(cfg),
                       dict(source or {}))


# ---------------------------------------------------------------------------------- re-deciding


def redecide(signals: Mapping[str, Any], cfg: VerdictConfig) -> Optional[Verdict]:
    """The verdict of a recorded pose under other thresholds, from its stored ``signals``.

    The signals of a row (``result.row()["signals"]``): the score's fields, ``converged`` and the
    method's extras (``ambiguous``, ``rival``, ...), all passed to :func:`~.verify.decide`.
    None when the row has no score (the pose could not be checked).
    """
    if not isinstance(signals, Mapping) or signals.get("inliers") is None:
        return None
    parts = {}
    for k in SCORE_FIELDS:
        v = signals.get(k)
        parts[k] = float("inf") if v is None and k.endswith(("_px", "_rmse")) else v
    if any(parts[k] is None for k in SCORE_FIELDS):
        return None
    score = PoseScore(**parts)
    extra = {k: v for k, v in signals.items()
             if k not in SCORE_FIELDS and k not in ("converged", "inlier_ratio")}
    return decide(score, cfg, converged=signals.get("converged"), extra=extra)


def stricter(a: Optional[str], b: Optional[str]) -> Optional[str]:
    """The stricter of two verdict statuses (``failed`` < ``uncertain`` < ``ok``)."""
    if a not in VERDICTS:
        return b if b in VERDICTS else a
    if b not in VERDICTS:
        return a
    rank = {"failed": 0, "uncertain": 1, "ok": 2}
    return a if rank[a] <= rank[b] else b


# ---------------------------------------------------------------------------------- storage


def model_key(model: GaussianModel) -> str:
    """The fingerprint a calibration is stored under: the model as the Localizer renders it.

    ``candidate_cache.model_fingerprint`` of the model with its higher SH bands dropped when they
    are all zero (the Localizer renders such a model at degree 0), so the key is the same whether
    the model folder's Gaussians or the Localizer's are given.
    """
    if not isinstance(model, GaussianModel):
        raise ValueError(f"model must be a GaussianModel, got {type(model).__name__}")
    return model_fingerprint(model.without_zero_sh())


def calibration_path(model_id: str, cache_dir: Optional[PathLike] = None) -> Path:
    """``<cache_dir>/calibration/<model_id>.json`` (default: ``default_cache_dir()``)."""
    base = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
    return base / "calibration" / f"{model_id}.json"


def save_calibration(calibration: Calibration, model: GaussianModel,
                     path: Optional[PathLike] = None,
                     cache_dir: Optional[PathLike] = None) -> Path:
    """Store ``calibration`` for ``model`` atomically; returns the file written.

    At ``path`` when given, else at :func:`calibration_path` of the model in ``cache_dir``.
    """
    key = model_key(model)
    target = Path(path).expanduser() if path else calibration_path(key, cache_dir)
    write_json_atomic(target, calibration.to_json(key))
    return target


def _read(p: Path, key: str) -> VerdictConfig:
    """The VerdictConfig stored at ``p`` for the model ``key`` (CalibrationError otherwise)."""
    try:
        doc = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CalibrationError(f"calibration file {p} unreadable ({type(e).__name__}: {e})") \
            from None
    if not isinstance(doc, dict) or doc.get("format") != CALIBRATION_FORMAT:
        raise CalibrationError(f"{p} is not a verdict calibration ({CALIBRATION_FORMAT})")
    if doc.get("model") != key:
        raise CalibrationError(
            f"the calibration {p} is for another model (fingerprint {doc.get('model')!r}, this "
            f"model {key!r}): audit this model (icomma-audit) to calibrate it")
    try:
        return config_from_dict(VerdictConfig, doc.get("verdict"), f"{p}: verdict")
    except (TypeError, ValueError) as e:
        raise CalibrationError(f"calibration file {p}: {e}") from None


def load_calibration(model: GaussianModel, cache_dir: Optional[PathLike] = None,
                     path: Optional[PathLike] = None) -> Optional[VerdictConfig]:
    """The calibrated verdict thresholds of ``model``, or None when it has none.

    Args:
        model: the Gaussians (its :func:`model_key` names the file).
        cache_dir: the cache folder (default ``candidate_cache.default_cache_dir()``).
        path: a calibration file to read instead of the cache's.

    Raises:
        CalibrationError: ``path`` missing, unreadable, not a calibration or for another model.
            A damaged file in the cache is logged and read as no calibration.
    """
    key = model_key(model)
    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise CalibrationError(f"calibration file not found: {p}")
        return _read(p, key)
    p = calibration_path(key, cache_dir)
    if not p.is_file():
        return None
    try:
        return _read(p, key)
    except CalibrationError as e:
        logger.warning("%s: the global verdict thresholds are used", e)
        return None
