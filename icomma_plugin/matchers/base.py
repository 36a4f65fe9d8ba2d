"""The `Matches` container and the `Matcher` base class (interface fixed in docs/CONTRACTS.md).

Pixel convention: keypoints are `(x, y)` pixels of their own image with pixel centres at integer
coordinates (the 3DGS convention: the first pixel's centre is `(0, 0)`, the image centre is
`((W - 1) / 2, (H - 1) / 2)`). Back-ends whose library uses `+0.5` centres convert on the way out.

`image0` is the RENDER (the image whose keypoints may carry gradients), `image1` the QUERY photo.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Dict, List, Mapping, Optional, Sequence, Tuple

import torch

from .refine import refine_render_keypoints
from ..checks import check_bool, check_int, check_real

logger = logging.getLogger(__name__)

#: Images may leave [0, 1] by this much (a 3DGS render is not clamped: SH colours and the
#: background blend can overshoot slightly); they are clamped before detection. Anything further
#: out is taken for a wrong scale (0..255, mean/std normalised) and rejected.
RANGE_TOLERANCE = 0.25

#: Smallest image side a matcher accepts.
MIN_IMAGE_SIDE = 16


def _check_keypoints(value: Any, name: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise ValueError(
            f"{name} must be a torch.Tensor of shape [N, 2], got {type(value).__name__}"
        )
    if value.ndim != 2 or value.shape[1] != 2:
        raise ValueError(f"{name} must have shape [N, 2], got {tuple(value.shape)}")
    if not value.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {value.dtype}")
    return value


@dataclass(frozen=True)
class Matches:
    """Correspondences between image0 (render) and image1 (query).

    kpts0: [N, 2] float (x, y) pixels of image0; may carry gradients back to image0.
    kpts1: [N, 2] float (x, y) pixels of image1.
    confidence: [N] float, higher is better; in [0, 1] for every built-in matcher.
    subpixel: kpts0 are already sub-pixel positions refined against image1 (``patch_search``):
        a PnP's sub-pixel step leaves them as they are.
    """

    kpts0: torch.Tensor
    kpts1: torch.Tensor
    confidence: torch.Tensor
    subpixel: bool = False

    def __post_init__(self):
        _check_keypoints(self.kpts0, "Matches.kpts0")
        _check_keypoints(self.kpts1, "Matches.kpts1")
        if not isinstance(self.confidence, torch.Tensor) or self.confidence.ndim != 1:
            raise ValueError(
                "Matches.confidence must be a 1-D tensor [N], got "
                f"{getattr(self.confidence, 'shape', type(self.confidence).__name__)}"
            )
        n = self.kpts0.shape[0]
        if self.kpts1.shape[0] != n or self.confidence.shape[0] != n:
            raise ValueError(
                "Matches.kpts0, kpts1 and confidence must have the same length, got "
                f"{n}, {self.kpts1.shape[0]} and {self.confidence.shape[0]}"
            )

    def __len__(self) -> int:
        return int(self.kpts0.shape[0])

    @classmethod
    def empty(
        cls, device: Optional[torch.device] = None, dtype: torch.dtype = torch.float32
    ) -> "Matches":
        """No matches, with tensors on ``device`` of ``dtype``."""
        z = torch.zeros((0, 2), device=device, dtype=dtype)
        return cls(z, z.clone(), torch.zeros((0,), device=device, dtype=dtype))

    def select(self, index: torch.Tensor) -> "Matches":
        """Subset by a boolean mask or an index tensor (gradients of kpts0 are kept)."""
        return Matches(self.kpts0[index], self.kpts1[index], self.confidence[index],
                       self.subpixel)

    def filter(self, min_confidence: float) -> "Matches":
        """The matches whose confidence is >= `min_confidence`."""
        check_real(min_confidence, "min_confidence")
        return self.select(self.confidence >= min_confidence)

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> "Matches":
        """The matches with every tensor moved to ``device`` / cast to ``dtype``."""
        return Matches(
            self.kpts0.to(device=device, dtype=dtype),
            self.kpts1.to(device=device, dtype=dtype),
            self.confidence.to(device=device, dtype=dtype),
            self.subpixel,
        )


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image, from `Matcher.extract` (detector-based matchers).

    kpts: [K, 2] float (x, y) pixels, integer pixel centres.
    desc: [K, D] float descriptors.
    size: (width, height) of the image they were detected in.
    """

    kpts: torch.Tensor
    desc: torch.Tensor
    size: Tuple[int, int]

    def __len__(self) -> int:
        return int(self.kpts.shape[0])


def _mutual_nn_pairs(f0: Features, f1: Features, min_cosine: float, normalize: bool):
    """(mask over f0 [K0], index into f1 [K0], cosine [K0]) of the mutual nearest neighbours."""
    d0, d1 = f0.desc.float(), f1.desc.float()
    if normalize:
        d0 = torch.nn.functional.normalize(d0, dim=-1)
        d1 = torch.nn.functional.normalize(d1, dim=-1)
    sim = d0 @ d1.T
    best1 = sim.argmax(1)
    best0 = sim.argmax(0)
    idx0 = torch.arange(len(f0), device=sim.device)
    cos = sim[idx0, best1]
    return (best0[best1] == idx0) & (cos > min_cosine), best1, cos


def mutual_nn(f0: Features, f1: Features, min_cosine: float = 0.8,
              normalize: bool = True) -> Matches:
    """Mutual nearest neighbours of two descriptor sets whose cosine exceeds `min_cosine`.

    The confidence is the cosine (clamped to [0, 1]). `normalize=False` takes descriptors that are
    unit vectors already (XFeat's).
    """
    if len(f0) == 0 or len(f1) == 0:
        return Matches.empty(f0.kpts.device)
    ok, best1, cos = _mutual_nn_pairs(f0, f1, min_cosine, normalize)
    return Matches(f0.kpts[ok].float(), f1.kpts[best1[ok]].float(),
                   cos[ok].float().clamp(0.0, 1.0))


def mutual_nn_count(f0: Features, f1: Features, min_cosine: float = 0.8) -> int:
    """Number of `mutual_nn` matches: a cheap similarity of two images (ranks candidate views).

    Only counted: no `Matches` is built (it runs for every candidate view and turn).
    """
    if len(f0) == 0 or len(f1) == 0:
        return 0
    return int(_mutual_nn_pairs(f0, f1, min_cosine, True)[0].sum())


class DescriptorStack:
    """Many images' descriptors in one tensor, to count mutual nearest neighbours in one pass.

    `mutual_nn_counts` gives, for every image, what `mutual_nn_count(image, f1)` gives, from
    batched products instead of one small product per image (the candidate views' ranking:
    hundreds of views, four turns of the photo). The descriptors are made unit length once and
    padded with rows that never win a nearest-neighbour search.
    """

    def __init__(self, features: Sequence[Optional[Features]]):
        self.size = len(features)
        self.rows = [i for i, f in enumerate(features) if f is not None and len(f) > 0]
        k = max((len(features[i]) for i in self.rows), default=0)
        d = features[self.rows[0]].desc.shape[1] if self.rows else 0
        self.empty = [i for i, f in enumerate(features) if f is not None and len(f) == 0]
        # one more column: 0 in real rows, -2 in padding rows, against a 1 appended to the other
        # image's descriptors: a padding row's cosine is -2 and a real one's is unchanged
        self.desc = torch.zeros(len(self.rows), k, d + 1)
        self.desc[:, :, d] = -2.0
        self.valid = torch.zeros(len(self.rows), k, dtype=torch.bool)
        for r, i in enumerate(self.rows):
            f = features[i]
            self.desc[r, : len(f), :d] = torch.nn.functional.normalize(f.desc.float().cpu(), dim=-1)
            self.desc[r, : len(f), d] = 0.0
            self.valid[r, : len(f)] = True

    def mutual_nn_counts(self, f1: Features, min_cosine: float = 0.8,
                         chunk_bytes: int = 4 << 20) -> List[int]:
        """Each image's `mutual_nn_count` with ``f1`` (-1 for an image without features)."""
        out = [-1] * self.size
        for i in self.empty + (self.rows if len(f1) == 0 else []):
            out[i] = 0
        if not self.rows or len(f1) == 0:
            return out
        d1 = torch.nn.functional.normalize(f1.desc.float().cpu(), dim=-1)
        d1 = torch.cat([d1, torch.ones(len(d1), 1)], 1)
        k = self.desc.shape[1]
        step = max(1, chunk_bytes // max(4 * k * len(d1), 1))
        for lo in range(0, len(self.rows), step):
            valid = self.valid[lo: lo + step]
            sim = torch.matmul(self.desc[lo: lo + step], d1.T)  # [n, K, K1]
            # a pair is mutual when its cosine is the largest of its row and of its column: two
            # value-only reductions and one comparison, over 4 MB chunks that stay in the cache
            # (1.0-2.3x faster than max with indices along both dims: docs/SPEED.md); a row
            # counts at most once
            row = sim.amax(2, keepdim=True)  # [n, K, 1]
            mutual = (sim >= torch.maximum(row, sim.amax(1, keepdim=True))).any(2)  # [n, K]
            counts = (mutual & (row[..., 0] > min_cosine) & valid).sum(1)
            for r, n in enumerate(counts.tolist()):
                out[self.rows[lo + r]] = int(n)
        return out


def patch_search(image0: torch.Tensor, image1: torch.Tensor, kpts1: torch.Tensor,
                 window: int = 3, min_ncc: float = 0.8, iterations: int = 0,
                 min_margin: Optional[float] = None) -> Matches:
    """The keypoints ``kpts1`` of image1 (the query) found in image0 near the same positions.

    image0 is a render from nearly the same pose; each keypoint is searched for within ``window``
    pixels of its own position. No features of image0 and no matching step: each query patch is
    compared with the render's around its own position by normalised cross-correlation (an
    integer search over ``(2 window + 1)^2`` positions, then one sub-pixel step:
    ``refine_render_keypoints``), and kept where the NCC there exceeds ``min_ncc`` (the
    confidence). For renders within a few pixels of the photo (tracking: a render at the
    predicted pose); a render further off keeps few, or matches moved by most of the window. The
    matches' ``kpts0`` are sub-pixel already (``Matches.subpixel``). No gradients.

    ``min_margin``: also drop the keypoints whose NCC peak stands less than this above the best
    score 2 or more pixels from it (`refine.peak_margin`): on a flat surface (a soft render, a
    texture-less or repeating patch) the peak's place says nothing, and such matches stay where
    they were, agreeing with whatever pose the render was made at. None: no such test.
    """
    check_int(window, "window", 1)
    check_real(min_ncc, "min_ncc", -1.0, 1.0)
    check_int(iterations, "iterations", 0)
    check_real(min_margin, "min_margin", 0.0, optional=True)
    k1 = _check_keypoints(kpts1, "kpts1")
    if len(k1) == 0:
        return Matches.empty(image0.device, image0.dtype)
    with torch.no_grad():
        k1 = k1.to(image0.device, image0.dtype)
        k0, ncc, margin = refine_render_keypoints(image0.detach(), image1.detach(), k1.clone(),
                                                  k1, window=window, iterations=iterations,
                                                  return_score=True, return_margin=True)
        keep = ncc > min_ncc
        if min_margin is not None:
            keep &= margin > min_margin
        return Matches(k0[keep], k1[keep], ncc[keep].clamp(0.0, 1.0), subpixel=True)


def on_device(module: torch.nn.Module, device: torch.device) -> torch.nn.Module:
    """``module`` on ``device``, moved only when it is elsewhere.

    ``Module.to`` walks every parameter even when nothing moves: ~40 ms of a lego localization.
    """
    first = next(module.parameters(), None)
    if first is not None and first.device != torch.device(device):
        module.to(device)
    return module


def check_image(image: Any, name: str) -> torch.Tensor:
    """Validate a `[3, H, W]` float image in [0, 1] (see `RANGE_TOLERANCE`).

    Raises:
        ValueError: naming `name`, when the image is not such a tensor.
    """
    if not isinstance(image, torch.Tensor):
        raise ValueError(
            f"{name} must be a torch.Tensor [3, H, W] in [0, 1], got {type(image).__name__}"
        )
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(
            f"{name} must have shape [3, H, W] (RGB, no batch dimension), got {tuple(image.shape)}"
        )
    if not image.is_floating_point():
        raise ValueError(
            f"{name} must be a floating-point tensor in [0, 1], got dtype {image.dtype}"
        )
    h, w = image.shape[1:]
    if h < MIN_IMAGE_SIDE or w < MIN_IMAGE_SIDE:
        raise ValueError(
            f"{name} must be at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} pixels, got {h}x{w} (HxW)"
        )
    with torch.no_grad():  # one pass: the extremes are NaN or infinite when any value is
        lo, hi = (float(v) for v in torch.aminmax(image))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if lo < -RANGE_TOLERANCE or hi > 1.0 + RANGE_TOLERANCE:
        raise ValueError(
            f"{name} must hold values in [0, 1] (float RGB), got the range [{lo:.3g}, {hi:.3g}]; "
            "divide 8-bit images by 255 and do not mean/std-normalise"
        )
    return image


class Matcher:
    """Base class of every matcher. Subclasses implement `_match` on detached, clamped images.

    What a matcher is and needs are class attributes, read by `available_matchers()` (a new
    matcher sets them; see docs/MATCHERS.md, "Adding a matcher"):

    Attributes:
        name: the matcher's name (records, messages; a built-in's key in `BUILTIN_MATCHERS`).
        weight_ids: ids of `weights.WEIGHT_FILES` it loads by default (packaged weights).
        python_modules: import name -> PyPI name of the modules it imports (looked up, not
            imported, e.g. ``{"cv2": "opencv-python-headless"}``).
        required_arguments: argument -> what to pass, for arguments it cannot be built without
            (LoFTR's ``checkpoint``).
        supports_image_gradient: with `differentiable=True`, `kpts0` carries gradients back to
            `image0` (through `refine.refine_render_keypoints`, the LoFTR-fine-style step).
        min_confidence: matches below this confidence are dropped.
        max_matches: keep at most this many matches (highest confidence first); None keeps all.
        refine: keyword arguments of `refine_render_keypoints` (window, patch, temperature, ...).
        min_detect_side: images whose longer side is below this are enlarged by an integer
            factor for detection (keypoints are returned in the image's own pixels); 0 disables.
            The longer side, as `CandidateConfig.rank_side`: ranking images are left as they are.
    """

    name: str = "base"
    weight_ids: ClassVar[Tuple[str, ...]] = ()
    python_modules: ClassVar[Mapping[str, str]] = {}
    required_arguments: ClassVar[Mapping[str, str]] = {}
    supports_image_gradient: bool = True
    #: `extract` / `match_features` work (keypoints and descriptors can be computed once per image
    #: and reused, e.g. the query's across the iterations of a localization).
    supports_features: bool = False

    def __init__(self, *, min_confidence: float = 0.0, max_matches: Optional[int] = None,
                 refine: Optional[Dict[str, Any]] = None, min_detect_side: int = 128):
        check_real(min_confidence, "min_confidence")
        self.min_detect_side = check_int(min_detect_side, "min_detect_side", 0)
        check_int(max_matches, "max_matches", 1, optional=True)
        if refine is not None and not isinstance(refine, dict):
            raise ValueError(
                f"refine must be a dict of refine_render_keypoints arguments, got {refine!r}"
            )
        self.min_confidence = float(min_confidence)
        self.max_matches = max_matches
        self.refine = dict(refine or {})

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"

    def _upsampled(self, image: torch.Tensor) -> Tuple[torch.Tensor, int]:
        """``image`` enlarged by an integer factor when it is small, and that factor.

        Below ``min_detect_side`` px (longer side) detectors find few keypoints: 0 matches at
        64 px on the demo, 133 at 128.
        """
        side = max(int(image.shape[1]), int(image.shape[2]))
        if not self.min_detect_side or side >= self.min_detect_side:
            return image, 1
        f = -(-self.min_detect_side // side)
        up = torch.nn.functional.interpolate(image[None], scale_factor=f, mode="bilinear",
                                             align_corners=False)[0]
        return up.clamp(0.0, 1.0), f

    @staticmethod
    def _shrunk(kpts: torch.Tensor, f: int) -> torch.Tensor:
        """Pixel positions in an image enlarged ``f`` times, back in the original.

        Pixel centres sit at integers: ``x = (x_up + 0.5) / f - 0.5``.
        """
        return kpts if f == 1 else (kpts + 0.5) / f - 0.5

    def _features_of(self, image: torch.Tensor) -> Features:
        up, f = self._upsampled(image)
        feats = self._extract(up)
        if f == 1:
            return feats
        size = (int(image.shape[2]), int(image.shape[1]))
        return Features(self._shrunk(feats.kpts, f), feats.desc, size)

    def _match_images(self, image0: torch.Tensor, image1: torch.Tensor) -> Matches:
        if self.supports_features:
            return self._match_features(self._features_of(image0), self._features_of(image1))
        up0, f0 = self._upsampled(image0)
        up1, f1 = self._upsampled(image1)
        m = self._match(up0, up1)
        return Matches(self._shrunk(m.kpts0, f0), self._shrunk(m.kpts1, f1), m.confidence)

    def _extract(self, image: torch.Tensor) -> Features:
        """Keypoints and descriptors of a detached, clamped image (detector-based matchers)."""
        raise NotImplementedError

    def _match_features(self, f0: Features, f1: Features) -> Matches:
        """Match two feature sets (detector-based matchers)."""
        raise NotImplementedError

    def _match(self, image0: torch.Tensor, image1: torch.Tensor) -> Matches:
        """Match two detached images `[3, H, W]` in [0, 1]; keypoints in the module's convention.

        Detector-based matchers implement `_extract` and `_match_features` instead.
        """
        return self._match_features(self._extract(image0), self._extract(image1))

    def extract(self, image: torch.Tensor) -> Features:
        """Keypoints and descriptors of `image` ([3, H, W] in [0, 1]).

        For `match(..., features1=...)` and `match_features`. Only where `supports_features`.

        Raises:
            ValueError: the matcher does not support features, or a bad image.
        """
        if not self.supports_features:
            raise ValueError(f"the {self.name!r} matcher cannot extract features on their own "
                             "(supports_features is False); call match() on the images")
        check_image(image, "image")
        with torch.no_grad():
            return self._features_of(image.detach().clamp(0.0, 1.0))

    def _finish(self, m: Matches, device, dtype) -> Matches:
        m = Matches(
            m.kpts0.to(device, dtype), m.kpts1.to(device, dtype), m.confidence.to(device, dtype)
        )
        if self.min_confidence > 0:
            m = m.filter(self.min_confidence)
        if self.max_matches is not None and len(m) > self.max_matches:
            m = m.select(torch.argsort(m.confidence, descending=True)[: self.max_matches])
        return m

    def match_features(self, features0: Features, features1: Features) -> Matches:
        """Match two feature sets from `extract` (no gradients)."""
        if not self.supports_features:
            raise ValueError(
                f"the {self.name!r} matcher has no match_features (supports_features is False)"
            )
        for name, f in (("features0", features0), ("features1", features1)):
            if not isinstance(f, Features):
                raise ValueError(
                    f"{name} must be a Features (from extract()), got {type(f).__name__}"
                )
        with torch.no_grad():
            m = self._match_features(features0, features1)
            return self._finish(m, features0.kpts.device, torch.float32)

    def match_mutual_nn(self, image0: torch.Tensor, features1: Features,
                        min_cosine: float) -> Matches:
        """Match `image0` with the image of `features1`: `mutual_nn` of this matcher's descriptors.

        The matcher's own matching step (LightGlue, ...) is skipped: much cheaper, for images
        taken from nearly the same pose. Only where `supports_features`.
        """
        f0 = self.extract(image0)
        with torch.no_grad():
            return self._finish(mutual_nn(f0, features1, min_cosine), image0.device, image0.dtype)

    def match(self, image0: torch.Tensor, image1: torch.Tensor, differentiable: bool = False,
              features1: Optional[Features] = None) -> Matches:
        """Match `image0` (render) with `image1` (query).

        With `differentiable=True`, `kpts0` is re-estimated by `refine_render_keypoints` so that it
        carries gradients back to `image0`; `kpts1` and `confidence` never do. `features1` (from
        `extract(image1)`, where `supports_features`) skips detecting the query again.
        """
        check_image(image0, "image0")
        check_image(image1, "image1")
        check_bool(differentiable, "differentiable")
        if differentiable and not self.supports_image_gradient:
            raise ValueError(f"differentiable=True is not supported by the {self.name!r} matcher")
        if features1 is not None:
            if not self.supports_features or not isinstance(features1, Features):
                raise ValueError(
                    "features1 must be the Features of image1 from this matcher's extract(), "
                    f"got {type(features1).__name__} for matcher {self.name!r}"
                )
            if tuple(features1.size) != (int(image1.shape[2]), int(image1.shape[1])):
                raise ValueError(
                    f"features1 were extracted from a {features1.size[0]}x{features1.size[1]} "
                    f"image, but image1 is {image1.shape[2]}x{image1.shape[1]}"
                )
        with torch.no_grad():
            if features1 is not None:
                m = self._match_features(self._features_of(image0.detach().clamp(0.0, 1.0)),
                                         features1)
            else:
                m = self._match_images(image0.detach().clamp(0.0, 1.0),
                                       image1.detach().clamp(0.0, 1.0))
            m = self._finish(m, image0.device, image0.dtype)
        if differentiable and len(m) > 0:
            kpts0 = refine_render_keypoints(
                image0, image1.detach(), m.kpts0, m.kpts1, **self.refine
            )
            m = Matches(kpts0, m.kpts1, m.confidence)
        return m
