"""Check a pose without ground truth.

Render there, match the render against the query, and measure how well the two agree; turn the
measurements into a verdict.

The central signal needs no 3D reasoning: at the right pose the render and the photo show the
same thing at the same place, so a match between them has (almost) no displacement. A match is an
*inlier* of the pose when its render and query keypoints lie within ``inlier_px`` of each other.
The other signals (share of inliers, their median displacement and spread, the photometric
residual on the covered area, how much of the photo the render covers, whether the optimiser
stopped moving) catch what the inlier count alone misses.

Thresholds of :class:`VerdictConfig` were calibrated on the benchmark (docs/BENCHMARK.md): the
poses called ``ok`` there were right (< 5 deg, < 0.05).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any, Dict, Optional, Tuple

import numpy as np
import torch

from ..checks import check_int, check_real
from .state import LocalizationState, Observation
from .types import Verdict

__all__ = [
    "PoseScore",
    "VerdictConfig",
    "can_match",
    "coverage_mask",
    "decide",
    "focal_disagrees",
    "observe_and_score",
    "score_observation",
    "score_pose",
    "verify_pose",
]


@dataclass
class PoseScore:
    """What a render-and-match at one pose says about that pose (see the module docstring).

    matches: matches found; inliers: those with a displacement below ``inlier_px``.
    median_px, mean_px: median and mean displacement of the inliers, in pixels of the matched
        images (the working resolution: matchers are about equally precise in their own pixels
        at any resolution). Detectors that return integer pixels make the median 0 at a good
        pose; the mean still resolves sub-pixel differences.
    spread: fraction of the image's bounding box spanned by the inliers (0 when < 3 inliers).
    coverage: fraction of the query's valid pixels where the render has alpha > 0.5 (or, with a
        query alpha, the intersection-over-union of the two silhouettes).
    photometric_rmse: RMS colour difference on the covered, valid pixels.
    """

    matches: int
    inliers: int
    median_px: float
    mean_px: float
    spread: float
    coverage: float
    photometric_rmse: float

    @property
    def inlier_ratio(self) -> float:
        """Inliers / matches (0 without matches)."""
        return self.inliers / self.matches if self.matches else 0.0

    def better_than(self, other: Optional["PoseScore"], tie: float = 0.02) -> bool:
        """Whether this score beats ``other`` (None is beaten by any score).

        More inliers than ``other`` by more than a share ``tie``, or about as many (within that
        share) with a smaller mean displacement.
        """
        if other is None:
            return True
        if self.inliers > other.inliers * (1.0 + tie):
            return True
        return self.inliers >= other.inliers * (1.0 - tie) and self.inliers > 0 \
            and self.mean_px < other.mean_px

    def to_json(self) -> Dict[str, Any]:
        """The score as JSON, with ``inlier_ratio``."""
        d = asdict(self)
        d["inlier_ratio"] = self.inlier_ratio
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()
        }


def coverage_mask(obs: Observation, state: LocalizationState) -> torch.Tensor:
    """``[1, H, W]`` float mask of the pixels the comparing loss uses at this observation.

    Valid query pixels where the render or the query (its alpha, when given) shows the scene.
    """
    q = state.query_at(obs.scale)
    cover = obs.alpha > 0.5
    if q.alpha is not None:
        cover = cover | (q.alpha > 0.5)
    m = cover.to(obs.alpha.dtype)
    if q.valid is not None:
        m = m * q.valid
    return m


def score_observation(obs: Observation, state: LocalizationState, inlier_px: float) -> PoseScore:
    """Score the pose of ``obs`` (which must hold matches) against the query.

    ``inlier_px`` is in pixels of the observation's (working) resolution.
    """
    q = state.query_at(obs.scale)
    W, H = q.intrinsics.width, q.intrinsics.height
    n_matches, inliers, median, mean, spread = 0, 0, float("inf"), float("inf"), 0.0
    m = obs.matches
    if m is not None and len(m) > 0:
        k0 = m.kpts0.detach().double().cpu().numpy()
        k1 = m.kpts1.detach().double().cpu().numpy()
        disp = np.linalg.norm(k0 - k1, axis=1)
        n_matches = len(disp)
        inl = disp < inlier_px
        inliers = int(inl.sum())
        if inliers:
            median = float(np.median(disp[inl]))
            mean = float(np.mean(disp[inl]))
        if inliers >= 3:
            pts = k1[inl]
            span = (pts.max(0) - pts.min(0)) / np.array([max(W - 1, 1), max(H - 1, 1)])
            spread = float(np.clip(span[0] * span[1], 0.0, 1.0))
    with torch.no_grad():
        rend_cover = obs.alpha > 0.5
        valid = q.valid > 0.5 if q.valid is not None else torch.ones_like(rend_cover)
        if q.alpha is not None:
            qa = (q.alpha > 0.5) & valid
            ra = rend_cover & valid
            union = float((qa | ra).sum())
            coverage = float((qa & ra).sum()) / union if union > 0 else 0.0
        else:
            coverage = float((rend_cover & valid).sum()) / max(float(valid.sum()), 1.0)
        mask = coverage_mask(obs, state)
        msum = float(mask.sum())
        if msum > 0:
            d2 = ((obs.color - q.rgb.to(obs.color.dtype)) ** 2 * mask).sum() / (3.0 * msum)
            rmse = float(torch.sqrt(d2))
        else:
            rmse = float("inf")
    return PoseScore(n_matches, inliers, median, mean, spread, coverage, rmse)


@dataclass
class VerdictConfig:
    """Thresholds of the verdict (calibrated on the benchmark, docs/BENCHMARK.md).

    ok_inliers / ok_ratio / ok_median_px / ok_mean_px / ok_spread / ok_coverage: all must hold
        for ``ok``.
    fail_inliers: fewer inliers than this is ``failed``; fail_coverage: a render covering less of
        the photo than this is ``failed`` (the pose sees almost none of the scene).
    inlier_px: displacement below which a match is an inlier [px at the working resolution].
    ok_focal_scale / ok_focal_gain: the intrinsics check (the default method's). The final
        render's matches are fitted by their reprojection with the focal length free; when that
        fit finds a focal length further than ``ok_focal_scale`` (a share) from the one the pose
        holds with AND reprojects them with a root mean square error at most ``ok_focal_gain``
        times the pose's alone, the pose is ``uncertain``: the photo's intrinsics are likely off,
        and a wrong focal length is made up for by a wrong distance (4 % -> 0.05 scene radii on
        fox). The default method first tries again with the focal length free
        (``RobustConfig.focal_retry``). On object-centred captures the matches seldom tell a
        focal length from a distance, and the check seldom asks (docs/LOCALIZATION.md).
        None: not checked.
    """

    inlier_px: float = 2.0
    ok_inliers: int = 30
    ok_ratio: float = 0.5
    ok_median_px: float = 1.0
    ok_mean_px: float = 0.8
    ok_spread: float = 0.04
    ok_coverage: float = 0.1
    fail_inliers: int = 8
    fail_coverage: float = 0.02
    ok_focal_scale: Optional[float] = 0.03
    ok_focal_gain: float = 0.9

    def __post_init__(self):
        for name in ("inlier_px", "ok_median_px", "ok_mean_px"):
            check_real(getattr(self, name), f"VerdictConfig.{name}", 0.0, lo_open=True)
        check_real(self.ok_focal_scale, "VerdictConfig.ok_focal_scale", 0.0, lo_open=True,
                   optional=True)
        check_real(self.ok_focal_gain, "VerdictConfig.ok_focal_gain", 0.0, 1.0, lo_open=True)
        for name in ("ok_ratio", "ok_spread", "ok_coverage", "fail_coverage"):
            check_real(getattr(self, name), f"VerdictConfig.{name}", 0.0, 1.0)
        for name in ("ok_inliers", "fail_inliers"):
            check_int(getattr(self, name), f"VerdictConfig.{name}", 0)

    def pixels_scaled(self, factor: float) -> "VerdictConfig":
        """These thresholds with their pixel ones (``*_px``) multiplied by ``factor``."""
        return replace(self, inlier_px=self.inlier_px * factor,
                       ok_median_px=self.ok_median_px * factor, ok_mean_px=self.ok_mean_px * factor)


def decide(score: Optional[PoseScore], cfg: VerdictConfig, converged: Optional[bool] = None,
           extra: Optional[Dict[str, Any]] = None) -> Verdict:
    """The verdict for a pose from its score (None: the pose could not be checked)."""
    signals: Dict[str, Any] = dict(extra or {})
    signals["converged"] = converged
    if score is None:
        return Verdict(
            "uncertain",
            "the pose could not be checked (no matcher to compare the render "
            "with the photo); pass a matcher to get a verdict",
            signals,
        )
    signals.update(score.to_json())
    if score.coverage < cfg.fail_coverage:
        return Verdict(
            "failed",
            f"the render at the estimated pose covers {100 * score.coverage:.1f}% "
            "of the photo: the pose sees almost none of the scene; start from another pose "
            "or without one (init=none)",
            signals,
        )
    if score.inliers < cfg.fail_inliers:
        return Verdict(
            "failed",
            f"only {score.inliers} of {score.matches} matches agree with the "
            "estimated pose: it is wrong, or the photo does not show this scene",
            signals,
        )
    problems = []
    if score.inliers < cfg.ok_inliers:
        problems.append(f"{score.inliers} agreeing matches (< {cfg.ok_inliers})")
    if score.inlier_ratio < cfg.ok_ratio:
        problems.append(
            f"{100 * score.inlier_ratio:.0f}% of the matches agree (< {100 * cfg.ok_ratio:.0f}%)"
        )
    if not score.median_px <= cfg.ok_median_px:
        problems.append(f"median displacement {score.median_px:.2f} px (> {cfg.ok_median_px:g})")
    if not score.mean_px <= cfg.ok_mean_px:
        problems.append(f"mean displacement {score.mean_px:.2f} px (> {cfg.ok_mean_px:g})")
    if score.spread < cfg.ok_spread:
        problems.append(f"agreeing matches span {100 * score.spread:.1f}% of the image (< "
                        f"{100 * cfg.ok_spread:.0f}%)")
    if score.coverage < cfg.ok_coverage:
        problems.append(f"the render covers {100 * score.coverage:.0f}% of the photo (< "
                        f"{100 * cfg.ok_coverage:.0f}%)")
    if converged is False:
        problems.append("the optimisation had not stopped moving")
    if focal_disagrees(signals.get("focal"), cfg):
        f = signals["focal"]
        todo = ("a localization with the focal length free did not pass either: check them"
                if signals.get("focal_retry") == "not kept" else
                "check them, or localize with the focal length free (refine.focal=true)")
        problems.append(
            f"the matches fit a focal length {f['scale']:.3f}x the one used better (rms "
            f"{f['rms_px']:.2f} against {f['rms_px_given']:.2f} px): the photo's intrinsics "
            f"look off, and the distance with them; {todo}")
    rival = signals.get("rival")
    if signals.get("ambiguous") and rival:
        problems.append(f"a rival pose {rival['rot_deg_apart']:.0f} deg away agrees almost as well "
                        f"({rival['support']} vs {rival['best_support']}): two places look alike")
    if problems:
        return Verdict("uncertain", "check this pose: " + "; ".join(problems), signals)
    return Verdict(
        "ok",
        # the mean first: with a detector's integer pixels the median of a good pose is 0
        f"{score.inliers} of {score.matches} matches agree, {score.mean_px:.2f} px apart on "
        f"average (median {score.median_px:.2f}), render covers {100 * score.coverage:.0f}% of "
        "the photo",
        signals,
    )


def focal_disagrees(focal: Optional[Dict[str, Any]], cfg: VerdictConfig) -> bool:
    """Whether the intrinsics check's fit (the ``focal`` signal) makes a pose uncertain."""
    if not focal or cfg.ok_focal_scale is None:
        return False
    try:
        scale, err, err_given = (float(focal[k]) for k in ("scale", "rms_px", "rms_px_given"))
    except (KeyError, TypeError, ValueError):
        return False
    return abs(scale - 1.0) > cfg.ok_focal_scale and err <= cfg.ok_focal_gain * err_given


def can_match(matcher) -> bool:
    """Whether ``matcher`` finds matches at all (None and the ``none`` matcher do not)."""
    return matcher is not None and getattr(matcher, "name", None) != "none"


def observe_and_score(state: LocalizationState, w2c: np.ndarray, scale: float, inlier_px: float,
                      observation: Optional[Observation] = None
                      ) -> Tuple[PoseScore, Observation]:
    """Render at ``w2c`` (or reuse ``observation``, a render there), match, score (timed verify).

    The one render-and-match that checks a final pose, for every method; returns the score and
    the render it scored, with its matches.
    """
    with state.timed("verify"):
        obs = observation
        if obs is None or obs.scale != scale:
            obs = state.observe(w2c, scale, match=False)
        obs.matches = state.match(obs.color, scale)
        obs.subpixel.clear()  # refined and lifted for other matches
        obs.lifted.clear()
        return score_observation(obs, state, inlier_px), obs


def score_pose(state: LocalizationState, w2c: np.ndarray, scale: float, inlier_px: float,
               observation: Optional[Observation] = None) -> PoseScore:
    """:func:`observe_and_score`'s score alone."""
    return observe_and_score(state, w2c, scale, inlier_px, observation)[0]


def verify_pose(state: LocalizationState, w2c: np.ndarray, scale: float, cfg: "VerdictConfig",
                converged: Optional[bool], extra: Optional[Dict[str, Any]] = None,
                observation: Optional[Observation] = None) -> Tuple[Verdict, Optional[PoseScore]]:
    """The verdict of the pose ``w2c`` and its score (None without a matcher to check with)."""
    if not can_match(state.matcher):
        return decide(None, cfg, converged, extra), None
    score = score_pose(state, w2c, scale, cfg.inlier_px, observation)
    return decide(score, cfg, converged, extra), score
