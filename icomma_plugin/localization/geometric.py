"""The geometric stage: render, match, lift the render keypoints to 3D, solve PnP; repeat.

It renders colour, depth and alpha at the current pose, matches the render against the query,
lifts the render keypoints to world points with the rendered depth, and solves PnP for the query
camera. Repeated from the new pose while it gets better.

Each round renders and matches at a pose, which both scores that pose
(``verify.score_observation``: how many matches agree with it) and proposes the next one (PnP). A
proposal is accepted only when its own render scores better than the best pose so far;
otherwise the stage keeps the best pose and stops, or, ``patience`` rounds in a row at most, goes
on from that render's own proposal (a score can dip on the way to the right pose); such a render
whose own proposal barely moves it, within ``fixed_point_tie`` of the best's score, ends the
stage there. It also stops when a proposal barely moves the pose (then that last, tiny step is
taken: the photometric refinement and the final verification that follow check it).
"""
from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np
import torch

from ..checks import check_bool, check_choice, check_int, check_real
from ..pose.convert import invert_rigid, rotation_error_deg
from .geometry import (
    DistortionFit,
    FocalFit,
    PnPResult,
    fit_pose_and_distortion,
    fit_pose_and_focal,
    lift_keypoints,
    median_depth,
    solve_pnp,
)
from .state import LocalizationState, Observation
from .types import Stage
from .verify import PoseScore, score_observation

logger = logging.getLogger(__name__)

__all__ = ["ANCHORS", "GeometricConfig", "GeometricOutcome", "distortion_fits", "focal_fits",
           "pnp_from_observation", "pose_motion", "render_correspondences", "run_geometric"]

#: Where the geometric stage's 2D-3D correspondences come from (``GeometricConfig.anchors``).
ANCHORS = ("renders", "photos", "both")


@dataclass
class GeometricConfig:
    """Constants of the geometric stage.

    max_rounds: render-match-PnP rounds at most (usually 2-5 are used; from 60 degrees and more
        the PnP pose can still improve in the fifth: 4 rounds left 2 of 200 held-out lego starts
        at 1-9 degrees).
    ransac_px: RANSAC inlier threshold [px at the working resolution].
    ransac_iterations, ransac_confidence: RANSAC (USAC-MAGSAC) iterations at most, confidence.
    min_pnp_inliers: a PnP with fewer inliers is no proposal.
    min_alpha: lift only keypoints where the rendered alpha exceeds this.
    max_depth_jump: drop keypoints next to depth discontinuities (relative depth range of the 3x3
        neighbourhood above this); None keeps them.
    subpixel: refine the render keypoints to sub-pixel positions against the query patch (NCC)
        before lifting them, once the pose agrees with at least ``subpixel_inliers`` matches (far
        from the answer integer keypoints are precise enough, and refining costs time).
    subpixel_iterations: fixed-point (Newton) iterations of that refinement before its last step
        (``matchers.refine.refine_render_keypoints``, whose own default is 4). 1: on held-out lego
        starts the PnP's time fell from 0.25 to 0.14 CPU s a pose and the median error stayed at
        0.028-0.029 deg (0 iterations: 0.032 deg; docs/SPEED.md).
    inlier_px: displacement below which a match agrees with a pose (the score; see verify.py).
    accept_tie: a proposal is accepted when its render agrees with more matches than the pose it
        came from by more than this share, or with about as many (within it) at a smaller mean
        displacement (``PoseScore.better_than``'s ``tie``). Near the answer both counts are noisy
        by a few %, and so is the mean displacement: 0.05 took better proposals on lego (3 of 20
        starts, 0.13-0.17 -> 0.04-0.07 deg) and bird (2 runs) but a worse one on a goldcape photo
        (0.028 -> 0.100 deg in all its 13 runs), so the default stays 0.02
        (docs/LOCALIZATION.md, "A proposal within the score's noise").
    stop_rot_deg, stop_trans_rel: a proposal that moves the pose less than this (rotation, and
        centre motion relative to the scene depth) ends the stage. 0.25 deg: the rounds after it
        moved lego poses by 0.03-0.08 deg, back and forth, and the refinement gets there anyway
        (0.05 deg took 13 steps where 0.25 takes 8, same accuracy; docs/SPEED.md).
    patience: a proposal whose render agrees with fewer matches than the best pose so far does
        not end the stage at once: the rounds go on from that render's own PnP proposal, up to
        this many such rounds in a row, and the stage keeps the best-scored pose unless a later
        render beats it. On a foggy fit the score can dip on the way from a pose off along a
        narrow lens's rotation-translation ambiguity to the right one: goldcape's IMG_5937 went
        1.36 deg (244 agreeing matches) -> 0.85 (210) -> 0.53 (200) -> 0.05 deg (327), where the
        stage had stopped at 1.36 (docs/LOCALIZATION.md, "A dip in the score"). 0: stop at the
        first such proposal.
    fixed_point_tie: a render that scores below the best pose (one of those ``patience`` goes on
        from), but whose own PnP proposal moves it by less than the stop (a pose PnP converged
        on, where the best-scored one's proposal moved away), ends the stage there when it
        agrees with at least ``1 - fixed_point_tie`` as many matches as the best: near the
        answer the counts differ by a few % of noise.
        goldcape's IMG_5953: 322 agreeing matches at 0.33 deg, its proposal's render 310 at 0.07
        deg and a fixed point; the stage had kept the 0.33-deg pose (docs/LOCALIZATION.md, "A
        dip in the score"). None: always the best-scored pose.
    anchors: which 2D-3D correspondences the PnP takes: ``renders`` (the render at the current
        pose matched to the query), ``photos`` (the model's source photos nearest the current pose
        matched to the query, lifted with the model's depth at their cameras: ``anchors.py``) or
        ``both`` (pooled). Without source photos, ``renders``. Default ``renders``: on held-out
        photos of three captures the photos' correspondences did not help and on bird they hurt
        (their recorded poses disagree with the model by 0.1-2 deg: docs/LOCALIZATION.md).
    anchor_photos: source photos matched per round; anchor_max_angle_deg: only photos whose
        optical axis is within this angle of the current pose's.
    anchor_until_inliers: with ``both``, the photos' correspondences join only while the render
        at the current pose agrees with fewer matches than this (None: always): far from the
        answer, or on a foggy render, they find the way; near it, the render's own sub-pixel
        correspondences are the precise ones (on lego, pooling them to the end left the median
        error at 0.064 deg against 0.026; docs/LOCALIZATION.md).
    full_model_within_deg: with a level of detail (the Localizer's reduced model serves the
        stage), a round whose pose the last PnP step moved by less than this (and not from a
        render that scored below the best: ``patience``) renders the full model: near the answer
        the stage's last render-and-match is then the full model's, which the verdict may read
        (``RobustConfig.verify_near``) instead of rendering and matching the full model once
        more at nearly the same pose. None: every round the reduced model.
    coarse_scale: the first rounds render and match at this share of the working resolution
        (1: all at the working resolution) until a proposal moves the pose by less than
        ``coarse_until_deg``: far from the answer, a quarter of the pixels finds the way.
    """

    max_rounds: int = 8
    ransac_px: float = 3.0
    ransac_iterations: int = 2000
    ransac_confidence: float = 0.9999
    min_pnp_inliers: int = 12
    min_alpha: float = 0.5
    max_depth_jump: Optional[float] = 0.05
    subpixel: bool = True
    subpixel_inliers: int = 30
    subpixel_iterations: int = 1
    inlier_px: float = 2.0
    accept_tie: float = 0.02
    stop_rot_deg: float = 0.25
    stop_trans_rel: float = 5e-3
    patience: int = 2
    fixed_point_tie: Optional[float] = 0.05
    anchors: str = "renders"
    anchor_photos: int = 2
    anchor_max_angle_deg: float = 60.0
    anchor_until_inliers: Optional[int] = 80
    full_model_within_deg: Optional[float] = 1.0
    coarse_scale: float = 1.0
    coarse_until_deg: float = 2.0

    def first_scale(self, scale: float) -> float:
        """The scale the first rounds render and match at, for a working ``scale``."""
        return scale * self.coarse_scale if self.coarse_scale < 1.0 else scale

    def __post_init__(self):
        n = "GeometricConfig."
        check_int(self.max_rounds, n + "max_rounds", 1)
        check_int(self.ransac_iterations, n + "ransac_iterations", 1)
        check_real(self.ransac_confidence, n + "ransac_confidence", 0.0, 1.0, lo_open=True,
                   hi_open=True)
        check_int(self.min_pnp_inliers, n + "min_pnp_inliers", 6)
        check_int(self.subpixel_inliers, n + "subpixel_inliers", 0)
        check_int(self.subpixel_iterations, n + "subpixel_iterations", 0)
        check_int(self.patience, n + "patience", 0)
        check_real(self.fixed_point_tie, n + "fixed_point_tie", 0.0, 1.0, hi_open=True,
                   optional=True)
        for name in ("ransac_px", "inlier_px"):
            check_real(getattr(self, name), n + name, 0.0, lo_open=True)
        check_real(self.min_alpha, n + "min_alpha", 0.0, 1.0)
        check_real(self.accept_tie, n + "accept_tie", 0.0, 1.0, hi_open=True)
        check_real(self.max_depth_jump, n + "max_depth_jump", 0.0, lo_open=True, optional=True)
        check_real(self.stop_rot_deg, n + "stop_rot_deg", 0.0)
        check_real(self.stop_trans_rel, n + "stop_trans_rel", 0.0)
        check_bool(self.subpixel, n + "subpixel")
        check_choice(self.anchors, n + "anchors", ANCHORS)
        check_int(self.anchor_photos, n + "anchor_photos", 0)
        check_real(self.anchor_max_angle_deg, n + "anchor_max_angle_deg", 0.0, 180.0)
        check_int(self.anchor_until_inliers, n + "anchor_until_inliers", 0, optional=True)
        check_real(self.coarse_scale, n + "coarse_scale", 0.0, 1.0, lo_open=True)
        check_real(self.coarse_until_deg, n + "coarse_until_deg", 0.0)
        check_real(self.full_model_within_deg, n + "full_model_within_deg", 0.0, optional=True)


@dataclass
class GeometricOutcome:
    """Result of :func:`run_geometric` from one start.

    w2c: the pose the stage ends on. observation/score: the render-and-match that scored the best
    pose (at ``w2c``, or at the pose one tiny step before it when the stage converged).
    first_pnp_inliers: PnP inliers of the first round (0: the start gave no usable proposal).
    start_coverage: share of the photo the render at the start pose covered.
    pnp_inliers: PnP inliers of each accepted round (not of the renders that scored below the
        best: the last is the best pose's proposal).
    joined: the stage stopped because a proposal came near the pose it was given to join
        (``run_geometric``'s ``join``): it leads where that pose is; ``w2c`` and ``score`` are
        those of its best render before (not a pose of its own).
    """

    w2c: np.ndarray
    observation: Optional[Observation]
    score: Optional[PoseScore]
    rounds: int
    converged: bool
    first_pnp_inliers: int
    start_coverage: float
    pnp_inliers: List[int] = field(default_factory=list)
    joined: bool = False


#: ``run_geometric``'s ``join``: the camera centres within this share of the scene depth.
JOIN_DEPTH_SHARE = 0.1


def pose_motion(w2c_a: np.ndarray, w2c_b: np.ndarray) -> Tuple[float, float]:
    """(rotation [deg], camera-centre distance [world units]) between two w2c poses."""
    ca, cb = invert_rigid(w2c_a), invert_rigid(w2c_b)
    return float(rotation_error_deg(ca, cb)), float(np.linalg.norm(ca[:3, 3] - cb[:3, 3]))


def render_correspondences(state: LocalizationState, obs: Observation, cfg: GeometricConfig,
                           subpixel: bool) -> Tuple[np.ndarray, np.ndarray]:
    """(world points, query pixels) of the matches of ``obs``, lifted with its rendered depth."""
    m = obs.matches
    if m is None or len(m) < cfg.min_pnp_inliers:
        return np.zeros((0, 3)), np.zeros((0, 2))
    refined = cfg.subpixel_iterations if subpixel and not m.subpixel else None
    key = (refined, cfg.min_alpha, cfg.max_depth_jump)
    if key not in obs.lifted:  # (the PnP's and the verdict's focal refit's: lifted once)
        pts, pix = _lift_matches(state, obs, cfg, subpixel)
        pts.flags.writeable = pix.flags.writeable = False
        obs.lifted[key] = pts, pix
    return obs.lifted[key]


def _lift_matches(state: LocalizationState, obs: Observation, cfg: GeometricConfig,
                  subpixel: bool) -> Tuple[np.ndarray, np.ndarray]:
    m = obs.matches
    intr = state.intrinsics_at(obs.scale)
    kpts0, kpts1 = m.kpts0.detach(), m.kpts1.detach()
    if subpixel and not m.subpixel:  # (a patch search's are sub-pixel already)
        from ..matchers.refine import refine_render_keypoints

        refined = obs.subpixel.get(cfg.subpixel_iterations)
        if refined is None:
            with state.timed("pnp"):
                refined = refine_render_keypoints(
                    obs.color,
                    state.query_at(obs.scale).rgb.to(obs.color.dtype),
                    kpts0.to(obs.color.dtype),
                    kpts1.to(obs.color.dtype),
                    window=1,
                    iterations=cfg.subpixel_iterations,
                ).detach()
            obs.subpixel[cfg.subpixel_iterations] = refined
        kpts0 = refined
    with state.timed("pnp"):
        c2w = invert_rigid(obs.w2c)
        pts, keep = lift_keypoints(kpts0, obs.depth, obs.alpha, intr, torch.as_tensor(c2w),
                                   cfg.min_alpha, cfg.max_depth_jump)
        return pts.cpu().numpy(), kpts1[keep].double().cpu().numpy()


def focal_fits(state: LocalizationState, obs: Observation,
               cfg: GeometricConfig) -> Optional[Tuple[FocalFit, FocalFit]]:
    """The matches of ``obs`` fitted by their reprojection with the focal length free and fixed.

    ``(free, fixed)``, each a ``geometry.FocalFit``, from ``obs``'s pose and the focal length the
    state holds (its ``focal_scale``), on the matches within 3 RANSAC thresholds (a focal length
    a few % off moves the keypoints near the edges by several pixels more than the pose can make
    up for); None with too few matches.
    The render's keypoints sub-pixel as for the PnP (``cfg.subpixel``): a pose fitted with a
    wrong focal length leaves displacements of a fraction of a pixel, which whole-pixel keypoints
    round away (four frames of the lego path video given a focal length 8 % short, refitted from
    the true pose: 97-99 % of the true focal length on whole pixels, 99.4-100.4 % sub-pixel). No
    render: a few milliseconds.
    """
    pts, pix = render_correspondences(state, obs, cfg, subpixel=cfg.subpixel)
    if len(pts) == 0:
        return None
    args = (pts, pix, obs.w2c, state.intrinsics_at(obs.scale), 3.0 * cfg.ransac_px)
    free, fixed = fit_pose_and_focal(*args), fit_pose_and_focal(*args, max_log_focal=0.0)
    return None if free is None or fixed is None else (free, fixed)


def distortion_fits(state: LocalizationState, obs: Observation, cfg: GeometricConfig,
                    rms_given: Optional[float] = None
                    ) -> Optional[Tuple[DistortionFit, float]]:
    """The matches of ``obs`` fitted by their reprojection with the lens's distortion free.

    ``(free, rms_given)``: the ``geometry.DistortionFit`` with the focal length and k1, k2, p1,
    p2 free, from ``obs``'s pose, on the same correspondences as :func:`focal_fits`, and the root
    mean square error of the pose alone there (``rms_given`` when the focal check's fit gave it,
    else that fit made here); None with too few.
    """
    pts, pix = render_correspondences(state, obs, cfg, subpixel=cfg.subpixel)
    if len(pts) == 0:
        return None
    intr = state.intrinsics_at(obs.scale)
    args = (pts, pix, obs.w2c, intr, 3.0 * cfg.ransac_px)
    if intr.cx is None or intr.cy is None:  # the image centre taken: its move with k1, k2 (the
        free = fit_pose_and_distortion(*args, terms=2, centre=True)  # tangential terms would
    else:  # stand for it)
        free = fit_pose_and_distortion(*args)
    if rms_given is None:
        fixed = fit_pose_and_focal(*args, max_log_focal=0.0)
        rms_given = None if fixed is None else fixed.rms_px
    return None if free is None or rms_given is None else (free, rms_given)


def pnp_from_observation(state: LocalizationState, obs: Observation, cfg: GeometricConfig,
                         seed: int = 0, subpixel: Optional[bool] = None,
                         inliers: Optional[int] = None) -> Optional[PnPResult]:
    """A PnP estimate of the query pose from the correspondences at ``obs``, or None.

    The render's matches (``cfg.anchors`` renders / both) and the nearest source photos' (photos
    / both, when the state has anchors, and with both only while the render agrees with fewer
    than ``cfg.anchor_until_inliers`` matches: ``inliers``, its score), pooled in one RANSAC.
    """
    subpixel = cfg.subpixel if subpixel is None else subpixel
    photos = state.anchors if cfg.anchors != "renders" else None
    if photos is not None and cfg.anchors == "both" and cfg.anchor_until_inliers is not None \
            and inliers is not None and inliers >= cfg.anchor_until_inliers:
        photos = None  # the render agrees well: its own correspondences are the precise ones
    pts, pix = np.zeros((0, 3)), np.zeros((0, 2))
    if cfg.anchors != "photos" or photos is None:
        pts, pix = render_correspondences(state, obs, cfg, subpixel)
    if photos is not None:
        X, x, _ = photos(state, obs.scale, invert_rigid(obs.w2c), cfg, subpixel=subpixel)
        pts, pix = np.concatenate([pts, X]), np.concatenate([pix, x])
    if len(pts) < cfg.min_pnp_inliers:
        return None
    with state.timed("pnp"):
        return solve_pnp(pts, pix, state.intrinsics_at(obs.scale), cfg.ransac_px,
                         cfg.ransac_iterations, cfg.ransac_confidence,
                         min_inliers=cfg.min_pnp_inliers, seed=seed)


def run_geometric(state: LocalizationState, w2c_start: np.ndarray, cfg: GeometricConfig,
                  scale: float = 1.0, scene_depth: Optional[float] = None,
                  hypothesis: Optional[int] = None,
                  join: Optional[Tuple[np.ndarray, float]] = None) -> GeometricOutcome:
    """Render-match-PnP rounds from ``w2c_start`` (see the module docstring).

    With ``cfg.coarse_scale`` < 1 the rounds start at that share of ``scale`` and move to
    ``scale`` once a proposal moves the pose by less than ``cfg.coarse_until_deg``; scores of
    the two resolutions are not compared (the first round at ``scale`` is taken as it is).
    ``join``: ``(w2c, degrees)``: stop (``joined``) once a proposal lies within that rotation of
    that pose and within ``JOIN_DEPTH_SHARE`` of the scene depth of its centre, the rounds after
    it would find that pose again (a rival hypothesis that leads to the best one).
    """
    w2c = np.asarray(w2c_start, np.float64)
    best_w2c, best_obs, best_score = w2c, None, None
    first_inliers, start_cov, converged, joined = 0, 0.0, False, False
    inliers_per_round: List[int] = []
    rounds, dips = 0, 0  # dips: rounds in a row whose render scored below the best
    level = cfg.first_scale(scale)
    last_step = None  # the rotation of the PnP step that led to this round's pose [deg]
    for r in range(cfg.max_rounds):
        rounds = r + 1
        # (not after a dip: rounds that go on from a worse render seldom end the stage)
        near = (state.reduced is not None and cfg.full_model_within_deg is not None
                and last_step is not None and last_step < cfg.full_model_within_deg
                and dips == 0)
        with state.full_model() if near else contextlib.nullcontext():
            obs = state.observe(w2c, level)
        sc = score_observation(obs, state, cfg.inlier_px)
        if r == 0:
            start_cov = sc.coverage
        new_level = best_obs is not None and best_obs.scale != level
        accepted = new_level or sc.better_than(best_score, cfg.accept_tie)
        rec = state.new_record(
            Stage.GEOMETRIC,
            w2c,
            matches=0 if obs.matches is None else len(obs.matches),
            inliers=sc.inliers,
            accepted=accepted,
            hypothesis=hypothesis,
            scale=level,
        )
        dip = not accepted
        if dip and (dips >= cfg.patience or r + 1 >= cfg.max_rounds):
            state.record(rec)
            logger.debug("geometric round %d: %d inliers, worse than %d: keep the best pose", r,
                         sc.inliers, best_score.inliers)
            break
        if not dip:
            dips = 0
            best_w2c, best_obs, best_score = w2c, obs, sc
        pnp = pnp_from_observation(state, obs, cfg, seed=r,
                                   subpixel=cfg.subpixel and sc.inliers >= cfg.subpixel_inliers,
                                   inliers=sc.inliers)
        n_pnp = 0 if pnp is None else pnp.num_inliers
        if not dip:  # (the last one stays the best pose's: ``robust._support``)
            inliers_per_round.append(n_pnp)
        rec.matches_used = n_pnp
        state.record(rec)
        if r == 0:
            first_inliers = n_pnp
        if pnp is None:
            break
        drot, dtrans = pose_motion(w2c, pnp.w2c)
        last_step = drot
        depth = scene_depth if scene_depth else median_depth(obs.depth, obs.alpha)
        small = drot < cfg.stop_rot_deg and dtrans < cfg.stop_trans_rel * depth  # (the stop)
        if join is not None:
            jrot, jtrans = pose_motion(join[0], pnp.w2c)
            if jrot < join[1] and jtrans < JOIN_DEPTH_SHARE * depth:
                joined = True
                break
        if dip:  # (``patience``) on from its proposal, unless the pose is PnP's own fixed point
            if small:
                tie = cfg.fixed_point_tie
                if tie is not None and sc.inliers >= (1.0 - tie) * best_score.inliers:
                    best_w2c, best_obs, best_score = pnp.w2c, obs, sc  # (as a converged stage)
                    converged = True
                    inliers_per_round.append(n_pnp)
                break
            dips += 1
            logger.debug("geometric round %d: %d inliers, below the best %d: on from its PnP", r,
                         sc.inliers, best_score.inliers)
            w2c = pnp.w2c
            continue
        w2c = pnp.w2c
        if level != scale:
            if drot < cfg.coarse_until_deg:
                level = scale  # near enough: the next rounds at the working resolution
            continue
        if small:
            converged = True
            best_w2c = w2c  # the last, tiny step (checked by the refinement and verification)
            break
    return GeometricOutcome(
        best_w2c,
        best_obs,
        best_score,
        rounds,
        converged,
        first_inliers,
        start_cov,
        inliers_per_round,
        joined,
    )
