"""LoFTR (kornia), the paper's matcher, from a checkpoint the user supplies. Never downloads.

No installable package ships LoFTR weights, and kornia's `LoFTR(pretrained=...)` downloads them,
so this builds `LoFTR(pretrained=None)` and loads `torch.load(checkpoint)['state_dict']` (the
`matcher.` prefix of the authors' checkpoints is stripped by kornia's `load_state_dict`).

As in iComMa, the QUERY is LoFTR's image0 (keypoints on the 1/8 coarse grid) and the RENDER its
image1 (keypoints moved by LoFTR's fine step). kornia's LoFTR outputs put pixel centres at
`+0.5`; they are shifted to the 3DGS convention (integer centres). kornia's matching steps are
`@torch.no_grad()`, so the gradient to the render comes from `refine.refine_render_keypoints`.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from .base import Matcher, Matches, on_device
from .weights import MissingWeightsError

logger = logging.getLogger(__name__)

CHECKPOINT_HELP = (
    "LoFTR needs a checkpoint file, which no package ships and which is never downloaded: get "
    "outdoor_ds.ckpt (the checkpoint iComMa uses) from the LoFTR authors' release "
    "(github.com/zju3dv/LoFTR, README 'Download the pretrained weights', Google Drive folder "
    "'weights'), or kornia's loftr_outdoor.ckpt, and pass its path: "
    "matcher.checkpoint=/path/to/outdoor_ds.ckpt "
    "(Python: make_matcher('loftr', checkpoint='/path/to/outdoor_ds.ckpt')); or pick another "
    "matcher, e.g. matcher=xfeat"
)


def _gray(image: torch.Tensor) -> torch.Tensor:
    w = image.new_tensor((0.299, 0.587, 0.114)).view(3, 1, 1)
    return (image * w).sum(0, keepdim=True)[None]


class LoFTRMatcher(Matcher):
    """kornia LoFTR loaded from `checkpoint`.

    Args:
        checkpoint: path of a LoFTR checkpoint ({'state_dict': ...} or a bare state dict).
        resize: optional (H, W) at which LoFTR runs (iComMa: (480, 640)); None: native size.
        temp_bug_fix: positional-encoding flag; False for outdoor_ds.ckpt (as iComMa), True for
            indoor_ds_new.ckpt.
        coarse_threshold: dual-softmax threshold of the coarse matches (LoFTR and iComMa: 0.2).
        min_confidence, max_matches, refine: see `Matcher` (iComMa keeps confidence > 0.5).
    """

    name = "loftr"
    python_modules = {"kornia": "kornia"}
    required_arguments = {
        "checkpoint": "a user-supplied LoFTR checkpoint file: "
                      "matcher.checkpoint=/path/to/outdoor_ds.ckpt (never downloaded)",
    }

    def __init__(self, checkpoint: Optional[str] = None, resize: Optional[Sequence[int]] = None,
                 temp_bug_fix: bool = False, coarse_threshold: float = 0.2, **kwargs):
        super().__init__(**kwargs)
        if checkpoint is None or (isinstance(checkpoint, str) and not checkpoint.strip()):
            raise ValueError(f"checkpoint is required: {CHECKPOINT_HELP}")
        if not isinstance(checkpoint, (str, Path)):
            raise ValueError(
                f"checkpoint must be a path, got {type(checkpoint).__name__}. {CHECKPOINT_HELP}"
            )
        path = Path(checkpoint).expanduser()
        if not path.is_file():
            raise MissingWeightsError(f"checkpoint {str(path)!r} not found. {CHECKPOINT_HELP}")
        if resize is not None:
            if len(resize) != 2 or any((not isinstance(v, int)) or v < 32 for v in resize):
                raise ValueError(f"resize must be None or (H, W) ints >= 32, got {resize!r}")
            resize = (int(resize[0]), int(resize[1]))
        self.resize = resize
        from kornia.feature import LoFTR
        from kornia.feature.loftr.loftr import default_cfg
        import copy

        cfg = copy.deepcopy(default_cfg)
        cfg["coarse"]["temp_bug_fix"] = bool(temp_bug_fix)
        if not isinstance(coarse_threshold, (int, float)) or not 0.0 <= coarse_threshold < 1.0:
            raise ValueError(f"coarse_threshold must be in [0, 1), got {coarse_threshold!r}")
        cfg["match_coarse"]["thr"] = float(coarse_threshold)
        self.model = LoFTR(pretrained=None, config=cfg)
        try:
            ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - re-raised with the path
            raise ValueError(
                f"checkpoint {str(path)!r} could not be read as a torch checkpoint: {exc}"
            ) from exc
        sd = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
        if not isinstance(sd, dict):
            raise ValueError(f"checkpoint {str(path)!r} holds no state dict")
        try:
            self.model.load_state_dict(dict(sd))
        except RuntimeError as exc:
            raise ValueError(
                f"checkpoint {str(path)!r} does not fit kornia's LoFTR: {exc}"
            ) from exc
        self.model.eval()
        self.checkpoint = str(path)

    def _match(self, image0: torch.Tensor, image1: torch.Tensor) -> Matches:
        dev = image0.device
        on_device(self.model, dev)
        render, query = _gray(image0.float()), _gray(image1.float())
        sr = sq = (1.0, 1.0)
        if self.resize is not None:
            h, w = self.resize
            sr = (image0.shape[2] / w, image0.shape[1] / h)
            sq = (image1.shape[2] / w, image1.shape[1] / h)
            render = F.interpolate(
                render, (h, w), mode="bilinear", align_corners=False, antialias=True
            )
            query = F.interpolate(
                query, (h, w), mode="bilinear", align_corners=False, antialias=True
            )
        out = self.model({"image0": query, "image1": render})
        kq, kr, conf = out["keypoints0"], out["keypoints1"], out["confidence"]
        # +0.5 centres of the (resized) image -> integer centres of the input image
        kr = kr * kr.new_tensor(sr) - 0.5
        kq = kq * kq.new_tensor(sq) - 0.5
        return Matches(kr.float(), kq.float(), conf.float())
