"""Tile-based front-to-back alpha blending (upstream ``renderCUDA``), pure PyTorch.

Loops over 16x16 tiles; within a tile it is dense over the tile's Gaussians (those whose tile
rect contains the tile, in depth order). Per pixel and Gaussian:
``power = -0.5 (c00 dx^2 + c11 dy^2) - c01 dx dy`` (skipped if > 0),
``alpha = min(0.99, o exp(power))`` (skipped if < 1/255). The pixel stops BEFORE the Gaussian
whose ``T (1 - alpha)`` would fall below 1e-4: a Gaussian contributes iff the inclusive cumulative
product of ``(1 - alpha)`` up to it is >= 1e-4. ``T_i`` is the exclusive cumulative product.
"""
from __future__ import annotations

from typing import Tuple

import torch

from .projection import BLOCK

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
CHUNK = 128  # Gaussians per step within a tile (memory/speed trade-off only)


def _tile_alpha(xy, conic, opacity, pix):
    """alpha [N, K] after the power > 0 and 1/255 skips (skipped entries are 0)."""
    d = xy[None, :, :] - pix[:, None, :]  # d = xy - pix (upstream)
    dx, dy = d[..., 0], d[..., 1]
    power = -0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) - conic[:, 1] * dx * dy
    alpha = torch.clamp_max(opacity * torch.exp(power), ALPHA_MAX)
    valid = (power <= 0) & (alpha >= ALPHA_MIN)
    return torch.where(valid, alpha, torch.zeros_like(alpha))


def _blend_tile(xy, conic, opacity, feats, members, pix, inside, chunk: int = CHUNK):
    """Blend one tile front to back over `members` (depth order) in chunks, carrying T.

    Stops early once every pixel of the tile (inside the image) has hit the T < 1e-4 stop.

    Returns:
        (acc [N, F], T_final [N]).
    """
    N = pix.shape[0]
    T_carry = torch.ones(N, dtype=xy.dtype, device=xy.device)
    done = ~inside  # pixels outside the image are done from the start (cropped anyway)
    acc = None
    for ids in members.split(chunk):
        a = _tile_alpha(xy[ids], conic[ids], opacity[ids], pix)  # [N, C]
        with torch.no_grad():
            # contributes iff the pixel has not stopped and T (1 - a) stays >= 1e-4 up to here
            mask = (T_carry[:, None] * torch.cumprod(1.0 - a, dim=1) >= T_MIN) & ~done[:, None]
        a = a * mask
        incl = torch.cumprod(1.0 - a, dim=1)
        T = T_carry[:, None] * torch.cat([torch.ones_like(incl[:, :1]), incl[:, :-1]], 1)
        # elementwise multiply-sum, not a matmul: tiny BLAS calls can stall on busy multi-core hosts
        part = ((a * T)[:, :, None] * feats[ids][None, :, :]).sum(1)  # [N, F]
        acc = part if acc is None else acc + part
        T_carry = T_carry * incl[:, -1]
        done = done | ~mask[:, -1]
        if bool(done.all()):
            break
    return acc, T_carry


def blend(
    xy, conic, opacity, feats, depth, rect_min, rect_max, *, image_height, image_width
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Blend the kept Gaussians.

    Args:
        xy: [K, 2] pixel positions.
        conic: [K, 3].
        opacity: [K].
        feats: [K, F] the features to blend.
        depth: [K] the sort key.
        rect_min: [K, 2] long, first tile (x, y) of each Gaussian's rect.
        rect_max: [K, 2] long, its exclusive end.
        image_height: H.
        image_width: W.

    Returns:
        (accumulated features [F, H, W], T_final [1, H, W]).
    """
    H, W = image_height, image_width
    gx, gy = (W + BLOCK - 1) // BLOCK, (H + BLOCK - 1) // BLOCK
    dev, dt = xy.device, xy.dtype
    F = feats.shape[1]
    order = torch.sort(depth.detach(), stable=True).indices  # ties by index
    xy, conic, opacity, feats = xy[order], conic[order], opacity[order], feats[order]
    rmin, rmax = rect_min[order], rect_max[order]

    local = torch.arange(BLOCK, device=dev, dtype=dt)
    tiles_out = []
    tiles_T = []
    for ty in range(gy):
        row_out, row_T = [], []
        in_row = (rmin[:, 1] <= ty) & (ty < rmax[:, 1])
        for tx in range(gx):
            members = torch.nonzero(in_row & (rmin[:, 0] <= tx) & (tx < rmax[:, 0])).flatten()
            if members.numel() == 0:
                row_out.append(torch.zeros(F, BLOCK, BLOCK, device=dev, dtype=dt))
                row_T.append(torch.ones(1, BLOCK, BLOCK, device=dev, dtype=dt))
                continue
            py, px = torch.meshgrid(ty * BLOCK + local, tx * BLOCK + local, indexing="ij")
            pix = torch.stack([px.reshape(-1), py.reshape(-1)], -1)  # [256, 2] (x, y)
            inside = (pix[:, 0] < W) & (pix[:, 1] < H)
            acc, T_fin = _blend_tile(xy, conic, opacity, feats, members, pix, inside)
            row_out.append(acc.T.reshape(F, BLOCK, BLOCK))
            row_T.append(T_fin.reshape(1, BLOCK, BLOCK))
        tiles_out.append(torch.cat(row_out, 2))
        tiles_T.append(torch.cat(row_T, 2))
    if not tiles_out:
        return torch.zeros(F, H, W, device=dev, dtype=dt), torch.ones(1, H, W, device=dev, dtype=dt)
    out = torch.cat(tiles_out, 1)[:, :H, :W]
    T_final = torch.cat(tiles_T, 1)[:, :H, :W]
    return out, T_final
