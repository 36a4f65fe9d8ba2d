"""Pure-PyTorch reference backend: the numerical oracle.

Any device, float32/float64, backward by autograd.

`rasterize_gaussians_reference` follows the internal backend contract of docs/CONTRACTS.md.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch

from .blend import blend
from .projection import preprocess
from .sh import eval_sh, sh_to_rgb

__all__ = ["rasterize_gaussians_reference", "eval_sh", "sh_to_rgb"]


def rasterize_gaussians_reference(
    means3D: torch.Tensor,
    means2D: Optional[torch.Tensor],
    opacities: torch.Tensor,
    shs: Optional[torch.Tensor],
    colors_precomp: Optional[torch.Tensor],
    scales: Optional[torch.Tensor],
    rotations: Optional[torch.Tensor],
    cov3D_precomp: Optional[torch.Tensor],
    bg: torch.Tensor,
    viewmatrix: torch.Tensor,
    projmatrix: torch.Tensor,
    campos: torch.Tensor,
    *,
    image_height: int,
    image_width: int,
    tanfovx: float,
    tanfovy: float,
    scale_modifier: float,
    sh_degree: int,
    prefiltered: bool = False,
    antialiasing: bool = False,
    shs_rest: Optional[torch.Tensor] = None,
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> (color [3,H,W], radii [P] int32, invdepth [1,H,W], depth_acc [1,H,W], alpha [1,H,W]).

    `prefiltered` is accepted for API parity and ignored (as upstream's culling ignores it).
    `shs_rest`: the SH coefficients after the first (``shs`` then holds the first), joined here.
    """
    if shs_rest is not None:
        shs = torch.cat([shs, shs_rest], dim=1)
    P = means3D.shape[0]
    proj = preprocess(
        means3D,
        means2D,
        opacities,
        scales,
        rotations,
        cov3D_precomp,
        viewmatrix,
        projmatrix,
        image_height=image_height,
        image_width=image_width,
        tanfovx=tanfovx,
        tanfovy=tanfovy,
        scale_modifier=scale_modifier,
        antialiasing=antialiasing,
    )
    ids = proj.ids
    if colors_precomp is not None:
        rgb = colors_precomp.index_select(0, ids)
    else:
        rgb = sh_to_rgb(sh_degree, shs.index_select(0, ids), means3D.index_select(0, ids), campos)
    z = proj.depth
    feats = torch.cat([rgb, (1.0 / z)[:, None], z[:, None]], -1)  # [K, 5]
    acc, T_final = blend(
        proj.xy,
        proj.conic,
        proj.opacity,
        feats,
        z,
        proj.rect_min,
        proj.rect_max,
        image_height=image_height,
        image_width=image_width,
    )
    color = acc[:3] + T_final * bg[:, None, None]
    invdepth = acc[3:4]
    depth_acc = acc[4:5]
    alpha = 1.0 - T_final
    radii = torch.zeros(P, dtype=torch.int32, device=means3D.device)
    radii[ids] = proj.radius.to(torch.int32)
    return color, radii, invdepth, depth_acc, alpha
