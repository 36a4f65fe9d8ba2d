"""Candidate views: where to start when the given start pose is unusable, or when there is none.

Candidates are the model's cameras (``cameras.json``: the views the model was fitted from) plus
views sampled on a sphere around the scene, looking at its centre. They are ranked by how many
mutual-nearest-neighbour descriptor matches their render shares with the query, at low resolution;
the renders and their features are computed once per model and camera (:class:`CandidateIndex`),
kept by the Localizer (in memory, and on disk: ``candidate_cache.py``) and reused for every
query.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Dict, FrozenSet, Iterable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from ..checks import check_bool, check_int, check_real
from ..matchers.base import DescriptorStack, Features
from ..pose.convert import invert_rigid, same_pose
from ..pose.views import sample_views, scene_frame
from .anchors import name_stem
from .state import LocalizationState

logger = logging.getLogger(__name__)

__all__ = [
    "CandidateConfig",
    "CandidateIndex",
    "candidate_intrinsics",
    "rolled_w2c",
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
    photos: rank against the model's source photos where they are known (a camera with a photo
        is described by its photo, not its render; photos without a camera entry are candidates
        too): sharp and real where the render is foggy (``anchors.py``).
    rival_share: a candidate far from the best one (``rival_deg`` apart) whose ranking count is
        at least this share of the best's is run through the geometric stage too, even when the
        best one convinced: two places that look alike (``robust.py``, ambiguity).
    rival_deg: how far apart (rotation [deg]) two poses must be to be rivals.
    """

    num_sampled: int = 60
    rank_side: int = 128
    top_k: int = 4
    min_cosine: float = 0.8
    quarter_turns: bool = True
    photos: bool = True
    rival_share: float = 0.8
    rival_deg: float = 10.0

    def __post_init__(self):
        check_int(self.num_sampled, "CandidateConfig.num_sampled", 0)
        check_int(self.rank_side, "CandidateConfig.rank_side", 16)
        check_int(self.top_k, "CandidateConfig.top_k", 1)
        check_real(self.min_cosine, "CandidateConfig.min_cosine", -1.0, 1.0)
        check_bool(self.quarter_turns, "CandidateConfig.quarter_turns")
        check_bool(self.photos, "CandidateConfig.photos")
        check_real(self.rival_share, "CandidateConfig.rival_share", 0.0, 1.0)
        check_real(self.rival_deg, "CandidateConfig.rival_deg", 0.0, 180.0)


def candidate_intrinsics(query: Intrinsics, cameras: Sequence[Intrinsics], side: int
                         ) -> Intrinsics:
    """The camera the candidate views are rendered with for photos taken with ``query``.

    At ``side`` px. The model camera with the median focal length (relative to the image
    diagonal) among those of the photo's aspect ratio, so that photos whose focal lengths differ
    a little (COLMAP's per-image cameras) share one candidate index: the ranking counts
    descriptor matches, which a few percent of zoom barely changes; the geometric stage then
    works with the photo's own intrinsics. Without such a camera, the photo's own.
    """
    aspect = query.width / query.height
    same = [c for c in cameras if math.isclose(c.width / c.height, aspect, rel_tol=0.01)]
    if not same:
        return query.scaled(query.scale_to_side(side))
    rel = [c.fx / math.hypot(c.width, c.height) for c in same]
    cam = same[int(np.argsort(rel, kind="stable")[(len(rel) - 1) // 2])]
    return cam.scaled(cam.scale_to_side(side))


@dataclass
class CandidateIndex:
    """Candidate views with the features of their low-resolution renders (or photos).

    Built once per model and candidate camera (:func:`candidate_intrinsics`), kept by the
    Localizer in memory and on disk (``candidate_cache.py``), reused for every query.

    c2w: candidate poses; the first ``num_cameras`` are the model's cameras, then the source
    photos without a camera entry, then sampled views. source: their names. intrinsics: the
    camera of the renders. features: the matcher's features of each render, or of the camera's
    source photo (None for a view that sees nothing of the scene). kinds: ``camera``, ``photo``
    (described by its source photo) or ``sampled``.
    """

    c2w: List[np.ndarray]
    source: List[str]
    intrinsics: Intrinsics
    features: List = field(default_factory=list)
    num_cameras: int = 0
    kinds: List[str] = field(default_factory=list)
    _stack: Optional[DescriptorStack] = field(default=None, init=False, repr=False,
                                              compare=False)  # the features, for `rank`

    @classmethod
    def build(
        cls,
        state: LocalizationState,
        cameras_c2w: Sequence[np.ndarray],
        cfg: CandidateConfig,
        names: Optional[Sequence[str]] = None,
        intrinsics: Optional[Intrinsics] = None,
        photos=None,
    ) -> "CandidateIndex":
        """Describe ``cameras_c2w`` (the model's cameras) and ``cfg.num_sampled`` sampled views.

        Renders with ``intrinsics`` (the query's at ``cfg.rank_side`` when None); with
        ``photos`` (``anchors.PhotoAnchors``) and ``cfg.photos``, a camera that has a source photo
        is described by the photo, and photos without a camera are candidates too. Features by
        ``state.matcher``.
        """
        cams = [np.asarray(c, np.float64) for c in cameras_c2w]
        names = list(names) if names is not None else [f"camera_{i}" for i in range(len(cams))]
        use = photos if (photos is not None and cfg.photos) else None
        # a camera is described by the photo of its name taken at its pose: a Blender folder
        # names its train and test views alike (r_0, r_1, ...) and a model's cameras.json lists
        # both, while the source photos are the train views only
        of_camera = [None if use is None else use.index_of(n) for n in names[: len(cams)]]
        of_camera = [j if j is not None and same_pose(c, use.photos[j].c2w) else None
                     for c, j in zip(cams, of_camera)]
        extra = [] if use is None else [
            i for i in range(len(use)) if i not in set(j for j in of_camera if j is not None)]
        centre, radius, up = scene_frame(state.model.means.detach().cpu().numpy(), cams)
        sampled = sample_views(centre, radius, up, cfg.num_sampled)
        c2w = cams + [use.photos[i].c2w for i in extra] + sampled
        source = names[: len(cams)] + [use.photos[i].name for i in extra] + [
            f"sampled_{i}" for i in range(len(sampled))]
        photo_of = of_camera + extra + [None] * len(sampled)
        kinds = ["camera" if j is None else "photo" for j in of_camera] + ["photo"] * len(
            extra) + ["sampled"] * len(sampled)
        q = state.query.intrinsics
        intr = intrinsics or q.scaled(q.scale_to_side(cfg.rank_side))
        feats = []
        with state.timed("candidates"):
            for T, j in zip(c2w, photo_of):
                if j is not None:
                    feats.append(use.features(j, max(intr.width, intr.height), state.matcher))
                    continue
                with torch.no_grad():
                    out = state.render(invert_rigid(T), intrinsics=intr)
                if float(out.alpha.mean()) < 0.01:
                    feats.append(None)  # sees nothing of the scene
                    continue
                feats.append(state.matcher.extract(out.color.clamp(0.0, 1.0)))
        logger.debug("candidate index: %d cameras (%d described by photos) + %d photos + %d "
                     "sampled views at %dx%d", len(cams), kinds.count("photo") - len(extra),
                     len(extra), len(sampled), intr.width, intr.height)
        return cls(c2w, source, intr, feats, len(cams), kinds)

    def compatible(self, intrinsics: Intrinsics) -> bool:
        """Whether photos taken with ``intrinsics`` can be ranked against this index.

        They must have the aspect ratio of its renders (1 %).
        """
        return math.isclose(intrinsics.width / intrinsics.height,
                            self.intrinsics.width / self.intrinsics.height, rel_tol=0.01)

    def own_cameras(self, gt_c2w: Optional[np.ndarray], name: Optional[str] = None
                    ) -> FrozenSet[int]:
        """Candidates that are the query's own: at the pose ``gt_c2w``, or named ``name``.

        Names are compared without folders and extension (a camera and its photo file).
        """
        stem = None if name is None else name_stem(name)
        out = set()
        for i, (c, src) in enumerate(zip(self.c2w, self.source)):
            sampled = self.kinds[i] == "sampled" if self.kinds else i >= self.num_cameras
            if not sampled and ((gt_c2w is not None and same_pose(c, gt_c2w))
                                or (stem is not None and name_stem(src) == stem)):
                out.add(i)
        return frozenset(out)

    def rank(self, state: LocalizationState, cfg: CandidateConfig,
             exclude: Iterable[int] = ()) -> List[Tuple[int, int]]:
        """(candidate index, quarter turns), best first (most mutual-NN matches with the query).

        The query is ranked at the size of the index's renders. The quarter turns (0 unless
        ``cfg.quarter_turns``) are those of the photo that matched the candidate best;
        `start_w2c` turns the candidate's camera alike. Candidates in ``exclude`` are left out.
        """
        q = state.query.intrinsics
        if not self.compatible(q):
            raise ValueError("this candidate index was built for photos of another aspect ratio "
                             f"({self.intrinsics}); build one for {q}")
        scale = q.scale_to_side(max(self.intrinsics.width, self.intrinsics.height))
        turns = range(4) if cfg.quarter_turns else range(1)
        skip = set(exclude)
        best: List[Tuple[int, int]] = [(-1, 0)] * len(self.features)
        with state.timed("candidates"):
            if self._stack is None or self._stack.size != len(self.features):
                self._stack = DescriptorStack(self.features)
            for k in turns:
                counts = self._stack.mutual_nn_counts(state.query_features(scale, k),
                                                      cfg.min_cosine)
                for i, n in enumerate(counts):
                    if i not in skip and n > best[i][0]:
                        best[i] = (n, k)
        order = [i for i in sorted(range(len(best)), key=lambda i: -best[i][0]) if i not in skip]
        self.last_counts = [b[0] for b in best]
        return [(i, best[i][1]) for i in order]

    def start_w2c(self, index: int, quarter_turns: int = 0) -> np.ndarray:
        """The start pose (w2c) of candidate ``index`` for a photo that matched it turned."""
        return rolled_w2c(invert_rigid(self.c2w[index]), quarter_turns)

    def to_state(self) -> Dict[str, Any]:
        """The index as tensors, lists and numbers (``torch.load`` reads it with weights_only)."""
        feats = [None if f is None else {"kpts": f.kpts.cpu(), "desc": f.desc.cpu(),
                                          "size": list(f.size)} for f in self.features]
        return {"c2w": torch.as_tensor(np.stack(self.c2w)) if self.c2w else torch.zeros(0, 4, 4,
                dtype=torch.float64), "source": list(self.source),
                "intrinsics": self.intrinsics.to_json(), "features": feats,
                "num_cameras": self.num_cameras, "kinds": list(self.kinds)}

    @classmethod
    def from_state(cls, d: Dict[str, Any]) -> "CandidateIndex":
        """The index :meth:`to_state` wrote."""
        feats = [None if f is None else Features(f["kpts"], f["desc"], tuple(f["size"]))
                 for f in d["features"]]
        c2w = [np.asarray(T, np.float64) for T in d["c2w"].numpy()]
        return cls(c2w, list(d["source"]), Intrinsics.from_json(d["intrinsics"]), feats,
                   int(d["num_cameras"]), list(d.get("kinds") or []))


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


def usable(matcher) -> bool:
    """Candidates need a matcher that extracts features on their own."""
    return matcher is not None and bool(getattr(matcher, "supports_features", False))

