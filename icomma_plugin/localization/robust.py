"""The default localizer.

A geometric stage, several hypotheses when needed, photometric refinement with roll-back, and a
verdict.

1. From the start pose (if any): render-match-PnP rounds (``geometric.py``).
2. When the start gives too few PnP inliers (a large rotation, a camera that sees little of the
   scene), or when there is no start: rank candidate views (``candidates.py``) and run the
   geometric stage from the best few; keep the best hypothesis by its verified score.
3. Photometric refinement of that pose (``refine.py``), checked by a render-and-match at the
   result: a refinement that loses agreeing matches is rolled back.
4. The verdict (``verify.py``) from the measured signals.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..checks import check_bool, check_choice, check_int, check_real
from .candidates import CandidateConfig, CandidateSet, usable
from .geometric import GeometricConfig, GeometricOutcome, run_geometric
from .refine import RefineConfig, refine_photometric
from .state import LocalizationState
from .types import Stage, TraceRecord, Verdict
from .verify import PoseScore, VerdictConfig, decide, score_observation

logger = logging.getLogger(__name__)

__all__ = ["RobustConfig", "RobustOutcome", "localize_robust"]

#: Keys Hydra's instantiate reads (a config composed with ``_target_`` still builds with from_dict).
HYDRA_KEYS = ("_target_", "_convert_", "_recursive_", "_partial_")


@dataclass
class RobustConfig:
    """Constants of the default localizer (conf/optimizer/robust.yaml).

    work_side: longer side of the working resolution [px] (None: the query's own).
    min_start_inliers: when the geometric stage from the start pose ends with fewer agreeing
        matches than this, or with a score the verdict would not call ok, the candidate views are
        tried too.
    use_candidates: allow the candidate search at all.
    good_inliers: a hypothesis with this many agreeing matches (and a score the verdict calls
        ok) ends the search.
    rollback_inliers: the refined pose is kept only if it keeps this share of the agreeing
        matches of the geometric pose (and its median displacement grows by less than
        ``rollback_median_px``).
    """

    work_side: Optional[int] = None
    min_start_inliers: int = 40
    use_candidates: bool = True
    good_inliers: int = 80
    rollback_inliers: float = 0.9
    rollback_median_px: float = 0.5
    sh_degree: Optional[int] = None
    antialiasing: bool = False
    record_trace: bool = True
    geometric: GeometricConfig = field(default_factory=GeometricConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    verdict: VerdictConfig = field(default_factory=VerdictConfig)

    def __post_init__(self):
        # Nested groups may come as mappings (Hydra's instantiate, JSON): build their dataclasses.
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, dict) and f.default_factory is not dataclasses.MISSING:
                kind = type(f.default_factory())
                setattr(self, f.name, _from_dict(kind, v, f"RobustConfig.{f.name}"))
        n = "RobustConfig."
        check_int(self.work_side, n + "work_side", 16, optional=True)
        for name in ("min_start_inliers", "good_inliers"):
            check_int(getattr(self, name), n + name, 0)
        check_real(self.rollback_inliers, n + "rollback_inliers", 0.0, 1.0)
        check_real(self.rollback_median_px, n + "rollback_median_px", 0.0)
        if self.sh_degree is not None:
            check_choice(self.sh_degree, n + "sh_degree", (0, 1, 2, 3))
        for name in ("use_candidates", "antialiasing", "record_trace"):
            check_bool(getattr(self, name), n + name)

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "RobustConfig":
        """From a plain (nested) mapping, e.g. a Hydra group; unknown keys raise ValueError."""
        return _from_dict(cls, d, "RobustConfig")

    def to_dict(self) -> Dict[str, Any]:
        """The config as a nested dict (as `from_dict` reads it)."""
        return dataclasses.asdict(self)


def _from_dict(cls, d: Dict[str, Any], where: str):
    if not isinstance(d, dict):
        raise ValueError(f"{where} must be a mapping, got {type(d).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    d = {k: v for k, v in d.items() if k not in HYDRA_KEYS}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ValueError(f"unknown {where} keys {unknown}; known keys: {sorted(fields)}")
    kw = {}
    for k, v in d.items():
        default = (
            fields[k].default_factory()
            if fields[k].default_factory is not dataclasses.MISSING
            else None
        )
        if dataclasses.is_dataclass(default) and isinstance(v, dict):
            kw[k] = _from_dict(type(default), v, f"{where}.{k}")
        elif isinstance(v, list):
            kw[k] = tuple(v)
        else:
            kw[k] = v
    return cls(**kw)


@dataclass
class RobustOutcome:
    """What the default method ends with: the pose, its verdict and score, the hypotheses tried."""

    w2c: np.ndarray
    verdict: Verdict
    score: Optional[PoseScore]
    hypotheses: List[Dict[str, Any]]
    rolled_back: bool
    refine_iterations: int
    converged: bool


def work_scale(state: LocalizationState, cfg: RobustConfig) -> float:
    intr = state.query.intrinsics
    if cfg.work_side is None:
        return 1.0
    return min(1.0, float(cfg.work_side) / max(intr.width, intr.height))


def _summary(name: str, g: GeometricOutcome, state: LocalizationState) -> Dict[str, Any]:
    rot, trans = state.errors(g.w2c)
    return {"start": name, "rounds": g.rounds, "first_pnp_inliers": g.first_pnp_inliers,
            "pnp_inliers": g.pnp_inliers, "converged": g.converged,
            "score": None if g.score is None else g.score.to_json(),
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


def localize_robust(
    state: LocalizationState,
    init_w2c: Optional[np.ndarray],
    cfg: RobustConfig,
    cameras_c2w: Sequence[np.ndarray] = (),
    camera_names: Optional[Sequence[str]] = None,
    candidate_set: Optional[CandidateSet] = None,
) -> RobustOutcome:
    """Run the default localizer (module docstring) on ``state``.

    Args:
        state: scene, query and matcher.
        init_w2c: the start pose, or None (then the candidates alone are used).
        cfg: the constants.
        cameras_c2w: the model's cameras (candidate views), c2w; never the query's own camera.
        camera_names: their names (reports).
        candidate_set: a prebuilt :class:`CandidateSet` (reused across a batch), else built here
            when needed.
    """
    if state.matcher is None:
        raise ValueError("the default localizer needs a matcher (matcher=none only works with the "
                         "paper's optimizer=icomma or compare_only)")
    scale = work_scale(state, cfg)
    hyps: List[Tuple[str, GeometricOutcome]] = []
    best: Optional[GeometricOutcome] = None
    fallback_w2c = None if init_w2c is None else np.asarray(init_w2c, np.float64)
    empty_start = False
    if init_w2c is not None:
        g = run_geometric(state, init_w2c, cfg.geometric, scale, hypothesis=0)
        hyps.append(("start", g))
        best = g
        empty_start = g.start_coverage < cfg.verdict.fail_coverage
    need = init_w2c is None or not _convincing(best.score, cfg)
    if need and cfg.use_candidates and usable(state.matcher):
        cs = candidate_set
        if cs is None:
            cs = CandidateSet.build(state, cameras_c2w, cfg.candidates, camera_names)
        order = cs.rank(state, cfg.candidates)
        if fallback_w2c is None and order:
            fallback_w2c = cs.start_w2c(*order[0])
        state.record(TraceRecord(iteration=state.steps, stage=Stage.CANDIDATES, matches=len(order)))
        for rank, (idx, turns) in enumerate(order[: cfg.candidates.top_k]):
            if cs.features[idx] is None:
                continue
            g = run_geometric(
                state, cs.start_w2c(idx, turns), cfg.geometric, scale, hypothesis=rank + 1
            )
            hyps.append((cs.source[idx] + (f" turned {90 * turns} deg" if turns else ""), g))
            if _better(g, best):
                best = g
            if _convincing(best.score, cfg, cfg.good_inliers):
                break
    summaries = [_summary(n, g, state) for n, g in hyps]
    if best is None or best.score is None or best.score.inliers < cfg.verdict.fail_inliers:
        w2c = best.w2c if best is not None else fallback_w2c
        if w2c is None:  # no start and no candidate view: nothing to report but the identity
            w2c = np.eye(4)
        score = None if best is None else best.score
        verdict = decide(score, cfg.verdict, converged=None,
                         extra={"start_render_empty": empty_start, "hypotheses": len(hyps)})
        if empty_start and verdict.status == "failed":
            verdict.reason += ("; the render at the start pose was empty (it looks away from the "
                               "scene): give a start that sees the scene, or none (init=none)")
        return RobustOutcome(
            np.asarray(w2c, np.float64), verdict, score, summaries, False, 0, False
        )

    # photometric refinement of the best hypothesis, checked by a render-and-match
    depth = float(np.median(best.observation.depth[best.observation.alpha > 0.5].cpu().numpy())) \
        if bool((best.observation.alpha > 0.5).any()) else 1.0
    ref = refine_photometric(state, best.w2c, cfg.refine, base_scale=scale, scene_depth=depth)
    with state.timed("verify"):
        obs = ref.observation
        if obs is None or obs.scale != scale:
            obs = state.observe(ref.w2c, scale, match=False)
        obs.matches = state.match(obs.color, scale)
        sc = score_observation(obs, state, cfg.verdict.inlier_px)
    geo = best.score
    keep = (sc.inliers >= cfg.rollback_inliers * geo.inliers
            and sc.median_px <= geo.median_px + cfg.rollback_median_px)
    rec = state.new_record(
        Stage.VERIFY, ref.w2c, matches=sc.matches, inliers=sc.inliers, accepted=keep, scale=scale
    )
    state.record(rec)
    if keep:
        w2c, score = ref.w2c, sc
    else:
        logger.info(
            "photometric refinement rolled back: %d -> %d agreeing matches", geo.inliers, sc.inliers
        )
        w2c, score = best.w2c, geo
    extra = {
        "start_render_empty": empty_start,
        "hypotheses": len(hyps),
        "refine_rolled_back": not keep,
        "refine_iterations": ref.iterations,
        "refine_loss": [ref.loss_start, ref.loss_end],
    }
    verdict = decide(score, cfg.verdict, converged=ref.converged or not keep, extra=extra)
    if empty_start:
        verdict.reason += (
            "; note: the render at the start pose was empty (relocalized from candidate views)"
        )
    return RobustOutcome(
        np.asarray(w2c, np.float64),
        verdict,
        score,
        summaries,
        not keep,
        ref.iterations,
        ref.converged,
    )
