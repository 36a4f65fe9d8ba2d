"""Differentiable sub-pixel refinement of rendered keypoints (iComMa's "image" gradient mode).

iComMa patches LoFTR so that the fine (sub-pixel) offsets of the matched keypoints in the
RENDERED image are a soft-argmax over a correlation window, and hence carry gradients back to the
rendered image and from there to the camera pose. `refine_render_keypoints` gives any matcher
that property with a fine step of our own:

1. For every match, a grayscale patch of the query around its keypoint is compared with patches of
   the render around candidate positions (normalised cross-correlation, Gaussian-weighted patch,
   bilinear `grid_sample`, integer pixel centres).
2. An integer search over `(2 window + 1)^2` candidates recentres the keypoint (no gradient).
3. A soft-argmax step (softmax of NCC / temperature over a `(2 radius + 1)^2` window, LoFTR-fine
   style) gives a sub-pixel displacement `F(c)`. Newton iterations (J = dF/dc in closed form) find
   its fixed point `F(c*) = 0` (no gradient).
4. The returned position `c* - J^-1 F(c*, render)`, with `J = dF/dc` detached, has the value `c*`
   (plus a last Newton step) and the gradient of the implicit function theorem:
   `d c*/d render = -J^-1 dF/d render`. So a render translated by `delta` moves the keypoint by
   exactly `delta` to first order (a plain one-step soft-argmax, as in LoFTR, would move it by a
   damped fraction of `delta`). With `implicit=False` the last step is the plain soft-argmax step.

Symmetric comparison: candidate displacement `d` compares the render at `c + d/2 + o` with the
query at `p - d/2 + o` (o: patch offsets). Under a pure translation this score is exactly symmetric
in `d` around the true displacement, so the fixed point of the soft-argmax is unbiased (a one-sided
window is biased toward the integer peak).

Pixel convention: (x, y), integer pixel centres (3DGS), see docs/CONTRACTS.md.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional, Tuple, Union

import torch
import torch.nn.functional as F
from ..checks import check_bool, check_int, check_real

_GRAY = (0.299, 0.587, 0.114)
_MODE = "bilinear"


def _to_gray(image: torch.Tensor, blur: float = 0.0) -> torch.Tensor:
    """[C, H, W] -> [1, 1, H, W] grayscale, optionally Gaussian-blurred (sigma `blur` px)."""
    if image.shape[0] == 1:
        g = image
    else:
        w = image.new_tensor(_GRAY).view(3, 1, 1)
        g = (image * w).sum(0, keepdim=True)
    g = g.unsqueeze(0)
    if blur > 0:  # separable, as shifted sums (a third of the time of two 1-channel convolutions)
        r = max(1, int(math.ceil(3 * blur)))
        x = torch.arange(-r, r + 1, dtype=torch.float64)
        k = torch.exp(-x * x / (2 * blur * blur))
        k = (k / k.sum()).tolist()
        h, w = g.shape[-2:]
        p = F.pad(g, (r, r, r, r), mode="replicate")[0, 0]
        rows = p.new_zeros((h + 2 * r, w))
        for i, ki in enumerate(k):
            rows = rows.add_(p[:, i:i + w], alpha=ki)
        out = p.new_zeros((h, w))
        for i, ki in enumerate(k):
            out = out.add_(rows[i:i + h], alpha=ki)
        g = out[None, None]
    return g


def _offset_grid(radius: int, device, dtype) -> torch.Tensor:
    """[(2r+1)^2, 2] integer (x, y) offsets, row-major."""
    r = torch.arange(-radius, radius + 1, device=device, dtype=dtype)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def _pixel_scale(gray: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(sx, sy) with grid_sample's coordinate = pixel position * s - 1 (align_corners)."""
    h, w = gray.shape[-2:]
    return like.new_tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)])


def _grid_sample(gray: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of gray [1,1,H,W] at grid_sample coordinates grid [N, K, 2] -> [N, K]."""
    return F.grid_sample(gray, grid.to(gray.dtype).unsqueeze(0), mode=_MODE,
                         padding_mode="border", align_corners=True)[0, 0]


def _sample(gray: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of gray [1,1,H,W] at pixel positions pos [N, K, 2] -> [N, K]."""
    return _grid_sample(gray, pos * _pixel_scale(gray, pos) - 1.0)


def _grid_radius(grid: torch.Tensor) -> int:
    """r of an ``_offset_grid(r)`` ((2r+1)^2 rows)."""
    return (math.isqrt(grid.shape[0]) - 1) // 2


def _half_grid_patches(gray, centre, radius, patch, sign, grad=False):
    """Samples of gray [1,1,H,W] at ``centre + sign d / 2 + o``: [N, D, O].

    For every displacement d of ``_offset_grid(radius)`` and offset o of ``_offset_grid(patch)``.
    All those positions lie on one half-pixel grid around each centre, ``centre + j / 2`` for
    ``|j| <= radius + 2 patch``: it is sampled once (half the samples of sampling each patch
    apart) and the patches are strided views of it. With ``grad`` also the samples' derivatives
    by x and by y of their positions, [N, D, O] each (from the image as a constant).
    """
    n = centre.shape[0]
    half = radius + 2 * patch
    g = 2 * half + 1
    scale = _pixel_scale(gray, centre)
    j = torch.arange(-half, half + 1, device=centre.device, dtype=centre.dtype) * 0.5
    # in grid_sample's units, by the same operations as sampling position by position: the
    # positions of integer keypoints are integers, where the side of a bilinear derivative
    # depends on the last bit (per axis on [N, G], then spread over the grid)
    x = ((centre[:, 0:1] + j) * scale[0] - 1.0).view(n, 1, g).expand(n, g, g)
    y = ((centre[:, 1:2] + j) * scale[1] - 1.0).view(n, g, 1).expand(n, g, g)
    grid = torch.stack([x, y], -1).view(n, g * g, 2).to(gray.dtype)
    k, m = 2 * radius + 1, 2 * patch + 1

    def patches(t):  # [N, G*G] -> [N, D, O]
        t = t.reshape(n, g, g)
        if t.requires_grad:  # a gather, whose backward accumulates the overlapping patches
            line = (sign * torch.arange(-radius, radius + 1, device=t.device).view(-1, 1)
                    + 2 * torch.arange(-patch, patch + 1, device=t.device).view(1, -1) + half)
            return t[:, line.view(k, 1, m, 1), line.view(1, k, 1, m)].reshape(n, k * k, m * m)
        st = t.stride()  # patch d starts at j = sign d - 2 patch, its samples 2 apart
        v = t.as_strided((n, k, k, m, m), (st[0], st[1], st[2], 2 * st[1], 2 * st[2]),
                         t.storage_offset())
        if sign < 0:  # the first patch in memory is that of d = +radius: one copy, reversed
            return torch.stack([v[:, k - 1 - i // k, k - 1 - i % k] for i in range(k * k)],
                               1).reshape(n, k * k, m * m)
        return v.reshape(n, k * k, m * m)

    if not grad:
        return patches(_grid_sample(gray, grid))
    leaf = grid.detach().requires_grad_(True)
    with torch.enable_grad():
        s = _grid_sample(gray.detach(), leaf)
        deriv = torch.autograd.grad(s.sum(), leaf)[0]
    s = _grid_sample(gray, grid.detach()) if gray.requires_grad else s.detach()
    # by pixel position: d/dx = d/dgrid_x * scale_x
    return patches(s), patches(deriv[..., 0] * scale[0]), patches(deriv[..., 1] * scale[1])


class _QueryPatches(NamedTuple):
    """The query's side of ``_ncc_scores``, the same at every step of one refinement.

    ``centred``: the patches at ``p - d/2 + o`` less their weighted means [N, D, O]; ``var``:
    their weighted variances [N, D] (made once per call instead of once per step).
    """

    centred: torch.Tensor
    var: torch.Tensor


def _query_patches(query_g, kpts_query, disp, offs, weights) -> _QueryPatches:
    """``_QueryPatches`` of query_g [1,1,H,W] at kpts_query [N, 2] (``_ncc_scores``' grids)."""
    b = _half_grid_patches(query_g, kpts_query, _grid_radius(disp), _grid_radius(offs), -1)
    b = b - (b @ weights).unsqueeze(-1)
    return _QueryPatches(b, (b * b) @ weights)


def _ncc_scores(render_g, query: _QueryPatches, centre, disp, offs, weights, eps,
                grad_centre: bool = False):
    """NCC of render at centre + d/2 + o against query at p - d/2 + o.

    centre: [N, 2]; ``query``: ``_query_patches`` at the query keypoints p; disp, offs:
    ``_offset_grid`` of the soft window's and the patch's radius; weights: [O] (sum 1) -> [N, D];
    with ``grad_centre`` also dNCC/dcentre [N, D, 2] (detached): the NCC's derivative by its
    samples (closed form) times the samples' by their positions (one backward pass of the
    bilinear sampling alone, instead of two through the whole step).
    """
    radius, patch = _grid_radius(disp), _grid_radius(offs)
    out = _half_grid_patches(render_g, centre, radius, patch, 1, grad_centre)
    a = out[0] if grad_centre else out
    b, var_b = query
    # weighted moments as matrix-vector products over the patch
    a = a - (a @ weights).unsqueeze(-1)
    cov = (a * b) @ weights
    var_a = (a * a) @ weights
    den = torch.sqrt(var_a * var_b + eps)
    s = cov / den
    if not grad_centre:
        return s
    with torch.no_grad():  # d s / d a_o = w_o (b_o - cov var_b a_o / den^2) / den (centred a, b)
        a, cov = a.detach(), cov.detach()
        den = den.detach()
        q = b - (cov * var_b / (den * den)).unsqueeze(-1) * a
        ds_dc = torch.stack([(q * out[1]) @ weights, (q * out[2]) @ weights], -1)
        ds_dc = ds_dc / den.unsqueeze(-1)
    return s, ds_dc


def _integer_search(render_g, query_g, centre, kpts_query, window, patch, offs, weights, eps,
                    margins: Optional[list] = None):
    """Best integer displacement by NCC: the new centres [N, 2].

    Render patches at round(centre) + d + o are compared with the query patch at
    kpts_query + o, for d in [-window, window]^2. ``margins``: a list to which the peak's margin
    [N] is appended (`peak_margin`).
    """
    n = centre.shape[0]
    h, w = render_g.shape[-2:]
    base = torch.round(centre)
    # query patches, normalised to zero weighted mean and unit weighted variance
    b = _sample(query_g, kpts_query.view(n, 1, 2) + offs.view(1, -1, 2))  # [N, O]
    b = b - (b * weights).sum(-1, keepdim=True)
    b = b / torch.sqrt((b * b * weights).sum(-1, keepdim=True) + eps)
    kern = (b * weights).view(n, 1, 2 * patch + 1, 2 * patch + 1)
    # render windows (integer pixels, clamped at the border)
    r = window + patch
    u = torch.arange(-r, r + 1, device=centre.device)
    xs = (base[:, 0:1].long() + u.view(1, -1)).clamp(0, w - 1)  # [N, S]
    ys = (base[:, 1:2].long() + u.view(1, -1)).clamp(0, h - 1)
    img = render_g[0, 0]
    win = img[ys.view(n, -1, 1), xs.view(n, 1, -1)].unsqueeze(0)  # [1, N, S, S]
    wk = weights.view(1, 1, 2 * patch + 1, 2 * patch + 1).expand(n, 1, -1, -1)
    corr = F.conv2d(win, kern, groups=n)[0]  # [N, 2w+1, 2w+1]
    mean = F.conv2d(win, wk, groups=n)[0]
    sq = F.conv2d(win * win, wk, groups=n)[0]
    var = (sq - mean * mean).clamp_min(0.0)
    ncc = (corr / torch.sqrt(var + eps)).reshape(n, -1)
    disp = _offset_grid(window, centre.device, centre.dtype)
    # ties (flat, texture-less windows) go to the smallest displacement
    ncc = ncc - 1e-6 * (disp * disp).sum(-1)
    best = ncc.argmax(dim=-1)
    d = disp[best]
    if margins is not None:
        margins.append(peak_margin(ncc, disp, best))
    return centre + d


def peak_margin(ncc: torch.Tensor, disp: torch.Tensor, best: torch.Tensor) -> torch.Tensor:
    """How far each NCC peak stands above the rest of its window: [N].

    The best score less the best one at least 2 pixels (Chebyshev) from the peak; +inf where the
    window has no such position. Near 0 where the surface is flat (a soft, texture-less or
    repeating patch: the peak's position is not determined by the image).
    """
    far = (disp.view(1, -1, 2) - disp[best].view(-1, 1, 2)).abs().amax(-1) >= 2  # [N, D]
    rival = torch.where(far, ncc, torch.full_like(ncc, -math.inf)).amax(-1)
    return ncc.gather(1, best.view(-1, 1)).view(-1) - rival


def _soft_step(render_g, query: _QueryPatches, centre, disp, offs, weights, eps, temperature,
               jacobian: bool = False):
    """Soft-argmax displacement F(centre) [N, 2] and the NCC at d = 0 [N].

    With ``jacobian`` also J = dF/dcentre [N, 2, 2] (``J[n, i, j] = dF_i / dc_j``, detached):
    with p = softmax(s / T), dF/dc = sum_d p_d (d - F) (ds_d/dc)^T / T.
    """
    out = _ncc_scores(render_g, query, centre, disp, offs, weights, eps, jacobian)
    s, ds_dc = out if jacobian else (out, None)
    prob = torch.softmax(s / temperature, dim=-1)
    step = prob @ disp
    centre_score = s[:, disp.shape[0] // 2]
    if not jacobian:
        return step, centre_score
    with torch.no_grad():
        spread = disp.unsqueeze(0) - step.detach().unsqueeze(1)  # [N, D, 2]
        jac = torch.einsum("nd,ndi,ndj->nij", prob.detach(), spread, ds_dc) / temperature
    return step, centre_score, jac


def _step(render_g, query: _QueryPatches, centre, disp, offs, weights, eps, temperature, implicit,
          radius):
    """One refinement step from `centre` (detached): (delta [N, 2], NCC at centre [N]).

    Plain: delta = F(c), the soft-argmax displacement. Implicit: delta = -J^-1 F(c) with
    J = dF/dc detached (a Newton step on F(c) = 0), where M = -J is well conditioned (about g I with
    0 < g <= 1 under a translation) and the Newton step agrees in direction with the plain step;
    elsewhere (texture-less or edge-like patches) the plain step.
    The value of delta is clamped to the soft window; its gradient w.r.t. the render is kept.
    """
    n = centre.shape[0]
    c = centre.detach()
    if not implicit:
        delta, score = _soft_step(render_g, query, c, disp, offs, weights, eps, temperature)
    else:
        step, score, jac = _soft_step(render_g, query, c, disp, offs, weights, eps, temperature,
                                      jacobian=True)
        m = -jac  # [N, 2, 2] = -dF/dc
        # 2x2 in closed form: the smallest singular value |det| / s_max, and the inverse
        det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
        fro2 = (m * m).sum((1, 2))
        s_max = torch.sqrt(0.5 * (fro2 + torch.sqrt((fro2 * fro2 - 4 * det * det).clamp_min(0))))
        good = det.abs() > 0.05 * s_max
        eye = torch.eye(2, device=c.device, dtype=c.dtype).expand(n, 2, 2)
        adj = torch.stack([m[:, 1, 1], -m[:, 0, 1], -m[:, 1, 0], m[:, 0, 0]], -1).view(n, 2, 2)
        inv = adj / torch.where(good, det, torch.ones_like(det)).view(n, 1, 1)
        a_mat = torch.where(good.view(n, 1, 1), inv, eye)
        newton = (a_mat @ step.detach().unsqueeze(-1)).squeeze(-1)
        # a Newton step against the soft-argmax step would leave the basin: plain step there
        good = good & ((newton * step.detach()).sum(-1) > 0)
        a_mat = torch.where(good.view(n, 1, 1), a_mat, eye)
        delta = (a_mat @ step.unsqueeze(-1)).squeeze(-1)
    limit = float(radius)
    delta = delta + (delta.detach().clamp(-limit, limit) - delta.detach())
    return delta, score.detach()


def _check_tensor(value, name: str, shape_desc: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor {shape_desc}, got {type(value).__name__}")
    if not value.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {value.dtype}")
    return value


def _check_int(value, name: str, lo: int) -> int:
    return check_int(value, name, lo)


def refine_render_keypoints(
    render: torch.Tensor,
    query: torch.Tensor,
    kpts_render: torch.Tensor,
    kpts_query: torch.Tensor,
    window: int = 4,
    patch: int = 5,
    temperature: float = 0.05,
    radius: int = 1,
    iterations: int = 4,
    implicit: bool = True,
    blur: float = 1.0,
    return_score: bool = False,
    chunk: int = 512,
    return_margin: bool = False,
) -> Union[torch.Tensor, Tuple[torch.Tensor, ...]]:
    """Sub-pixel positions in `render` of the query keypoints, differentiable w.r.t. `render`.

    Args:
        render: [C, H, W] (C = 3 RGB or 1 gray) rendered image; may require grad.
        query: [C, H', W'] query image (treated as a constant).
        kpts_render: [N, 2] initial (x, y) positions in the render (e.g. a matcher's kpts0).
        kpts_query: [N, 2] (x, y) keypoints in the query (kept fixed).
        window: integer search radius in pixels around `kpts_render` ((2w+1)^2 candidates); 0
            skips the search.
        patch: patch radius in pixels ((2p+1)^2 samples, Gaussian weight of sigma (p+1)/2).
        temperature: softmax temperature of the NCC scores (NCC lies in [-1, 1]).
        radius: radius of the soft-argmax window (3x3 for 1).
        iterations: Newton iterations on the soft-argmax fixed point before the final step.
        implicit: gradient of the last step by the implicit function theorem (a render translated
            by delta moves the keypoint by delta, to first order); False: the plain LoFTR-style
            soft-argmax gradient (damped, about 0.5 to 0.7 of that). The value is the same.
        blur: sigma in pixels of a Gaussian pre-blur of both grayscale images (reduces the bias of
            bilinear sampling at sub-pixel positions and widens the basin); 0 disables it.
        return_score: also return the NCC at the refined position [N] (detached), a quality
            measure (near 1 for a good match, near 0 on texture-less patches).
        chunk: matches processed at once by the integer search (memory bound).
        return_margin: also return the integer search's `peak_margin` [N] (detached; +inf
            without a search), after the score when that is returned too.

    Returns:
        kpts_render_refined [N, 2] in the render's dtype (then the score [N] if `return_score`,
        then the margin [N] if `return_margin`).
    """
    _check_tensor(render, "render", "[C, H, W]")
    _check_tensor(query, "query", "[C, H, W]")
    for name, img in (("render", render), ("query", query)):
        if img.ndim != 3 or img.shape[0] not in (1, 3):
            raise ValueError(
                f"{name} must have shape [3, H, W] or [1, H, W], got {tuple(img.shape)}"
            )
    _check_tensor(kpts_render, "kpts_render", "[N, 2]")
    _check_tensor(kpts_query, "kpts_query", "[N, 2]")
    for name, k in (("kpts_render", kpts_render), ("kpts_query", kpts_query)):
        if k.ndim != 2 or k.shape[1] != 2:
            raise ValueError(f"{name} must have shape [N, 2], got {tuple(k.shape)}")
    if kpts_render.shape[0] != kpts_query.shape[0]:
        raise ValueError(f"kpts_render and kpts_query must have the same length, got "
                         f"{kpts_render.shape[0]} and {kpts_query.shape[0]}")
    _check_int(window, "window", 0)
    _check_int(patch, "patch", 1)
    _check_int(radius, "radius", 1)
    _check_int(iterations, "iterations", 0)
    _check_int(chunk, "chunk", 1)
    check_real(temperature, "temperature", 0.0, lo_open=True)
    check_real(blur, "blur", 0.0)
    check_bool(implicit, "implicit")

    device = render.device
    dtype = render.dtype if render.dtype in (torch.float32, torch.float64) else torch.float32
    n = kpts_render.shape[0]
    if n == 0:
        out = kpts_render.detach().to(device, dtype).clone()
        extra = (out.new_zeros((0,)),) * (int(return_score) + int(return_margin))
        return (out, *extra) if extra else out

    render_g = _to_gray(render.to(dtype), blur)
    query_g = _to_gray(query.detach().to(device, dtype), blur)
    kq = kpts_query.detach().to(device, dtype)
    centre = kpts_render.detach().to(device, dtype).clone()
    offs = _offset_grid(patch, device, dtype)
    sigma = (patch + 1) / 2.0
    weights = torch.exp(-(offs * offs).sum(-1) / (2 * sigma * sigma))
    weights = weights / weights.sum()
    eps = 1e-8
    soft_disp = _offset_grid(radius, device, dtype)

    with torch.no_grad():
        rg = render_g.detach()
        # 1. integer search (render window at integer pixels, NCC by grouped convolutions)
        margins: list = []
        if window > 0:
            for s in range(0, n, chunk):
                sl = slice(s, min(n, s + chunk))
                centre[sl] = _integer_search(rg, query_g, centre[sl], kq[sl], window, patch, offs,
                                             weights, eps, margins)
        # 2. fixed-point iterations of the soft-argmax step (Newton steps where well conditioned)
        query_p = _query_patches(query_g, kq, soft_disp, offs, weights)
        for _ in range(iterations):
            delta, _ = _step(rg, query_p, centre, soft_disp, offs, weights, eps, temperature,
                             True, radius)
            centre = centre + delta.detach()

    # 3. final step, with the gradient w.r.t. the render
    delta, score = _step(render_g, query_p, centre, soft_disp, offs, weights, eps, temperature,
                         implicit, radius)
    refined = centre + delta
    if not (render.requires_grad and torch.is_grad_enabled()):
        refined = refined.detach()
    out = (refined,)
    if return_score:
        out += (score.detach(),)
    if return_margin:
        out += (torch.cat(margins) if margins else torch.full((n,), math.inf, dtype=dtype,
                                                               device=device),)
    return out if len(out) > 1 else refined
