"""Benchmark protocols and the methods compared.

A protocol says what is sampled, which methods run and which metrics are reported.

Protocol kinds (conf/benchmark_protocol/*.yaml):

- ``curves``: iNeRF-style study. Q queries x K initial poses per interval; the fraction of runs
  under each (rotation deg, translation) threshold pair is reported after every iteration.
- ``time``: success rate (< 5 deg and < 0.05) of the final pose and the mean seconds to first
  reach it, per method.
- ``relative_pose``: AUC@5/10/20 of the rotation error; iComMa against the matching-only baseline
  (matcher + essential matrix between the render at the initial pose and the query).
- ``ablation``: failure rate and the mean errors of the successes for full / w/o comparing /
  w/o matching.

Every localizer run also records its verdict (ok | uncertain | failed, judged without ground
truth); summaries report the verdict's precision (of the poses called ``ok``, how many are right)
and recall (of the right poses, how many are called ``ok``).

An interval with ``init: none`` gives no start pose at all (the default method searches the
candidate views; methods that need a start skip it).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

from ..localize import LocalizerConfig, RobustConfig
from .sampling import PIVOTS, TRANSLATION_MODES

__all__ = ["KINDS", "METHODS", "NEEDS_START", "Interval", "ProtocolSpec", "method_config",
           "is_localizer_method"]

KINDS = ("curves", "time", "relative_pose", "ablation")

#: method name -> what it is (the paper's naming in brackets)
METHODS: Dict[str, str] = {
    "robust": "the default localizer: geometric stage (render, match, lift, PnP), candidate "
    "views when the start is unusable or absent, photometric refinement with roll-back, verdict",
    "icomma": "full iComMa: matching + comparing, then comparing alone (the optimizer config as "
    "given)",
    "compare_only": "w/o matching: photometric comparing loss only (use_matching=false)",
    "match_only": "w/o comparing: matching loss only (lambda_match=1, never switches: "
    "switch_threshold=0)",
    "essential": "matching only: matcher + essential matrix (RANSAC) between the image rendered "
    "at the initial pose and the query (the paper's LightGlue / LoFTR + E rows)",
}


#: Methods that need a start pose (they are skipped in an ``init: none`` interval).
NEEDS_START = ("icomma", "compare_only", "match_only", "essential")


def is_localizer_method(name: str) -> bool:
    """Whether ``name`` runs the localizer (not the essential-matrix baseline)."""
    return name in ("robust", "icomma", "compare_only", "match_only")


def method_config(name: str, base: LocalizerConfig, max_iterations: Optional[int] = None,
                  robust: Optional[RobustConfig] = None):
    """The config of a localizer method.

    ``robust`` (the default method's config) for ``robust``, else a LocalizerConfig derived from
    ``base`` (the paper's optimizer group).
    """
    if not is_localizer_method(name):
        raise ValueError(
            f"method must be one of robust, icomma, compare_only, match_only, got {name!r}"
        )
    if name == "robust":
        return robust if robust is not None else RobustConfig()
    d = base.to_dict()
    if max_iterations is not None:
        d["max_iterations"] = int(max_iterations)
    if name == "icomma":
        d["use_matching"] = True
    elif name == "compare_only":
        d["use_matching"] = False
    elif name == "match_only":
        d["use_matching"] = True
        d["lambda_match"] = 1.0
        d["switch_threshold"] = 0.0
        d["max_stage1_iterations"] = None
    return LocalizerConfig.from_dict(d)


def _pair(v, name: str) -> Tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair [lo, hi], got {v!r}") from None
    if a > b or a < 0:
        raise ValueError(f"{name} must satisfy 0 <= lo <= hi, got {v!r}")
    return a, b


@dataclass(frozen=True)
class Interval:
    """One row of a protocol.

    The rotation and translation ranges of the start pose, or no start (``no_start``).
    """

    label: str
    rot_deg: Tuple[float, float]
    trans: Tuple[float, float]
    no_start: bool = False

    def to_json(self) -> dict:
        """The interval as in the protocol's YAML (``init: none`` for no start)."""
        d = {"label": self.label, "rot_deg": list(self.rot_deg), "trans": list(self.trans)}
        if self.no_start:
            d["init"] = "none"
        return d


@dataclass
class ProtocolSpec:
    """One protocol, as composed from conf/benchmark_protocol/<name>.yaml."""

    name: str
    kind: str
    intervals: List[Interval]
    methods: List[str]
    num_queries: int = 5
    poses_per_query: int = 10
    max_iterations: int = 500
    thresholds: List[Tuple[float, float]] = field(default_factory=lambda: [(5.0, 0.05)])
    auc_thresholds: List[float] = field(default_factory=lambda: [5.0, 10.0, 20.0])
    translation_mode: str = "per_axis"
    pivot: str = "origin"
    seed: int = 0
    description: str = ""
    paper_source: str = ""
    quick: bool = False
    essential_thresh_px: float = 1.0
    method_poses_per_query: Dict[str, int] = field(default_factory=dict)
    paper_dataset: str = "synthetic"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"benchmark_protocol.kind must be one of {KINDS}, got {self.kind!r}")
        if not self.intervals:
            raise ValueError("benchmark_protocol.intervals must not be empty")
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods:
            raise ValueError(
                f"benchmark_protocol.methods must be a non-empty list of {sorted(METHODS)}, "
                f"got {self.methods!r}"
            )
        for name in ("num_queries", "poses_per_query", "max_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool)) or v < 1:
                raise ValueError(f"benchmark_protocol.{name} must be a positive int, got {v!r}")
        if self.translation_mode not in TRANSLATION_MODES:
            raise ValueError(
                f"benchmark_protocol.translation_mode must be one of {TRANSLATION_MODES}, "
                f"got {self.translation_mode!r}"
            )
        if self.pivot not in PIVOTS:
            raise ValueError(
                f"benchmark_protocol.pivot must be one of {PIVOTS}, got {self.pivot!r}"
            )
        labels = [iv.label for iv in self.intervals]
        if len(set(labels)) != len(labels):
            raise ValueError(f"benchmark_protocol.intervals labels must be unique, got {labels}")
        for m, k in self.method_poses_per_query.items():
            if m not in self.methods or not isinstance(k, int) or isinstance(k, bool) or k < 1:
                raise ValueError(
                    "benchmark_protocol.method_poses_per_query must map methods of the protocol "
                    f"to positive ints, got {self.method_poses_per_query!r}"
                )
        if self.paper_dataset not in ("synthetic", "360"):
            raise ValueError(
                "benchmark_protocol.paper_dataset must be synthetic or 360, got "
                f"{self.paper_dataset!r}"
            )

    def poses_for(self, method: str) -> int:
        """How many start poses per query ``method`` runs.

        The first ones: a method given fewer runs a subset of the others' starts.
        """
        return min(
            self.poses_per_query, self.method_poses_per_query.get(method, self.poses_per_query)
        )

    def runs(self, method: str, interval: "Interval") -> int:
        """Planned runs of ``method`` in ``interval``.

        A no-start interval runs each of ``num_queries * poses_per_query`` distinct views once.
        """
        if interval.no_start:
            return 0 if method in NEEDS_START else self.num_queries * self.poses_per_query
        return self.num_queries * self.poses_for(method)

    @classmethod
    def from_dict(cls, d: Dict[str, Any], quick: bool = False) -> "ProtocolSpec":
        """From a plain mapping (the Hydra group as a container).

        With ``quick``, the mapping's ``quick`` block overrides the sizes (num_queries,
        poses_per_query, max_iterations, ...).
        """
        d = dict(d)
        q = d.pop("quick", None) or {}
        if quick:
            allowed = {
                "num_queries",
                "poses_per_query",
                "max_iterations",
                "intervals",
                "method_poses_per_query",
            }
            unknown_q = sorted(set(q) - allowed)
            if unknown_q:
                raise ValueError(
                    f"benchmark_protocol.quick may override {sorted(allowed)}; got {unknown_q}"
                )
            d.update(q)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown benchmark_protocol keys {unknown}; known: {sorted(names)}")
        ivs = []
        for i, iv in enumerate(d.get("intervals") or []):
            if isinstance(iv, dict) and iv.get("init") == "none":
                ivs.append(
                    Interval(str(iv.get("label") or "no_start"), (0.0, 0.0), (0.0, 0.0), True)
                )
                continue
            if not isinstance(iv, dict) or "rot_deg" not in iv or "trans" not in iv:
                raise ValueError(
                    f"benchmark_protocol.intervals[{i}] must have rot_deg and trans (or "
                    f"init: none), got {iv!r}"
                )
            rot = _pair(iv["rot_deg"], f"intervals[{i}].rot_deg")
            tr = _pair(iv["trans"], f"intervals[{i}].trans")
            label = iv.get("label") or f"r{rot[0]:g}-{rot[1]:g}"
            ivs.append(Interval(str(label), rot, tr))
        d["intervals"] = ivs
        if "thresholds" in d:
            d["thresholds"] = [tuple(float(x) for x in t) for t in d["thresholds"]]
        if "auc_thresholds" in d:
            d["auc_thresholds"] = [float(x) for x in d["auc_thresholds"]]
        d["methods"] = [str(m) for m in d.get("methods", [])]
        d["method_poses_per_query"] = {
            str(k): int(v)
            for k, v in (d.get("method_poses_per_query") or {}).items()
            if str(k) in d["methods"]
        }
        d["quick"] = bool(quick)
        return cls(**d)

    def to_json(self) -> dict:
        """The protocol as JSON (intervals and thresholds as lists)."""
        d = dataclasses.asdict(self)
        d["intervals"] = [iv.to_json() for iv in self.intervals]
        d["thresholds"] = [list(t) for t in self.thresholds]
        return d

    @property
    def num_runs(self) -> int:
        """Planned runs of the whole protocol (every method x interval)."""
        return sum(self.runs(m, iv) for iv in self.intervals for m in self.methods)
