"""The iComMa paper's published numbers, for side-by-side reports.

Paper: Yuan Sun et al., "iComMa: Inverting 3D Gaussian Splatting for Camera Pose Estimation via
Comparing and Matching", ECCV 2024, arXiv:2312.09031. The figures were transcribed into
``../shared/docs/paper_results.md`` (tables 1-4); each value below names its table. Nothing is
estimated or read off a plot: a cell the paper does not have (our extra rows, the default method)
is ``None`` with :data:`NOT_FOUND`.

Units follow our reports: success and failure rates and AUCs as fractions (the paper prints
percent for success and AUC), seconds, degrees, translation in the paper's units.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Tuple

PAPER = {
    "title": "iComMa: Inverting 3D Gaussian Splatting for Camera Pose Estimation via Comparing "
             "and Matching",
    "venue": "ECCV 2024",
    "arxiv": "2312.09031",
    "transcription": "../shared/docs/paper_results.md",
}

NOT_FOUND = "n/a (the paper has no such cell)"

#: Dataset families of the paper's tables: NeRF-synthetic, and its "360 degree" scenes
#: (Mip-NeRF360 + Deep Blending). Lego is synthetic; a real capture compares best with 360.
DATASETS = ("synthetic", "360")


@dataclass(frozen=True)
class PaperValue:
    """One published number (or its absence)."""

    value: Optional[float]
    source: str
    note: str = ""

    @property
    def found(self) -> bool:
        """Whether the paper gives this number."""
        return self.value is not None

    def text(self, fmt: str = ".3g") -> str:
        """The number formatted with ``fmt``, or `NOT_FOUND`."""
        return NOT_FOUND if self.value is None else format(self.value, fmt)

    def to_json(self) -> dict:
        """The fields as a dict."""
        return asdict(self)


Key = Tuple[str, str, str, str, str]  # (dataset, protocol, interval, method, metric)
PAPER_NUMBERS: Dict[Key, PaperValue] = {}


def _put(
    dataset: str, protocol: str, interval: str, method: str, metric: str, value: float, source: str
):
    PAPER_NUMBERS[(dataset, protocol, interval, method, metric)] = PaperValue(float(value), source)


# Table 1 (time table): chair, drums, hotdog, lego at 800x800, RTX A6000; 5 poses x 10 starts;
# delta_t +-[0, 0.2]; success < 5 deg and < 0.05; time = mean seconds to the thresholds of the
# successful samples. iComMa_c = comparing only (our compare_only).
_T1 = "Table 1 (time table; synthetic, 800x800, RTX A6000)"
for _iv, _rows in {
    "r10-20": {"inerf": (0.905, 12.66), "icomma": (1.00, 1.13), "compare_only": (1.00, 0.75)},
    "r20-40": {"inerf": (0.655, 23.33), "icomma": (1.00, 1.57), "compare_only": (0.96, 0.83)},
}.items():
    for _m, (_succ, _sec) in _rows.items():
        _put("synthetic", "time_table", _iv, _m, "success_rate", _succ, _T1)
        _put("synthetic", "time_table", _iv, _m, "seconds_to_success", _sec, _T1)

# Tables 2 and 3 (relative pose): AUC of the rotation error at 5/10/20 degrees, 50 pairs per bin.
# Baselines: matcher + RANSAC essential matrix (ours: essential_lightglue covers xfeat+LighterGlue
# and ALIKED/DISK+LightGlue, essential_loftr LoFTR).
_AUC = {
    "synthetic": (
        "Table 2 (relative pose, synthetic)",
        {
            "matchformer": ((39.65, 55.92, 70.94), (21.09, 33.16, 44.56), (6.08, 12.48, 19.44)),
            "essential_lightglue": (
                (61.76, 76.93, 86.55),
                (42.24, 58.71, 70.56),
                (17.65, 27.58, 36.82),
            ),
            "essential_loftr": ((59.27, 75.34, 85.56), (31.85, 45.98, 58.41), (8.07, 13.93, 19.77)),
            "icomma": ((90.95, 94.02, 96.71), (74.65, 78.40, 82.97), (37.93, 39.87, 43.98)),
        },
    ),
    "360": (
        "Table 3 (relative pose, 360-degree scenes)",
        {
            "matchformer": ((13.11, 34.86, 60.61), (0.39, 4.93, 28.06), (0.10, 0.80, 7.78)),
            "essential_lightglue": (
                (13.77, 37.92, 64.25),
                (0.65, 5.48, 31.51),
                (0.23, 1.40, 10.32),
            ),
            "essential_loftr": ((13.64, 35.55, 61.82), (0.42, 4.67, 30.03), (0.14, 1.17, 10.04)),
            "icomma": ((84.41, 86.39, 88.87), (73.27, 75.12, 78.30), (61.75, 63.50, 65.68)),
        },
    ),
}
for _ds, (_src, _rows) in _AUC.items():
    for _m, _bins in _rows.items():
        for _iv, _vals in zip(("r0-20", "r20-40", "r40-60"), _bins):
            for _t, _v in zip(("auc5", "auc10", "auc20"), _vals):
                _put(_ds, "relative_pose", _iv, _m, _t, _v / 100.0, _src)

# Table 4 (ablation): delta_r +-[30, 50]; delta_t +-[0, 0.6] synthetic, +-[0, 0.2] 360; failure
# rate and the mean errors of the successful samples. w/o comparing = match_only, w/o matching =
# compare_only.
_T4 = {"synthetic": "Table 4 (ablation, synthetic: chair, drums, ficus, lego)",
       "360": "Table 4 (ablation, 360: bicycle, Playroom, DrJohnson, room)"}
for _ds, _rows in {
    "synthetic": {"icomma": (0.090, 0.012, 0.001), "match_only": (0.140, 0.064, 0.006),
                  "compare_only": (0.380, 0.011, 0.001)},
    "360": {"icomma": (0.095, 0.024, 0.002), "match_only": (0.145, 0.043, 0.004),
            "compare_only": (0.385, 0.030, 0.002)},
}.items():
    for _m, (_f, _r, _t) in _rows.items():
        _put(_ds, "ablation", "r30-50", _m, "failure_rate", _f, _T4[_ds])
        _put(_ds, "ablation", "r30-50", _m, "mean_rot_deg", _r, _T4[_ds])
        _put(_ds, "ablation", "r30-50", _m, "mean_trans", _t, _T4[_ds])

#: The paper's method constants (Sec. 3.4), checked against conf/optimizer/icomma.yaml by a test.
METHOD_CONSTANTS = {
    "lambda_match": 0.8,
    "switch_threshold": 1e-3,
    "lr": 0.05,
    "betas": (0.9, 0.999),
    "lr_decay_base": 0.6,
    "lr_decay_steps": 50,
}


def paper_value(protocol: str, interval: str, method: str, metric: str,
                dataset: str = "synthetic") -> PaperValue:
    """The paper's number for this cell, or a not-found marker."""
    if dataset not in DATASETS:
        raise ValueError(f"dataset must be one of {DATASETS}, got {dataset!r}")
    v = PAPER_NUMBERS.get((dataset, protocol, interval, method, metric))
    if v is not None:
        return v
    return PaperValue(
        None, f"no cell for {protocol}/{interval}/{method}/{metric} ({dataset})", NOT_FOUND
    )


def paper_rows(protocol: str, dataset: str = "synthetic") -> List[dict]:
    """All cells of one protocol (JSON-ready), for results.json."""
    return [
        {"interval": iv, "method": m, "metric": k, **v.to_json()}
        for (ds, p, iv, m, k), v in sorted(PAPER_NUMBERS.items())
        if p == protocol and ds == dataset
    ]


def paper_summary() -> dict:
    """What this module holds (JSON-ready)."""
    return {"paper": PAPER, "cells": len(PAPER_NUMBERS), "datasets": list(DATASETS)}
