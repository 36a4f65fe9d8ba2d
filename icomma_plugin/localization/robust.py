"""The default localizer.

A geometric stage, several hypotheses when needed, photometric refinement with roll-back, and a
verdict.

1. From the start pose (if any): render-match-PnP rounds (``geometric.py``).
2. When the pose the start leads to is not convincing (fewer than ``min_start_inliers`` agreeing
   matches, or a score the verdict would not call ok: a large rotation, a camera that sees
   little of the scene), or when there is no start: rank candidate views (``candidates.py``) and
   run the geometric stage from the best few; keep the best hypothesis by its verified score.
3. Photometric refinement of that pose (``refine.py``), checked by a render-and-match at the
   result: a refinement that loses agreeing matches is rolled back.
4. The verdict (``verify.py``) from the measured signals.

With a level of detail (``level_of_detail.py``) the geometric stage, the candidate renders and
(``refine_reduced``) the refinement use the Localizer's reduced model; the refinement's check and
the verdict the full model (a score the verdict reads is always of a full-model render: a
geometric score is measured again on the full model when it is the final one).
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ..camera import Intrinsics
from ..checks import check_bool, check_choice, check_int, check_real, config_from_dict
from ..pose.convert import invert_rigid, rotation_error_deg
from .candidates import CandidateConfig, usable
from .geometric import (GeometricConfig, GeometricOutcome, distortion_fits, focal_fits,
                        pose_motion, run_geometric)
from .geometry import FocalFit, distortion_shift_px, median_depth
from .refine import RefineConfig, refine_photometric
from .state import LocalizationState, Observation
from .types import MethodOutcome, Stage, TraceRecord
from .verify import PoseScore, VerdictConfig, decide, focal_disagrees, observe_and_score

logger = logging.getLogger(__name__)

__all__ = ["RobustConfig"]


@dataclass
class RobustConfig:
    """Constants of the default localizer (conf/optimizer/robust.yaml).

    work_side: longer side of the working resolution [px] (None: the query's own; the
        Localizer sets it to the model's training side when the model folder says it).
    min_start_inliers: when the geometric stage from the start pose ends with fewer agreeing
        matches than this, or with a score the verdict would not call ok, the candidate views are
        tried too.
    use_candidates: allow the candidate search at all.
    good_inliers: a hypothesis with this many agreeing matches (and a score the verdict calls
        ok) ends the search.
    rollback_inliers: the refined pose is kept only if it keeps this share of the agreeing
        matches of the geometric pose (and its median displacement grows by less than
        ``rollback_median_px``).
    focal_retry: when the verdict's intrinsics check (``verdict.ok_focal_scale``) finds the final
        render's matches asking for another focal length, refine once more with the focal length
        free (as ``refine.focal``, from the matches' fit) and keep that pose when it passes the
        roll-back test and the check, and its render compares with the photo better than the
        first pose's (``details["focal_retry_loss"]``: the two photometric losses);
        ``details["focal_scale"]`` then says the estimate and the result's intrinsics are the
        estimated ones. It costs time only on such photos (none of the real captures' right
        ones): fox's held-out photos given a focal length 4 or 8 % off, 0.15-0.92 deg ->
        0.02-0.04 (median; docs/LOCALIZATION.md). Tried only where
        ``refine.can_estimate_focal`` (the refinement's defaults).
    lens_check: the verdict refits the final render's matches with the lens distortion free
        (``signals.distortion``, 3-4 ms a pose), which a batch of photos given one camera pools
        (``app.lens``), as a sequence does its first frames'; it does not move the verdict. Off
        in tracking's fast mode once the sequence's lens is decided.
    verify_geometric: when the refinement takes no step (``refine.iterations`` 0) and the geometric
        stage converged, the verdict is decided on the geometric stage's last render-and-match
        (at most ``geometric.stop_rot_deg`` from the returned pose, the PnP step that ended the
        stage) instead of a new render-and-match at the returned pose. Tracking's fast mode sets
        it (one matcher call a frame instead of two; docs/SPEED.md); the result's
        ``details["verified_on"]`` says which render decided.
    verify_near: when the refined pose is within the geometric stage's stop (``geometric.
        stop_rot_deg``, ``stop_trans_rel`` of the scene depth) of the stage's last render-and-match,
        and that render's score alone would be ``ok``, the verdict is decided on it too (as
        ``verify_geometric``) instead of a new render-and-match at the returned pose: a pose that
        close to a render the verdict calls right is right, and the matcher's second call at
        nearly the same pose costs a pose 3-14 % (docs/SPEED.md). A refinement that moved
        further, a render that is not ``ok`` alone, or a render of a reduced model (with a level
        of detail the stage renders the full one near the answer:
        ``geometric.full_model_within_deg``) is checked as before, and so can be rolled back.
        ``details["verified_on"]`` says which render decided.
    refine_reduced: with a level of detail, the photometric refinement renders the reduced model
        too (its check and the verdict always render the full model). Off by default: the pose is
        then the reduced model's optimum. On the 1M-Gaussian lego at 800 px a pose took 0.47x the
        time at the same error, but on the demo scene capped at 60 % of its Gaussians the poses
        ended 0.45 deg off instead of under 0.1 (docs/SPEED.md). For models whose reduced model
        renders like the full one at the working resolution.
    refine_model_side: with a ``work_side`` above the model's training side (``at_model_side``),
        the photometric refinement compares render and photo at the model's side (its levels'
        ``scales`` divided by ``work_side / model_side``); the geometric stage still matches, and
        the verdict still judges, at the working side. A model has no detail finer than the
        photos it was fitted on, and compared above it the pose drifted: lego's 200-px model at
        400 px, median 0.094 -> 0.036 deg; its 300k and 1M splits at 800 px, 0.191 -> 0.076 and
        0.122 -> 0.048 deg, in 0.71x and 0.64x the time (docs/SPEED.md). At or below the
        model's side (the default working side, every real capture here) nothing changes.
    mutual_nn: None: renders are matched to the query by the matcher (LightGlue, ...); a cosine
        in (0, 1): by mutual nearest neighbours of the matcher's descriptors above it
        (``matchers.mutual_nn``), for a matcher with features (``supports_features``). Several
        times cheaper, and enough between a render and a photo from nearly the same pose:
        tracking's fast mode (``tracking.fast_mutual_nn``).
    patch_search: None, or a window in pixels: renders are matched to the query by searching each
        of the query's keypoints (the matcher's features, extracted once) in the render within
        that window of the same position, by normalised cross-correlation above
        ``patch_search_ncc`` (``matchers.patch_search``, with ``geometric.subpixel_iterations``
        Newton iterations): no features of the render, and matches sub-pixel already, so the
        PnP's sub-pixel step is not run again. A render that keeps fewer than 30 % of the
        keypoints, or whose matches move by more than half the window, is matched as without it
        (``mutual_nn`` or the matcher). In the default method (lego 200, seed 2024, 10 starts)
        it saved a tenth of a pose and made two poses' errors larger: off by default. For renders
        within a few pixels of the photo, on request: tracking's fast mode
        (``tracking.fast_patch_search``, off by default: on photo collections and soft models
        it falls back more often than it serves, and costs time; docs/SPEED.md).
    patch_search_margin: keep only the patch search's matches whose NCC peak stands this much
        above the best score 2 or more pixels from it (``matchers.patch_search``'s
        ``min_margin``; None: no such test): a flat NCC surface (a soft render, texture-less or
        repeating patches) does not say where a keypoint is, and its matches stay where they
        were. Without it, goldcape tracked as a sequence had a frame called ``ok`` 1.1 deg off;
        with 0.1 none, and the fast mode settled as many frames as with descriptors
        (docs/SPEED.md).

    Its results' ``details``: ``hypotheses`` (one summary per start tried), ``rolled_back``,
    ``refine_iterations``, ``refine_loss`` ([before, after]) and ``start_render_empty``; with
    the intrinsics check's retry ``focal_retry``, ``focal_retry_loss`` and ``focal_scale``.
    """

    work_side: Optional[int] = None
    min_start_inliers: int = 40
    use_candidates: bool = True
    good_inliers: int = 80
    rollback_inliers: float = 0.9
    rollback_median_px: float = 0.5
    verify_geometric: bool = False
    verify_near: bool = True
    focal_retry: bool = True
    lens_check: bool = True
    refine_reduced: bool = False
    refine_model_side: bool = True
    mutual_nn: Optional[float] = None
    patch_search: Optional[int] = None
    patch_search_ncc: float = 0.8
    patch_search_margin: Optional[float] = 0.1
    sh_degree: Optional[int] = None
    antialiasing: bool = False
    record_trace: bool = True
    geometric: GeometricConfig = field(default_factory=GeometricConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    verdict: VerdictConfig = field(default_factory=VerdictConfig)

    #: The method's name in results and reports.
    name = "robust"
    #: The method can start without a start pose (from the candidate views).
    needs_start = False

    def __post_init__(self):
        # Nested groups may come as mappings (Hydra's instantiate, JSON): build their dataclasses.
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, dict) and f.default_factory is not dataclasses.MISSING:
                setattr(self, f.name,
                        config_from_dict(type(f.default_factory()), v, f"RobustConfig.{f.name}"))
        n = "RobustConfig."
        check_int(self.work_side, n + "work_side", 16, optional=True)
        for name in ("min_start_inliers", "good_inliers"):
            check_int(getattr(self, name), n + name, 0)
        check_real(self.rollback_inliers, n + "rollback_inliers", 0.0, 1.0)
        check_real(self.rollback_median_px, n + "rollback_median_px", 0.0)
        check_real(self.mutual_nn, n + "mutual_nn", 0.0, 1.0, lo_open=True, hi_open=True,
                   optional=True)
        check_int(self.patch_search, n + "patch_search", 1, optional=True)
        check_real(self.patch_search_ncc, n + "patch_search_ncc", -1.0, 1.0)
        check_real(self.patch_search_margin, n + "patch_search_margin", 0.0, optional=True)
        if self.sh_degree is not None:
            check_choice(self.sh_degree, n + "sh_degree", (0, 1, 2, 3))
        for name in ("use_candidates", "antialiasing", "record_trace", "verify_geometric",
                     "verify_near", "focal_retry", "lens_check", "refine_reduced",
                     "refine_model_side"):
            check_bool(getattr(self, name), n + name)

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "RobustConfig":
        """From a plain (nested) mapping, e.g. a Hydra group; unknown keys raise ValueError."""
        return config_from_dict(cls, d, "RobustConfig")

    def to_dict(self) -> Dict[str, Any]:
        """The config as a nested dict (as `from_dict` reads it)."""
        return dataclasses.asdict(self)

    def at_model_side(self, intrinsics: Intrinsics, model_side: Optional[int],
                      scale_pixels: bool = True) -> "RobustConfig":
        """This config for a model fitted on images of ``model_side`` px (longer side).

        Without its own ``work_side`` it works at ``model_side``. With a larger one the pixel
        thresholds of the score and the verdict (``verdict.*_px``, ``geometric.inlier_px``,
        ``rollback_median_px``) grow by ``work_side / model_side``: the model's renders are no
        sharper than its own pixels, so a pose is judged in them (a lego model fitted at
        200 px, localized at 800 px, agreed within 0.8-1.0 px of 800 px at 0.04-0.11 deg, under
        the 0.8 px mean of the default verdict, and every start searched the candidate views).
        With ``refine_model_side`` the refinement's levels are divided by the same factor.
        """
        if model_side is None:
            return self
        if self.work_side is None:
            return dataclasses.replace(self, work_side=model_side)
        factor = self.work_side / model_side
        if factor <= 1.0 or not scale_pixels:
            return self
        refine = self.refine
        if self.refine_model_side:  # compared in the model's pixels: its levels / factor
            refine = dataclasses.replace(refine, scales=tuple(s / factor for s in refine.scales))
        return dataclasses.replace(
            self, verdict=self.verdict.pixels_scaled(factor),
            rollback_median_px=self.rollback_median_px * factor, refine=refine,
            geometric=dataclasses.replace(self.geometric,
                                          inlier_px=self.geometric.inlier_px * factor))

    def work_scale(self, intrinsics: Intrinsics) -> float:
        """The working scale of a query with ``intrinsics``: its longer side at ``work_side``."""
        return 1.0 if self.work_side is None else intrinsics.scale_to_side(self.work_side)

    def needs(self, matcher) -> Optional[str]:
        """Why this method cannot run with ``matcher`` (None when it can)."""
        if matcher is None or getattr(matcher, "name", None) == "none":
            return ("the default localizer needs a matcher (matcher=none only works with the "
                    "paper's optimizer=icomma or compare_only)")
        if self.mutual_nn is not None and not getattr(matcher, "supports_features", False):
            return (f"RobustConfig.mutual_nn matches the matcher's descriptors, but the "
                    f"{getattr(matcher, 'name', type(matcher).__name__)!r} matcher has none "
                    "(supports_features is False): set mutual_nn to null")
        if self.patch_search is not None and not getattr(matcher, "supports_features", False):
            return (f"RobustConfig.patch_search searches the matcher's keypoints of the query, "
                    f"but the {getattr(matcher, 'name', type(matcher).__name__)!r} matcher has "
                    "none (supports_features is False): set patch_search to null")
        return None

    def run(self, state: LocalizationState, init_w2c: Optional[np.ndarray]) -> MethodOutcome:
        """The default localizer on ``state`` from ``init_w2c`` (None: candidate views alone)."""
        scale = self.work_scale(state.query.intrinsics)
        search = _Search(state, self, scale)
        with state.serving("geometric", reduced=True):
            search.from_start(init_w2c)
            if search.needs_candidates():
                search.from_candidates()
        if search.best is None or search.best.score is None \
                or search.best.score.inliers < self.verdict.fail_inliers:
            return search.unrefined()
        return _refine_and_verify(state, self, scale, search)


def _summary(name: str, g: GeometricOutcome, state: LocalizationState) -> Dict[str, Any]:
    rot, trans = state.errors(g.w2c)
    return {"start": name, "rounds": g.rounds, "first_pnp_inliers": g.first_pnp_inliers,
            "pnp_inliers": g.pnp_inliers, "converged": g.converged,
            "score": None if g.score is None else g.score.to_json(), "joined": g.joined,
            "start_coverage": g.start_coverage, "rot_err_deg": rot, "trans_err": trans}


def _convincing(
    score: Optional[PoseScore], cfg: RobustConfig, min_inliers: Optional[int] = None
) -> bool:
    """A geometric result that needs no other hypothesis.

    The verdict would call it ok (but for the convergence signal, which only the refinement gives)
    with at least ``min_inliers``.
    """
    if score is None or score.inliers < (
        cfg.min_start_inliers if min_inliers is None else min_inliers
    ):
        return False
    return decide(score, cfg.verdict, converged=True).status == "ok"


def _better(a: GeometricOutcome, b: Optional[GeometricOutcome]) -> bool:
    if b is None:
        return True
    if a.score is None:
        return False
    return a.score.better_than(b.score)


def _support(g: GeometricOutcome) -> int:
    """How much agrees with a hypothesis.

    The render's agreeing matches and the last PnP's inliers (its pooled render and photo
    correspondences).
    """
    return g.score.inliers + (g.pnp_inliers[-1] if g.pnp_inliers else 0)


#: A rival hypothesis whose proposal comes within this share of ``rival_deg`` of the best pose
#: (and near its centre) has joined it: its rounds stop there (``run_geometric``'s ``join``),
#: when the best hypothesis converged before its last round (goldcape's IMG_5913: the best
#: converged in the last of its 8 rounds, 0.61 deg off, and the rival that would have joined it
#: ended 0.37 deg off with more agreeing matches, 260 against 241).
RIVAL_JOIN_SHARE = 0.5


def _rival(hyps: List[Tuple[str, GeometricOutcome]], best: Optional[GeometricOutcome],
           cfg: RobustConfig, tie: float = 0.15) -> Optional[Dict[str, Any]]:
    """The hypothesis far from ``best`` whose support is within ``tie`` of the best's, if any."""
    if best is None or best.score is None:
        return None
    best_c2w = invert_rigid(best.w2c)
    rivals = []
    for name, g in hyps:
        if g is best or g.score is None or g.joined:
            continue
        apart = float(rotation_error_deg(invert_rigid(g.w2c), best_c2w))
        if apart > cfg.candidates.rival_deg and _support(g) >= (1.0 - tie) * _support(best):
            rivals.append({"start": name, "rot_deg_apart": apart, "support": _support(g),
                           "best_support": _support(best), "inliers": g.score.inliers})
    return max(rivals, key=lambda r: r["support"]) if rivals else None


class _Search:
    """The hypotheses of one localization: from the start pose, then from candidate views."""

    def __init__(self, state: LocalizationState, cfg: RobustConfig, scale: float):
        self.state, self.cfg, self.scale = state, cfg, scale
        self.hyps: List[Tuple[str, GeometricOutcome]] = []
        self.best: Optional[GeometricOutcome] = None
        self.rival: Optional[Dict[str, Any]] = None
        self.fallback_w2c: Optional[np.ndarray] = None
        self.empty_start = False
        self.had_start = False

    def from_start(self, init_w2c: Optional[np.ndarray]) -> None:
        """The geometric stage from the start pose (when there is one)."""
        if init_w2c is None:
            return
        self.had_start = True
        self.fallback_w2c = np.asarray(init_w2c, np.float64)
        g = run_geometric(self.state, init_w2c, self.cfg.geometric, self.scale, hypothesis=0)
        self.hyps.append(("start", g))
        self.best = g
        self.empty_start = g.start_coverage < self.cfg.verdict.fail_coverage

    def needs_candidates(self) -> bool:
        """Whether the candidate views are searched (no start, or an unconvincing one)."""
        need = not self.had_start or not _convincing(self.best.score, self.cfg)
        return (need and self.cfg.use_candidates and usable(self.state.matcher)
                and self.state.candidates is not None)

    def from_candidates(self) -> None:
        """Rank the candidate views, run the geometric stage from the best few."""
        state, cfg = self.state, self.cfg
        found = state.candidates()
        if found is None:
            return
        index, excluded = found
        order = index.rank(state, cfg.candidates, excluded)
        if self.fallback_w2c is None and order:
            self.fallback_w2c = index.start_w2c(*order[0])
        state.record(TraceRecord(iteration=state.steps, stage=Stage.CANDIDATES, matches=len(order)))
        ran = set()
        for rank, (idx, turns) in enumerate(order[: cfg.candidates.top_k]):
            if index.features[idx] is None:
                continue
            ran.add(idx)
            self._run_candidate(index, idx, turns, rank + 1)
            if _convincing(self.best.score, cfg, cfg.good_inliers):
                break
        self._run_rival(index, order, ran)
        self.rival = _rival(self.hyps, self.best, cfg)

    def _run_candidate(self, index, idx: int, turns: int, hypothesis: int,
                       note: str = "", join: Optional[Tuple[np.ndarray, float]] = None) -> None:
        g = run_geometric(self.state, index.start_w2c(idx, turns), self.cfg.geometric, self.scale,
                          hypothesis=hypothesis, join=join)
        name = index.source[idx] + (f" turned {90 * turns} deg" if turns else "") + note
        self.hyps.append((name, g))
        if not g.joined and _better(g, self.best):
            self.best = g

    def _run_rival(self, index, order: List[Tuple[int, int]], ran: set) -> None:
        """Run the best-ranked candidate far from the best pose, if it ranked almost as well.

        Two places that look alike (a repeating floor, a symmetric object) rank close; the best
        one convincing alone does not rule the other out.
        """
        cc = self.cfg.candidates
        if self.best is None or self.best.score is None or not order:
            return
        counts = index.last_counts
        top = max(counts[order[0][0]], 1)
        best_c2w = invert_rigid(self.best.w2c)
        for idx, turns in order[: 2 * cc.top_k]:
            if counts[idx] < cc.rival_share * top:
                return  # ranked in decreasing count: no later one ranks close
            if idx in ran or index.features[idx] is None:
                continue
            start_c2w = invert_rigid(index.start_w2c(idx, turns))
            if float(rotation_error_deg(start_c2w, best_c2w)) > cc.rival_deg:
                # stopped once it leads to the best pose (a rival only where it goes elsewhere)
                # when that converged before its last round; to one that did not, the rival's
                # rounds are a second descent into its basin, which may end better
                settled = self.best.converged and self.best.rounds < self.cfg.geometric.max_rounds
                join = (self.best.w2c, RIVAL_JOIN_SHARE * cc.rival_deg) if settled else None
                self._run_candidate(index, idx, turns, len(self.hyps) + 1, " (rival)", join=join)
                return

    def summaries(self) -> List[Dict[str, Any]]:
        """One summary per hypothesis tried (the result's ``details["hypotheses"]``)."""
        return [_summary(n, g, self.state) for n, g in self.hyps]

    def unrefined(self) -> MethodOutcome:
        """The outcome when no hypothesis is good enough to refine (the verdict says failed)."""
        best = self.best
        w2c = best.w2c if best is not None else self.fallback_w2c
        if w2c is None:  # no start and no candidate view: nothing to report but the identity
            w2c = np.eye(4)
        score = None if best is None else _full_model_score(self.state, best, self.scale,
                                                             self.cfg.verdict.inlier_px)[0]
        verdict = decide(score, self.cfg.verdict, converged=None,
                         extra={"start_render_empty": self.empty_start,
                                "hypotheses": len(self.hyps)})
        if self.empty_start and verdict.status == "failed":
            verdict.reason += ("; the render at the start pose was empty (it looks away from the "
                               "scene): give a start that sees the scene, or none (init=none)")
        return MethodOutcome(np.asarray(w2c, np.float64), verdict, score, self.state.steps,
                             "max_iterations", {"hypotheses": self.summaries(),
                                                "rolled_back": False, "refine_iterations": 0})


def _on_reduced(state: LocalizationState, stage: str) -> bool:
    """Whether a reduced model (level of detail) rendered ``stage``."""
    return state.rendered.get(stage, {}).get("reduced", False)


def _full_model_score(state: LocalizationState, g: GeometricOutcome, scale: float,
                      inlier_px: float) -> Tuple[Optional[PoseScore], Optional[Observation]]:
    """``g``'s score and the render it scores, measured again on the full model if reduced."""
    if g.score is None or not g.observation.reduced:
        return g.score, g.observation
    with state.serving("verify"):
        return observe_and_score(state, g.w2c, scale, inlier_px)


#: The matches' fit of the focal length is taken only when it reprojects them this much better
#: (median error) than the pose alone: on goldcape (a long lens, a foggy fit) with its focal
#: length given right, taken always it moved it 0.6 % and the poses 0.09 -> 0.14 deg.
FOCAL_FIT_GAIN = 0.9


def _focal_from_matches(state: LocalizationState, cfg: RobustConfig,
                        g: GeometricOutcome) -> np.ndarray:
    """The refinement's start with the focal length free, from the best render's matches.

    The pose and focal scale that best reproject them (``geometric.focal_fits``; sets
    ``state.focal_scale``) when that fit is ``FOCAL_FIT_GAIN`` better than the pose's alone;
    else ``g``'s pose as it is (too few matches, or none asking for another focal length).

    The photometric steps along the valley where the focal length trades against the camera's
    distance are short; the matches' reprojection gets there in a few milliseconds.
    """
    obs = g.observation
    if obs is None or obs.matches is None:
        return g.w2c
    with state.timed("pnp"):
        fits = focal_fits(state, obs, cfg.geometric)
    if fits is None or fits[0].median_px > FOCAL_FIT_GAIN * fits[1].median_px:
        return g.w2c  # left to the photometric steps
    state.focal_scale = fits[0].focal_scale
    return fits[0].w2c


def _focal_signal(state: LocalizationState, cfg: RobustConfig, obs: Optional[Observation]
                  ) -> Tuple[Optional[Dict[str, float]], Optional[FocalFit]]:
    """The verdict's intrinsics check at the final pose (``VerdictConfig.ok_focal_scale``).

    The final render's matches fitted with the focal length free: ``scale`` (of the focal length
    the pose holds with), ``rms_px`` and ``rms_px_given`` (the pose alone), the root mean square
    reprojection errors that the fits minimise (a median of a detector's integer keypoints can
    miss the gain); and that free fit. ``(None, None)`` when the check is off or there are too
    few matches.
    """
    if cfg.verdict.ok_focal_scale is None or obs is None or obs.matches is None:
        return None, None
    with state.timed("verify"):
        fits = focal_fits(state, obs, cfg.geometric)
    if fits is None:
        return None, None
    free, fixed = fits
    return {"scale": round(free.focal_scale, 5), "rms_px": round(free.rms_px, 4),
            "rms_px_given": round(fixed.rms_px, 4)}, free


def _distortion_signal(state: LocalizationState, cfg: RobustConfig, obs: Optional[Observation],
                       focal: Optional[Dict[str, float]] = None) -> Optional[Dict[str, Any]]:
    """The lens check at the final pose: a signal of the verdict, which it does not decide.

    The final render's matches fitted with the photo's lens distortion free (a render is a
    pinhole image; a photo whose lens distortion was not removed is not): ``coefficients``
    (OpenCV's k1, k2, p1, p2), ``shift_px`` (what they move a pixel by, at most, within the
    matches' reach, at the working size), ``reach`` (that largest normalised radius) and
    ``focal_px`` (the focal length of those pixels), ``rms_px`` and ``rms_px_given`` (the pose
    alone: the focal check's ``focal`` signal of the same render gives it); for a photo given no
    principal point (the image centre taken) ``centre``, the principal point's move the refit
    finds, in focal lengths (fitted with k1, k2 only: the tangential terms would stand for it).
    None with too few matches. One photo's coefficients scatter with its matches (bird's soft
    photos, undistorted, fit up to 9 px of it), so a batch pools them (``app.lens``).
    """
    if obs is None or obs.matches is None:
        return None
    with state.timed("verify"):
        fits = distortion_fits(state, obs, cfg.geometric,
                               None if focal is None else focal.get("rms_px_given"))
    if fits is None:
        return None
    free, rms_given = fits
    intr = state.intrinsics_at(obs.scale)
    fx = float(intr.fx)
    out = {"coefficients": [round(v, 6) for v in free.coefficients],
           "shift_px": round(distortion_shift_px(free.coefficients, free.max_radius, fx), 4),
           "reach": round(free.max_radius, 4), "focal_px": round(fx, 3),
           "rms_px": round(free.rms_px, 4), "rms_px_given": round(rms_given, 4)}
    if free.centre_px is not None:  # the image centre was taken: where the refit puts it
        out["centre"] = [round(free.centre_px[0] / fx, 6), round(free.centre_px[1] / fx, 6)]
    return out


def _near_geometric(cfg: RobustConfig, best: GeometricOutcome, w2c: np.ndarray,
                    depth: float) -> bool:
    """Whether ``best``'s last render-and-match may decide the verdict of ``w2c`` (``verify_near``).

    That render is of the full model, its score alone is ``ok``, and ``w2c`` is within the
    geometric stage's stop of the pose it rendered.
    """
    obs = best.observation
    if obs is None or not best.converged or obs.reduced \
            or not _convincing(best.score, cfg, min_inliers=cfg.verdict.ok_inliers):
        return False
    rot, trans = pose_motion(obs.w2c, w2c)
    g = cfg.geometric
    return rot <= g.stop_rot_deg and trans <= g.stop_trans_rel * depth


def _passes_rollback(sc: PoseScore, geo: PoseScore, cfg: RobustConfig) -> bool:
    """Whether a refined pose's score keeps the geometric one's agreement (else rolled back)."""
    return (sc.inliers >= cfg.rollback_inliers * geo.inliers
            and sc.median_px <= geo.median_px + cfg.rollback_median_px)


def _retry_focal_free(state: LocalizationState, cfg: RobustConfig, scale: float, free: FocalFit,
                      depth: float, geo: PoseScore, loss: Optional[float]):
    """The refinement again with the focal length free, from the matches' fit ``free``.

    ``((refinement, score, judged render, focal signal), its loss)``; the first is None (and
    the state's focal length restored) unless its pose passes the roll-back test against the
    geometric stage's score ``geo`` and the intrinsics check, and its render compares with the
    photo better than the first pose's did (``loss``, the photometric loss there; None: not
    asked). The last test tells a focal length that is off from a refit that trades it against
    the distance on an object in the middle of the frame: on bird's training photo 002.jpg,
    whose model was fitted at its recorded focal length, the matches asked for 1.04x and the
    pose moved 0.05 -> 0.56 deg off its record with the loss 1 % higher.
    """
    f0 = state.focal_scale
    state.focal_scale = f0 * free.focal_scale
    rcfg = dataclasses.replace(cfg.refine, focal=True)
    with state.serving("refine", reduced=cfg.refine_reduced):
        ref = refine_photometric(state, free.w2c, rcfg, base_scale=scale, scene_depth=depth)
    last = None if _on_reduced(state, "refine") else ref.observation
    with state.serving("verify"):
        sc, judged = observe_and_score(state, ref.w2c, scale, cfg.verdict.inlier_px, last)
    signal, _ = _focal_signal(state, cfg, judged)
    better = loss is None or (ref.loss_end is not None and ref.loss_end < loss)
    keep = better and _passes_rollback(sc, geo, cfg) and not focal_disagrees(signal, cfg.verdict)
    state.record(state.new_record(Stage.VERIFY, ref.w2c, matches=sc.matches, inliers=sc.inliers,
                                  accepted=keep, scale=scale))
    if not keep:
        logger.info("refinement with the focal length free not kept (%d agreeing matches, "
                    "loss %s against %s)", sc.inliers, ref.loss_end, loss)
        state.focal_scale = f0
        return None, ref.loss_end
    logger.info("focal length estimated at %.4f x the given one (the verdict's check asked)",
                state.focal_scale)
    return (ref, sc, judged, signal), ref.loss_end


def _refine_and_verify(state: LocalizationState, cfg: RobustConfig, scale: float,
                       search: _Search) -> MethodOutcome:
    """Photometric refinement of the best hypothesis, checked by a render-and-match."""
    best = search.best
    depth = median_depth(best.observation.depth, best.observation.alpha)
    start = best.w2c
    if cfg.refine.focal:  # the focal length first from the matches' reprojection (no render)
        start = _focal_from_matches(state, cfg, best)
    with state.serving("refine", reduced=cfg.refine_reduced):
        ref = refine_photometric(state, start, cfg.refine, base_scale=scale,
                                 scene_depth=depth)
    geo = best.score
    # (not when the matches' focal fit moved the pose and focal length off that render's)
    reuse = (cfg.verify_geometric and ref.iterations == 0 and best.converged
             and start is best.w2c and not best.observation.reduced)
    reuse = reuse or (cfg.verify_near and start is best.w2c
                      and _near_geometric(cfg, best, ref.w2c, depth))
    if reuse:  # the PnP step that ended the geometric stage was below its stop: judged there
        sc, judged = geo, best.observation
    else:  # the refinement's last render is judged when it is of the full model
        last = None if _on_reduced(state, "refine") else ref.observation
        with state.serving("verify"):
            sc, judged = observe_and_score(state, ref.w2c, scale, cfg.verdict.inlier_px, last)
    keep = _passes_rollback(sc, geo, cfg)
    state.record(state.new_record(Stage.VERIFY, ref.w2c, matches=sc.matches, inliers=sc.inliers,
                                  accepted=keep, scale=scale))
    if keep:
        w2c, score = ref.w2c, sc
    else:
        logger.info(
            "photometric refinement rolled back: %d -> %d agreeing matches", geo.inliers, sc.inliers
        )
        state.focal_scale = 1.0  # the geometric pose's (the recorded focal length)
        w2c = best.w2c
        score, judged = _full_model_score(state, best, scale, cfg.verdict.inlier_px)
    focal, free = _focal_signal(state, cfg, judged)
    retry = None  # what became of the intrinsics check's request for another focal length
    retry_loss = None  # [the first pose's photometric loss, the retry's]
    if free is not None and not cfg.refine.focal and focal_disagrees(focal, cfg.verdict):
        retry = "off"
        if cfg.focal_retry and cfg.refine.can_estimate_focal:
            first_loss = ref.loss_end if keep else ref.loss_start
            retried, retried_loss = _retry_focal_free(state, cfg, scale, free, depth, geo,
                                                      first_loss)
            retry_loss = [first_loss, retried_loss]
            retry = "not kept" if retried is None else "kept"
            if retried is not None:
                ref, score, judged, focal = retried
                w2c, keep = ref.w2c, True
    # (``focal``: the intrinsics check of this same render, whose pose-alone fit it reuses)
    distortion = _distortion_signal(state, cfg, judged, focal) if cfg.lens_check else None
    extra = {
        "start_render_empty": search.empty_start,
        "hypotheses": len(search.hyps),
        "ambiguous": search.rival is not None,
        "rival": search.rival,
        "refine_rolled_back": not keep,
        "refine_iterations": ref.iterations,
        "refine_loss": [ref.loss_start, ref.loss_end],
    }
    if focal is not None:
        extra["focal"] = focal
    if distortion is not None:
        extra["distortion"] = distortion
    if retry is not None:
        extra["focal_retry"] = retry
    # Whether the pose stopped moving is said by the last stage that moved it: the refinement, or
    # the geometric stage when the refinement took no step or was rolled back.
    converged = (ref.converged if ref.iterations > 0 else best.converged) or not keep
    verdict = decide(score, cfg.verdict, converged=converged, extra=extra)
    if search.empty_start:
        verdict.reason += (
            "; note: the render at the start pose was empty (relocalized from candidate views)"
        )
    stop = "rolled_back" if not keep else ("converged" if converged else "max_iterations")
    details = {"hypotheses": search.summaries(), "rival": search.rival, "rolled_back": not keep,
               "refine_iterations": ref.iterations, "refine_loss": [ref.loss_start, ref.loss_end],
               "start_render_empty": search.empty_start,
               "verified_on": "geometric" if reuse and retry != "kept" else "final"}
    if cfg.refine.focal or retry == "kept":  # the focal lengths' scale the pose holds with
        details["focal_scale"] = state.focal_scale
    if retry is not None:
        details["focal_retry"] = retry
    if retry_loss is not None:
        details["focal_retry_loss"] = retry_loss
    return MethodOutcome(np.asarray(w2c, np.float64), verdict, score, state.steps, stop, details)
