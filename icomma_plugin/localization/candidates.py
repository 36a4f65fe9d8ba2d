"""Candidate views: where to start when the given start pose is unusable, or when there is none.

Candidates are the model's cameras (``cameras.json``: the views the model was fitted from) plus
views sampled on a sphere around the scene, looking at its centre. They are ranked by how many
mutual-nearest-neighbour descriptor matches their render shares with the query, at low resolution;
the renders and their features are computed once per model (:class:`CandidateSet`) and reused for
every query of a batch.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Intrinsics
from ..checks import check_bool, check_int, check_real
from ..gaussians import GaussianModel
from ..matchers.base import mutual_nn_count
from ..pose.convert import look_at_c2w
from .state import LocalizationState

logger = logging.getLogger(__name__)

__all__ = [
    "CandidateConfig",
    "CandidateSet",
    "rank_scale",
    "rolled_w2c",
    "sample_views",
    "scene_frame",
    "usable",
]


@dataclass
class CandidateConfig:
    """Constants of the candidate search.

    num_sampled: views sampled on a sphere around the scene (Fibonacci lattice), besides the
        model's cameras.
    rank_side: the longer side of the images used for ranking [px].
    top_k: best-ranked candidates the geometric stage is run from.
    min_cosine: descriptor cosine for a ranking match.
    quarter_turns: also rank against the photo turned by 90, 180 and 270 degrees, and start from
        the candidate turned alike about its optical axis. Learned descriptors are not invariant
        to large in-plane rotations: a camera held sideways, or one looking straight down at the
        scene (every candidate near it differs by its roll), else finds no candidate.
    """

    num_sampled: int = 60
    rank_side: int = 128
    top_k: int = 4
    min_cosine: float = 0.8
    quarter_turns: bool = True

    def __post_init__(self):
        check_int(self.num_sampled, "CandidateConfig.num_sampled", 0)
        check_int(self.rank_side, "CandidateConfig.rank_side", 16)
        check_int(self.top_k, "CandidateConfig.top_k", 1)
        check_real(self.min_cosine, "CandidateConfig.min_cosine", -1.0, 1.0)
        check_bool(self.quarter_turns, "CandidateConfig.quarter_turns")


def scene_frame(model: GaussianModel, cameras_c2w: Sequence[np.ndarray]):
    """(centre [3], radius, up [3]) of the scene.

    From the cameras when there are any (the point their optical axes pass closest to, their
    median distance to it, their mean 'up'), else from the Gaussians (median position, 3x their
    spread, +z).
    """
    means = model.means.detach().double().cpu().numpy()
    if len(cameras_c2w) >= 2:
        C = np.stack([c[:3, 3] for c in cameras_c2w])
        D = np.stack([c[:3, 2] for c in cameras_c2w])
        # least-squares point nearest to all optical axes
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for c, d in zip(C, D):
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ c
        try:
            centre = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            centre = np.median(means, 0)
        if not np.all(np.isfinite(centre)) or np.linalg.cond(A) > 1e6:
            centre = np.median(means, 0)
        radius = float(np.median(np.linalg.norm(C - centre, axis=1)))
        up = -np.mean([c[:3, 1] for c in cameras_c2w], 0)  # OpenCV y points down
        up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
        return centre, radius, up
    centre = np.median(means, 0)
    spread = float(np.median(np.linalg.norm(means - centre, axis=1))) if len(means) else 1.0
    return centre, 3.0 * max(spread, 1e-3), np.array([0.0, 0.0, 1.0])


def sample_views(centre: np.ndarray, radius: float, up: np.ndarray, n: int) -> List[np.ndarray]:
    """``n`` c2w poses on a sphere of ``radius`` about ``centre`` (Fibonacci lattice).

    They look at the centre with image 'up' towards ``up``; directions too close to ``up`` are
    skipped.
    """
    out = []
    if n <= 0:
        return out
    golden = math.pi * (3.0 - math.sqrt(5.0))
    # an orthonormal frame with z = up
    z = up / np.linalg.norm(up)
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    for i in range(n):
        h = 1.0 - 2.0 * (i + 0.5) / n
        r = math.sqrt(max(0.0, 1.0 - h * h))
        d = r * math.cos(golden * i) * x + r * math.sin(golden * i) * y + h * z
        if abs(h) > 0.97:
            continue  # looking straight along 'up': the image's up is undefined
        out.append(look_at_c2w(centre + radius * d, centre, up))
    return out


@dataclass
class CandidateSet:
    """Candidate poses with their low-resolution renders' features.

    Built once per model and query camera; reusable across queries with the same intrinsics.
    """

    c2w: List[np.ndarray]
    source: List[str]
    intrinsics: Intrinsics
    features: List = field(default_factory=list)

    @classmethod
    def build(
        cls,
        state: LocalizationState,
        cameras_c2w: Sequence[np.ndarray],
        cfg: CandidateConfig,
        names: Optional[Sequence[str]] = None,
    ) -> "CandidateSet":
        """Candidates: ``cameras_c2w`` (the model's cameras) and ``cfg.num_sampled`` sampled views.

        They are rendered with the query's intrinsics at ``cfg.rank_side``.
        """
        cams = [np.asarray(c, np.float64) for c in cameras_c2w]
        centre, radius, up = scene_frame(state.model, cams)
        sampled = sample_views(centre, radius, up, cfg.num_sampled)
        c2w = cams + sampled
        names = list(names) if names is not None else [f"camera_{i}" for i in range(len(cams))]
        source = names[: len(cams)] + [f"sampled_{i}" for i in range(len(sampled))]
        scale = rank_scale(state.query.intrinsics, cfg.rank_side)
        intr = state.intrinsics_at(scale)
        feats = []
        with state.timed("candidates"):
            for T in c2w:
                obs = state.observe(np.linalg.inv(T), scale, match=False)
                if float(obs.alpha.mean()) < 0.01:
                    feats.append(None)  # sees nothing of the scene
                    continue
                feats.append(state.matcher.extract(obs.color))
        logger.debug(
            "candidate set: %d cameras + %d sampled views at %dx%d",
            len(cams),
            len(sampled),
            intr.width,
            intr.height,
        )
        return cls(c2w, source, intr, feats)

    @classmethod
    def for_model(
        cls,
        model: GaussianModel,
        intrinsics: Intrinsics,
        matcher,
        bg,
        cameras_c2w: Sequence[np.ndarray],
        cfg: Optional[CandidateConfig] = None,
        backend: str = "auto",
        names: Optional[Sequence[str]] = None,
    ) -> "CandidateSet":
        """A candidate set for photos taken with ``intrinsics``.

        Build it once and pass it to every ``localize(..., candidate_set=...)`` of a batch.
        """
        import torch

        from .types import Query

        if not usable(matcher):
            raise ValueError(
                f"candidate views need a matcher that extracts features, got {matcher!r}"
            )
        blank = torch.zeros(3, intrinsics.height, intrinsics.width)
        state = LocalizationState(
            model, Query(blank, intrinsics), bg, backend=backend, matcher=matcher
        )
        return cls.build(state, cameras_c2w, cfg or CandidateConfig(), names)

    def compatible(self, intrinsics: Intrinsics, cfg: CandidateConfig) -> bool:
        """Whether this set was rendered for photos with ``intrinsics``.

        Rendered at ``cfg.rank_side``, as `rank` needs.
        """
        return self.intrinsics == intrinsics.scaled(rank_scale(intrinsics, cfg.rank_side)) \
            if rank_scale(intrinsics, cfg.rank_side) != 1.0 else self.intrinsics == intrinsics

    def rank(self, state: LocalizationState, cfg: CandidateConfig) -> List[Tuple[int, int]]:
        """(candidate index, quarter turns), best first (most mutual-NN matches with the query).

        The quarter turns (0 unless ``cfg.quarter_turns``) are those of the photo that matched the
        candidate best; `start_w2c` turns the candidate's camera alike.
        """
        if not self.compatible(state.query.intrinsics, cfg):
            raise ValueError("this candidate set was built for photos of another size or camera "
                             f"({self.intrinsics}); build one for {state.query.intrinsics}")
        scale = rank_scale(state.query.intrinsics, cfg.rank_side)
        turns = range(4) if cfg.quarter_turns else range(1)
        best: List[Tuple[int, int]] = [(-1, 0)] * len(self.features)
        with state.timed("candidates"):
            for k in turns:
                fq = state.query_features(scale, k)
                for i, f in enumerate(self.features):
                    if f is not None:
                        n = mutual_nn_count(f, fq, cfg.min_cosine)
                        if n > best[i][0]:
                            best[i] = (n, k)
        order = sorted(range(len(best)), key=lambda i: -best[i][0])
        self.last_counts = [b[0] for b in best]
        return [(i, best[i][1]) for i in order]

    def start_w2c(self, index: int, quarter_turns: int = 0) -> np.ndarray:
        """The start pose (w2c) of candidate ``index`` for a photo that matched it turned."""
        return rolled_w2c(np.linalg.inv(self.c2w[index]), quarter_turns)


def rolled_w2c(w2c: np.ndarray, quarter_turns: int) -> np.ndarray:
    """``w2c`` rolled about its optical axis so that its image is ``torch.rot90(image, -k)``.

    A photo that matches a view after ``torch.rot90(photo, k)`` was taken by this camera. Rolling
    the camera frame by +90 degrees (x' = -y, y' = x) moves the content at pixel (x, y) to (-y, x)
    about the centre: a clockwise quarter turn on screen, which ``rot90`` with k = -1 makes.
    """
    k = quarter_turns % 4
    if k == 0:
        return np.asarray(w2c, np.float64)
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
    roll = np.eye(4)
    roll[:2, :2] = [[c, -s], [s, c]]
    return roll @ np.asarray(w2c, np.float64)


def rank_scale(intrinsics: Intrinsics, side: int) -> float:
    """The scale that brings the longer image side to ``side`` px (never above 1)."""
    return min(1.0, float(side) / max(intrinsics.width, intrinsics.height))


def usable(matcher) -> bool:
    """Candidates need a matcher that extracts features on their own."""
    return matcher is not None and bool(getattr(matcher, "supports_features", False))

