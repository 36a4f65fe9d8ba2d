"""What the stages of a localization share.

The scene, the query at each working scale, the matcher (with the query's features computed
once), the trace and the time spent per kind of work.

A stage reads and writes a :class:`LocalizationState`; the pose it works on is passed and
returned explicitly (``w2c``, float64 numpy), so that a stage can be run and tested on its own.
"""
from __future__ import annotations

import contextlib
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from ..gaussians import GaussianModel
from ..matchers.base import patch_search
from ..pose.convert import invert_rigid, rotation_error_deg, translation_error
from .types import Query, Stage, TraceRecord

__all__ = ["LocalizationState", "Observation", "query_features", "scaled_query"]

#: Kinds of work timed separately (issue: where does a pose's time go).
TIMED = ("render", "backward", "matcher", "pnp", "verify", "candidates")

#: A patch search that keeps fewer than this share of the query's keypoints, or whose median
#: displacement exceeds half its window, saw a render too far from the photo for that window
#: (LocalizationState.patch_search): the render is matched by descriptors instead.
PATCH_SEARCH_MIN_SHARE = 0.3
#: The patch search first tries this many of the query's keypoints (evenly spread over its list)
#: when it has more than twice as many, and falls back at once when they fail the test twice
#: over (half the share, the whole window): a render clearly too far off then costs a few ms
#: instead of a whole search (1024 keypoints of a 270x480 photo: ~0.1 s a frame on fox).
PATCH_SEARCH_PROBE = 64


def _patch_search_holds(m, tried: int, window: int, slack: float = 1.0) -> bool:
    """Whether a patch search over ``tried`` keypoints saw a render within its window."""
    return bool(len(m) and len(m) >= PATCH_SEARCH_MIN_SHARE / slack * tried
                and float((m.kpts0 - m.kpts1).norm(dim=-1).median()) <= 0.5 * slack * window)


def scaled_query(query: Query, scale: float, device=None, dtype=None) -> Query:
    """``query`` at working ``scale`` (on ``device`` / ``dtype``): what a state matches against."""
    intr = query.intrinsics if scale == 1.0 else query.intrinsics.scaled(scale)
    return query.at(intr, device, dtype)


def query_features(query: Query, scaled: Query, matcher, quarter_turns: int = 0):
    """The matcher's features of ``scaled``, ``query`` at a working scale (computed once).

    Turned ``quarter_turns`` times 90 degrees; kept in ``query.memo``, so computed once per
    query, size and matcher.
    """
    key = ("features", scaled.size, quarter_turns % 4, str(scaled.rgb.device), scaled.rgb.dtype)
    hit = query.memo.get(key)
    if hit is not None and hit[0] is matcher:
        return hit[1]
    f = matcher.extract(torch.rot90(scaled.rgb, quarter_turns % 4, dims=(1, 2)))
    query.memo[key] = (matcher, f)  # a dict item: safe to set from a look-ahead thread
    return f


@dataclass
class Observation:
    """A render at one pose and what was matched against the query there (detached).

    w2c: the pose rendered. scale: working scale of the render (its intrinsics are
    ``state.intrinsics_at(scale)``). color/depth/alpha: the render. matches: render (kpts0) vs
    query (kpts1) at that scale, or None if not matched. subpixel: the render's keypoints
    refined against the query (``geometric.render_correspondences``), by Newton iterations, so
    that the PnP and the verdict's focal refit of one render refine them once. lifted: those
    correspondences lifted to world points, ``(points, query pixels)`` (read-only) by how they
    were made, so that they are lifted once too. reduced: rendered from the reduced model (a
    level of detail), which the verdict does not read.
    """

    w2c: np.ndarray
    scale: float
    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    matches: Any = None
    reduced: bool = False
    subpixel: Dict[int, torch.Tensor] = field(default_factory=dict)
    lifted: Dict[tuple, Tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


@dataclass
class LocalizationState:
    """Scene, query and bookkeeping of one localization.

    model: Gaussians (detached); bg: background ``[3]``; backend: rasterizer backend.
    query: the photo at full resolution. matcher: the keypoint matcher (or None).
    mutual_nn: None: the matcher matches; a cosine: renders are matched to the query by mutual
        nearest neighbours of the matcher's descriptors above it (``matchers.mutual_nn``; no
        LightGlue pass), for a method's cheap mode (``RobustConfig.mutual_nn``).
    patch_search: None, or ``(window px, min NCC, Newton iterations, min peak margin or None)``:
        renders are matched to the query by searching each of the query's keypoints (the
        matcher's features) in the render near the same position (``matchers.patch_search``):
        no features of the render.
        When it keeps fewer than ``PATCH_SEARCH_MIN_SHARE`` of the query's keypoints, or its
        matches move by more than half the window (median), the render is matched as without
        it; a probe of ``PATCH_SEARCH_PROBE`` keypoints decides that first when there are many.
        The min margin: ``matchers.patch_search``'s ``min_margin``. For a method's cheap mode
        (``RobustConfig.patch_search``).
    gt_c2w: ground truth, used ONLY to fill the errors of trace records.
    progress: called with every trace record as it is added.
    scene: the model's rasterizer inputs (``render.prepare_scene`` at ``sh_degree``), prepared
        once by the Localizer for all its queries; prepared at the first render when None.
    candidates: ``() -> (CandidateIndex, excluded indices)`` or None: where the default method
        finds candidate views (the Localizer's index, built or loaded when first asked for).
    anchors: ``(state, scale, c2w, geometric config) -> (points [N, 3], pixels [N, 2], names)``
        or None: the model's source photos' correspondences near a pose (``anchors.py``).
    reduced: ``(intrinsics) -> prepared scene or None``: the reduced model (level of detail,
        ``lod.reduce_model``) for renders at ``intrinsics``, used inside :meth:`serving` blocks
        that ask for it (the geometric stage, the candidate renders); None: the full model
        always.
    rendered: per stage (the label of the enclosing :meth:`serving` block, ``other`` outside
        one): ``{"gaussians": [counts rendered], "renders": n, "reduced": any by the reduced
        model}`` (which model served which stage).
    focal_scale: the query's focal lengths are rendered and matched at this multiple of its
        recorded ones (1 unless the refinement estimates it: ``RefineConfig.focal``).
    """

    model: GaussianModel
    query: Query
    bg: torch.Tensor
    backend: str = "auto"
    matcher: Any = None
    mutual_nn: Optional[float] = None
    patch_search: Optional[Tuple[int, float, int, Optional[float]]] = None
    sh_degree: Optional[int] = None
    antialiasing: bool = False
    gt_c2w: Optional[np.ndarray] = None
    progress: Optional[Callable[[TraceRecord], Any]] = None
    record_trace: bool = True
    scene: Any = None
    candidates: Optional[Callable[[], Any]] = None
    anchors: Optional[Callable[..., Any]] = None
    reduced: Optional[Callable[[Intrinsics], Any]] = None
    rendered: Dict[str, Dict[str, Any]] = field(default_factory=dict)
    trace: List[TraceRecord] = field(default_factory=list)
    seconds: Dict[str, float] = field(default_factory=lambda: defaultdict(float))
    cpu_seconds: Dict[str, float] = field(default_factory=lambda: defaultdict(float))
    _queries: Dict[float, Query] = field(default_factory=dict)
    steps: int = 0  # trace records made so far (also when the trace is not kept)
    focal_scale: float = 1.0
    # renders the patch search matched, and those it left to the descriptors (too far off)
    patch_searched: Dict[str, int] = field(
        default_factory=lambda: {"matched": 0, "fell_back": 0})

    def __post_init__(self):
        # (the scan of the SH is remembered on the caller's model: a Localizer's, each frame)
        self.model = (self.model if self.sh_degree is not None
                      else self.model.without_zero_sh()).detach()
        dev, dt = self.model.device, self.model.dtype
        self.bg = torch.as_tensor(self.bg, device=dev, dtype=dt).reshape(3)
        self._t0, self._c0 = time.perf_counter(), time.process_time()
        self._last_record = self._t0
        self._nested: List[Tuple[float, float]] = []
        self._serving: Tuple[str, bool] = ("other", False)
        self.last_reduced = False  # whether the last render was of the reduced model

    # ------------------------------------------------------------------ which model renders
    def full_model(self):
        """Renders in the block are of the full model, counted as the stage served now."""
        return self.serving(self._serving[0], reduced=False)

    @contextlib.contextmanager
    def serving(self, stage: str, reduced: bool = False):
        """Renders in the block are counted as ``stage``'s; with ``reduced``, of the reduced model.

        The reduced model (``reduced``, when the state has one for the render's intrinsics)
        serves the geometric stage and the candidate renders; the full model the photometric
        refinement and the verdict (docs/LOCALIZATION.md, level of detail).
        """
        previous = self._serving
        self._serving = (stage, bool(reduced))
        try:
            yield
        finally:
            self._serving = previous

    def _scene_for(self, intrinsics: Intrinsics):
        """The prepared scene a render at ``intrinsics`` uses now (counted in ``rendered``)."""
        from ..render import prepare_scene

        stage, want_reduced = self._serving
        scene = self.reduced(intrinsics) if want_reduced and self.reduced is not None else None
        if scene is None:
            if self.scene is None:  # prepared (and checked) once: docs/SPEED.md
                self.scene = prepare_scene(self.model, self.sh_degree)
            scene = self.scene
        seen = self.rendered.setdefault(stage, {"gaussians": [], "renders": 0, "reduced": False})
        seen["reduced"] = seen["reduced"] or scene is not self.scene
        self.last_reduced = scene is not self.scene
        count = int(scene.means.shape[0])
        if count not in seen["gaussians"]:
            seen["gaussians"].append(count)
        seen["renders"] += 1
        return scene

    # ------------------------------------------------------------------ time
    @contextlib.contextmanager
    def timed(self, kind: str):
        """Add the wall and process CPU time spent in the block to ``seconds[kind]``.

        Less the time of timed blocks nested in it (they count as their own kind), so the kinds
        add up to the total (``cpu_seconds`` alike: on a loaded machine wall time inflates, the
        CPU time of one thread is the work).
        """
        t, c = time.perf_counter(), time.process_time()
        self._nested.append((0.0, 0.0))
        try:
            yield
        finally:
            spent, spent_cpu = time.perf_counter() - t, time.process_time() - c
            inner, inner_cpu = self._nested.pop()
            self.seconds[kind] += spent - inner
            self.cpu_seconds[kind] += spent_cpu - inner_cpu
            if self._nested:
                w, cp = self._nested[-1]
                self._nested[-1] = (w + spent, cp + spent_cpu)

    def elapsed(self) -> float:
        """Seconds since the state was made."""
        return time.perf_counter() - self._t0

    def stage_seconds(self, cpu: bool = False) -> Dict[str, float]:
        """Seconds per kind of work, plus ``other`` (Python, losses, bookkeeping) and ``total``.

        Wall seconds, or process CPU seconds with ``cpu``.
        """
        total = time.process_time() - self._c0 if cpu else self.elapsed()
        spent = self.cpu_seconds if cpu else self.seconds
        out = {k: float(spent.get(k, 0.0)) for k in TIMED}
        out["other"] = max(0.0, total - sum(out.values()))
        out["total"] = total
        return out

    # ------------------------------------------------------------------ query
    def intrinsics_at(self, scale: float) -> Intrinsics:
        """The query's intrinsics at working ``scale`` (its focal lengths x ``focal_scale``)."""
        intr = self.query.intrinsics
        intr = intr if scale == 1.0 else intr.scaled(scale)
        return intr.with_focal_scale(self.focal_scale)

    def query_at(self, scale: float) -> Query:
        """The query resized to ``scale``.

        The masks are kept conservative: a pixel of ``valid`` stays valid only if all of its
        source was.
        """
        q = self._queries.get(scale)
        if q is None:
            q = scaled_query(self.query, scale, self.model.device, self.model.dtype)
            self._queries[scale] = q
        return q

    def query_features(self, scale: float, quarter_turns: int = 0):
        """The matcher's features of the query at ``scale`` (once per query: `query_features`).

        ``quarter_turns``: of the query turned by that many times 90 degrees
        (``torch.rot90``, counter-clockwise on screen), for the candidate ranking.
        None when the matcher cannot extract features on their own.
        """
        if self.matcher is None or not getattr(self.matcher, "supports_features", False):
            return None
        with self.timed("matcher"):
            return query_features(self.query, self.query_at(scale), self.matcher, quarter_turns)

    # ------------------------------------------------------------------ render / match
    def render(self, w2c, scale: float = 1.0, intrinsics: Optional[Intrinsics] = None):
        """Render at ``w2c`` at working ``scale`` (or with other ``intrinsics``).

        ``w2c`` is a [4, 4] float64 numpy pose, or a torch tensor that may require grad.

        Returns:
            The rasterizer's ``RasterOutput``.
        """
        from ..render import render

        if isinstance(w2c, np.ndarray):
            w2c = torch.as_tensor(w2c, dtype=torch.float64)
        dev, dt = self.model.device, self.model.dtype
        intrinsics = intrinsics or self.intrinsics_at(scale)
        scene = self._scene_for(intrinsics)  # outside the timer: a first reduced model builds
        with self.timed("render"):
            return render(
                scene,
                intrinsics,
                w2c.to(device=dev, dtype=dt),
                self.bg,
                backend=self.backend,
                antialiasing=self.antialiasing,
            )

    def observe(self, w2c: np.ndarray, scale: float = 1.0, match: bool = True) -> Observation:
        """Render at ``w2c`` and (optionally) match the render against the query."""
        with torch.no_grad():
            out = self.render(w2c, scale)
        color = out.color.clamp(0.0, 1.0)  # matchers take images in [0, 1]
        obs = Observation(np.asarray(w2c, np.float64).copy(), scale, color, out.depth, out.alpha,
                          reduced=self.last_reduced)
        if match and self.matcher is not None:
            obs.matches = self.match(color, scale)
        return obs

    def match(self, render_rgb: torch.Tensor, scale: float, differentiable: bool = False):
        """Matches between a render at ``scale`` (kpts0) and the query at ``scale`` (kpts1)."""
        q = self.query_at(scale)
        feats = None if differentiable else self.query_features(scale)
        with self.timed("matcher"):
            if self.patch_search is not None and feats is not None:
                window, min_ncc, iterations, min_margin = self.patch_search
                kpts = feats.kpts
                held = True
                if len(kpts) > 2 * PATCH_SEARCH_PROBE:
                    probe = kpts[torch.linspace(0, len(kpts) - 1, PATCH_SEARCH_PROBE,
                                                device=kpts.device).long()]
                    held = _patch_search_holds(
                        patch_search(render_rgb, q.rgb, probe, window, min_ncc, iterations,
                                     min_margin), PATCH_SEARCH_PROBE, window, slack=2.0)
                if held:
                    m = patch_search(render_rgb, q.rgb, kpts, window, min_ncc, iterations,
                                     min_margin)
                    if _patch_search_holds(m, len(kpts), window):
                        self.patch_searched["matched"] += 1
                        return m
                self.patch_searched["fell_back"] += 1
            if self.mutual_nn is not None and feats is not None:
                return self.matcher.match_mutual_nn(render_rgb, feats, self.mutual_nn)
            return self.matcher.match(
                render_rgb, q.rgb, differentiable=differentiable, features1=feats
            )

    # ------------------------------------------------------------------ trace
    def errors(self, w2c: np.ndarray) -> Tuple[Optional[float], Optional[float]]:
        """(rotation error deg, camera-centre distance) against the ground truth, if known."""
        if self.gt_c2w is None:
            return None, None
        c2w = invert_rigid(w2c)
        return float(rotation_error_deg(c2w, self.gt_c2w)), float(
            translation_error(c2w, self.gt_c2w)
        )

    def record(self, rec: TraceRecord) -> TraceRecord:
        """Keep ``rec`` (and report it).

        A record without its own duration gets the time since the previous one, so the durations
        of a trace add up to the run's time.
        """
        now = time.perf_counter()
        if not rec.seconds:
            rec.seconds = now - self._last_record
        self._last_record = now
        self.steps += 1
        if self.record_trace:
            self.trace.append(rec)
        if self.progress is not None:
            self.progress(rec)
        return rec

    def new_record(self, stage: Stage, w2c: np.ndarray, **kw) -> TraceRecord:
        """A trace record of a step that rendered ``w2c`` (errors filled from the ground truth)."""
        rot, trans = self.errors(w2c)
        return TraceRecord(iteration=self.steps, stage=stage, rot_err_deg=rot, trans_err=trans,
                           w2c=np.asarray(w2c).tolist(), **kw)
