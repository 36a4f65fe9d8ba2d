"""Camera localisation against a 3DGS model: the one-off entry point.

    result = localize(model, query, matcher=matcher, init_c2w=start_c2w)      # the default
    result = localize(model, query, matcher=matcher, cameras=model_cameras)   # no start pose
    result = localize(model, query, matcher=matcher, init_c2w=start_c2w,
                      config=LocalizerConfig())                               # the paper's
    result.c2w, result.verdict.status, result.verdict.reason

``localize`` builds a :class:`~icomma_plugin.localization.localizer.Localizer` and localizes one
query with it. To localize several photos against one model, build the Localizer once and call
its ``localize`` for each: it prepares the model and the candidate views once.

Two methods, chosen by the ``config``:

- :class:`RobustConfig` (the default, ``localization/robust.py``): geometric stage (render, match,
  lift with the rendered depth, PnP), candidate views when the start is unusable or absent,
  photometric refinement with roll-back;
- :class:`LocalizerConfig` (the paper's iComMa, ``localization/icomma.py``): Adam on se(3), a
  matching stage and then a comparing stage, exactly as published.

Both end with a verdict (``ok | uncertain | failed``, ``localization/verify.py``) judged without
ground truth; ``gt_c2w`` is used only to report errors.
"""
from __future__ import annotations

from typing import Any, Callable, Optional

from .gaussians import GaussianModel
from .localization.icomma import GRADIENT_MODES, LocalizerConfig
from .localization.localizer import Localizer
from .localization.robust import RobustConfig
from .localization.types import LocalizationResult, Query, TraceRecord, Verdict

__all__ = ["GRADIENT_MODES", "LocalizationResult", "Localizer", "LocalizerConfig", "Query",
           "RobustConfig", "TraceRecord", "Verdict", "localize"]


def localize(
    model: GaussianModel,
    query: Query,
    *,
    matcher=None,
    config=None,
    init_c2w=None,
    gt_c2w=None,
    progress: Optional[Callable[[TraceRecord], Any]] = None,
    **options: Any,
) -> LocalizationResult:
    """Estimate the camera pose of ``query`` in ``model`` (a one-off :class:`Localizer`).

    Args:
        model: the 3DGS scene.
        query: the photo (:class:`Query`: ``[3, H, W]`` image in [0, 1], intrinsics, masks).
        matcher: an ``icomma_plugin.matchers.Matcher`` (the default method needs one).
        config: :class:`RobustConfig` (default) or :class:`LocalizerConfig` (the paper's).
        init_c2w: ``[4, 4]`` start pose, camera-to-world (OpenCV axes); None: no start pose.
        gt_c2w: the true pose, used ONLY to report errors.
        progress: called with each trace record as it is made.
        **options: the Localizer's keyword options (``cameras``, ``backend``, ``background``,
            ``model_side``, ``cache_dir``).
    """
    localizer = Localizer(model, matcher, config, **options)
    return localizer.localize(query, init_c2w=init_c2w, gt_c2w=gt_c2w, progress=progress)
