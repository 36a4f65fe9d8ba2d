"""The model's source photos as anchors of the localization.

A model fitted on a CPU renders its scene foggy where few photos looked, blurred on fine texture
and off in colour, but the photos it was fitted from are sharp, real and usually at hand. Where
they are known (a model folder's ``cfg_args`` source_path, or the dataset a user passes), the
localizer uses them besides the renders:

- the candidate views of the model's cameras are ranked against their photos (real images at low
  resolution) instead of their renders (``candidates.py``);
- in the geometric stage, the query is also matched against the source photos nearest to the
  current pose estimate, and those photos' keypoints are lifted to 3D with the model's rendered
  depth at their cameras (opaque pixels, off depth edges): 2D-3D correspondences pooled with the
  render-to-query ones in one RANSAC PnP (``geometric.py``).

The photos are loaded, described and their depth rendered lazily, once each per working
resolution, and kept by the Localizer for every query. A query's own photo (same name, or same
pose) is never an anchor of that query.
"""
from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, FrozenSet, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ..camera import Intrinsics
from ..pose.convert import invert_rigid, same_pose_mask
from ..pose.views import camera_nearness
from .geometry import lift_keypoints

logger = logging.getLogger(__name__)

__all__ = ["PhotoAnchors", "SourcePhoto", "name_stem"]


def name_stem(name: str) -> str:
    """An image name without folders and extension (how names are compared across formats)."""
    return os.path.splitext(os.path.basename(str(name)))[0]


#: Bytes read from each end of a source photo for its part of the fingerprint.
FILE_SAMPLE = 1 << 16


def _file_sample(path: Path) -> Optional[str]:
    """``size:digest`` of a file's first and last ``FILE_SAMPLE`` bytes; None when it is none."""
    if not path.is_file():
        return None
    size = path.stat().st_size
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        h.update(f.read(FILE_SAMPLE))
        if size > FILE_SAMPLE:
            f.seek(max(FILE_SAMPLE, size - FILE_SAMPLE))
            h.update(f.read(FILE_SAMPLE))
    return f"{size}:{h.hexdigest()}"


@dataclass
class SourcePhoto:
    """One photo the model was fitted from: its name, recorded camera and a way to load it.

    view: an ``io.datasets.View`` (``load_image(scale, background)``).
    """

    name: str
    c2w: np.ndarray
    intrinsics: Intrinsics
    view: Any

    @classmethod
    def of_view(cls, view) -> "SourcePhoto":
        """The source photo of a dataset view."""
        return cls(str(view.name), np.asarray(view.c2w, np.float64), view.intrinsics, view)


class PhotoAnchors:
    """The source photos of a model, loaded, described and given depth as they are needed.

    Args:
        photos: the photos the model was fitted from (never held-out views).
        background: what RGBA photos are composited over (the model's background).
    """

    def __init__(self, photos: Sequence[SourcePhoto], background: torch.Tensor):
        self.photos = list(photos)
        self.background = background.detach().float().cpu()
        self._by_stem = {name_stem(p.name): i for i, p in enumerate(self.photos)}
        self._c2ws = np.stack([p.c2w for p in self.photos]) if self.photos else np.zeros((0, 4, 4))
        self._images: Dict[Tuple[int, int], Any] = {}
        self._features: Dict[Tuple[int, int], Any] = {}
        self._depth: Dict[Tuple[int, int], Tuple[torch.Tensor, torch.Tensor, Intrinsics]] = {}
        self._fingerprint: Optional[str] = None

    def __len__(self) -> int:
        return len(self.photos)

    def index_of(self, name: str) -> Optional[int]:
        """The photo named ``name`` (extension and folders ignored), or None."""
        return self._by_stem.get(name_stem(name))

    def fingerprint(self) -> str:
        """A hash of the photos' names, cameras and files (their contents, sampled).

        Of each file its size and its first and last ``FILE_SAMPLE`` bytes, not its modification
        time: a capture copied to another disk or machine (a cluster's nodes) keeps its key, so
        the candidate index cached for it is found again instead of built again (fox's copy in
        ../shared took its index 1.0 -> 7.2 s). An edit that keeps a file's size and both ends
        is not seen. Made once.
        """
        if self._fingerprint is None:
            h = hashlib.blake2b(digest_size=16)
            for p in self.photos:
                path = Path(getattr(p.view, "image_path", "") or "")
                h.update(f"{p.name}|{p.intrinsics}|{_file_sample(path)}".encode())
                h.update(np.ascontiguousarray(p.c2w, np.float64).tobytes())
            self._fingerprint = h.hexdigest()
        return self._fingerprint

    def own(self, name: Optional[str], gt_c2w: Optional[np.ndarray]) -> FrozenSet[int]:
        """The photos that are the query's own (same name, or same pose as its truth)."""
        out = set()
        if name is not None and self.index_of(name) is not None:
            out.add(self.index_of(name))
        if gt_c2w is not None:
            out |= {int(i) for i in np.flatnonzero(same_pose_mask(self._c2ws, gt_c2w))}
        return frozenset(out)

    # ------------------------------------------------------------------ lazily made
    def image(self, i: int, side: int):
        """Photo ``i`` as a ``Query`` with its longer side at ``side`` px (loaded once)."""
        from .types import Query

        key = (i, int(side))
        if key not in self._images:
            p = self.photos[i]
            scale = p.intrinsics.scale_to_side(side, enlarge=True)
            im = p.view.load_image(scale=scale, background=self.background)
            intr = p.intrinsics if scale == 1.0 else p.intrinsics.scaled(scale)
            self._images[key] = Query(im.rgb, intr, im.alpha, im.valid, p.name)
        return self._images[key]

    def features(self, i: int, side: int, matcher):
        """The matcher's features of photo ``i`` at ``side`` px (extracted once)."""
        key = (i, int(side))
        if key not in self._features:
            self._features[key] = matcher.extract(self.image(i, side).rgb)
        return self._features[key]

    def depth(self, i: int, side: int, state) -> Tuple[torch.Tensor, torch.Tensor, Intrinsics]:
        """(depth, alpha, intrinsics) of the model rendered at photo ``i``'s camera (once)."""
        key = (i, int(side))
        if key not in self._depth:
            intr = self.image(i, side).intrinsics
            with torch.no_grad():
                out = state.render(invert_rigid(self.photos[i].c2w), intrinsics=intr)
            self._depth[key] = (out.depth.detach(), out.alpha.detach(), intr)
        return self._depth[key]

    # ------------------------------------------------------------------ use
    def nearest(self, c2w: np.ndarray, k: int, exclude: FrozenSet[int] = frozenset(),
                max_angle_deg: float = 60.0) -> List[int]:
        """The ``k`` photos whose cameras are nearest ``c2w`` (looking within ``max_angle_deg``).

        Nearest by ``pose.views.camera_nearness``: the angle between the optical axes plus the
        distance of the centres in units of their median.
        """
        if not self.photos or k <= 0:
            return []
        score, angle = camera_nearness(np.stack([p.c2w for p in self.photos]), c2w)
        order = [int(i) for i in np.argsort(score, kind="stable")
                 if int(i) not in exclude and angle[int(i)] <= max_angle_deg]
        return order[:k]

    def correspondences(self, state, scale: float, c2w: np.ndarray, k: int, cfg,
                        exclude: FrozenSet[int] = frozenset(), subpixel: bool = False
                        ) -> Tuple[np.ndarray, np.ndarray, List[str]]:
        """2D-3D correspondences of the query from the ``k`` photos nearest ``c2w``.

        The query (at working ``scale``) is matched against each photo (at the query's working
        size); the photo's keypoints are lifted with the model's depth at its camera
        (``cfg.min_alpha``, ``cfg.max_depth_jump``), refined to sub-pixel positions against the
        query first with ``subpixel`` (as the render's keypoints are).

        Returns:
            (world points [N, 3], query pixels [N, 2], names of the photos used).
        """
        q = state.query_at(scale)
        side = max(q.intrinsics.width, q.intrinsics.height)
        fq = state.query_features(scale)
        pts, pix, used = [], [], []
        for i in self.nearest(c2w, k, exclude, cfg.anchor_max_angle_deg):
            with state.timed("matcher"):
                m = state.matcher.match_features(self.features(i, side, state.matcher), fq)
            if len(m) < cfg.min_pnp_inliers:
                continue
            depth, alpha, intr = self.depth(i, side, state)
            kpts0 = m.kpts0
            if subpixel:
                from ..matchers.refine import refine_render_keypoints

                with state.timed("pnp"):
                    photo = self.image(i, side).rgb.to(q.rgb)
                    kpts0 = refine_render_keypoints(photo, q.rgb, m.kpts0.to(photo.dtype),
                                                    m.kpts1.to(photo.dtype), window=1,
                                                    iterations=cfg.subpixel_iterations).detach()
            with state.timed("pnp"):
                X, keep = lift_keypoints(kpts0.double(), depth, alpha, intr,
                                         torch.as_tensor(self.photos[i].c2w), cfg.min_alpha,
                                         cfg.max_depth_jump)
            if int(keep.sum()) == 0:
                continue
            pts.append(X.cpu().numpy())
            pix.append(m.kpts1[keep].double().cpu().numpy())
            used.append(self.photos[i].name)
        if not pts:
            return np.zeros((0, 3)), np.zeros((0, 2)), []
        return np.concatenate(pts), np.concatenate(pix), used

