"""Dataset views at the size a fit works at, for the trainer and the evaluation alike.

`-r/--resolution` follows upstream 3DGS: 1, 2, 4, 8 divide the size, any other positive value is
a target width in pixels, -1 caps the width at 1600; `downscale` divides by any factor.
"""

from __future__ import annotations

import math
from typing import List, Optional

import torch

from .trainer import FitView


def resolution_scale(resolution: Optional[int], downscale: Optional[float], width: int) -> float:
    """Image scale factor of an original `width`-wide image.

    Upstream `-r` semantics (module docstring).
    """
    if downscale is not None and resolution not in (None, -1):
        raise ValueError(
            f"give either resolution or downscale, not both (got resolution={resolution!r}, "
            f"downscale={downscale!r})"
        )
    if downscale is not None:
        if isinstance(downscale, bool) or not isinstance(downscale, (int, float)) or not (
                math.isfinite(downscale) and downscale > 0):
            raise ValueError(f"downscale must be a positive finite number, got {downscale!r}")
        return 1.0 / float(downscale)
    r = -1 if resolution is None else resolution
    if isinstance(r, bool) or not isinstance(r, int) or r == 0 or r < -1:
        raise ValueError(
            f"resolution must be -1 (auto), 1, 2, 4, 8 (divide) or a target width in pixels, "
            f"got {resolution!r}"
        )
    if r == -1:
        return 1600.0 / width if width > 1600 else 1.0
    if r in (1, 2, 4, 8):
        return 1.0 / r
    return r / float(width)


TINY_SIDE = 64  # pixels: a fitted image with a side under this is almost surely a mistake


def tiny_resolution_message(resolution: Optional[int], downscale: Optional[float],
                            intrinsics) -> Optional[str]:
    """A warning when `-r` read as a target width (upstream's rule) makes the images tiny.

    Upstream's `-r` divides the size for 1, 2, 4, 8 and is a target width in pixels otherwise,
    so `-r 6` means "6 px wide", not "a sixth". Returns the message (naming the flag and what the
    user probably meant) when a side of the result is under `TINY_SIDE`, else None.
    """
    if downscale is not None or resolution in (None, -1, 1, 2, 4, 8):
        return None
    small = intrinsics.scaled(resolution_scale(resolution, None, intrinsics.width))
    if min(small.width, small.height) >= TINY_SIDE:
        return None
    return (f"-r/--resolution {resolution} is a target width in pixels (upstream 3DGS's rule for "
            f"values other than 1, 2, 4, 8): the {intrinsics.width}x{intrinsics.height} images "
            f"become {small.width}x{small.height} px. -r 1/2/4/8 are downscale factors; to divide "
            f"the size by {resolution}, use --downscale {resolution} (downscale={resolution}).")


def cfg_resolution_value(resolution: Optional[int], downscale: Optional[float], width: int) -> int:
    """The `resolution` to store in cfg_args so that upstream reproduces the same image size."""
    if downscale is None:
        return -1 if resolution is None else int(resolution)
    if float(downscale) in (1.0, 2.0, 4.0, 8.0):
        return int(downscale)
    return max(1, int(round(width / float(downscale))))


def views_to_fit(views, resolution, downscale, background, dtype=torch.float32, device=None,
                 keep_alpha: bool = False) -> List[FitView]:
    """Load dataset `View`s at the requested resolution, composited over `background`.

    With their validity masks (pixels filled by undistortion are left out of losses and PSNR).
    """
    out = []

    def to(t):
        return None if t is None else t.to(dtype=dtype, device=device)

    for v in views:
        s = resolution_scale(resolution, downscale, v.intrinsics.width)
        im = v.load_image(scale=s, background=background)
        intr = v.intrinsics.scaled(s)
        w2c = torch.as_tensor(v.w2c, dtype=dtype, device=device)
        out.append(
            FitView(
                v.name,
                to(im.rgb),
                intr,
                w2c,
                alpha=to(im.alpha) if keep_alpha else None,
                valid=to(im.valid),
            )
        )
    return out
