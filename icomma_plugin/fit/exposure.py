"""Per-photo exposure: an affine colour transform per training photo (upstream `--train_test_exp`).

Upstream 3DGS (2024) optimises, for every training image, a 3x4 matrix `E = [A | b]` applied to
the render before the loss: `render'(c) = sum_k A[c, k] render(k) + b[c]`, initialised to the
identity, Adam with a learning rate decaying log-linearly from 1e-2 to 1e-3 over the run. The
scene is then free of each photo's exposure and white balance; the exposures are written beside
the model (`exposure.json`, {image name: 3x4 list}, as upstream) and never applied to renders at
localization time, so the model folder stays upstream-compatible.

Here the loss gradient with respect to the render is computed in closed form (no autograd
graph), so `ExposureState.backward` takes d loss / d render' and returns d loss / d render,
accumulating d loss / d E:
    d render = A^T d render',  d A = sum_pixels d render' render^T,  d b = sum_pixels d render'.
After each step the exposures are recentred (mean A = I, mean b = 0 over the photos): the
scene's own colours are those of the average photo, which is what a localization render
compares with.

Held-out photos have no exposure of their own: `fit_affine_colour` fits one by least squares on
a region (upstream fits it on the left half of each test image and measures on the right half),
and `NeighbourExposure` predicts one from the training photos taken nearest to it, without
looking at the photo.
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np
import torch

from ..checks import check_bool, check_int
from ..pose.convert import as_rigid, invert_rigid
from ..pose.views import camera_nearness
from .state import expon_lr


class ExposureState:
    """One affine colour transform [3, 4] per training photo, with its own Adam.

    ``sparse``: Adam steps only the photos seen since the last step, each with its own step
    count (as ``torch.optim.SparseAdam``): a photo's transform moves about one learning rate a
    visit. Upstream's dense Adam (False) also moves every photo between its visits, on the
    momentum of its last gradient, some 6-12 learning rates a visit in all.
    """

    def __init__(self, num_views: int, lr_init: float = 1e-2, lr_final: float = 1e-3,
                 max_steps: int = 30_000, dtype: torch.dtype = torch.float32,
                 device: Optional[torch.device] = None, sparse: bool = False):
        if isinstance(num_views, bool) or not isinstance(num_views, int) or num_views < 1:
            raise ValueError(f"num_views must be a positive int, got {num_views!r}")
        if not (lr_init > 0 and lr_final > 0):
            raise ValueError(f"lr_init and lr_final must be > 0, got {lr_init!r}, {lr_final!r}")
        check_bool(sparse, "sparse")
        eye = torch.eye(3, 4, dtype=dtype, device=device)
        self.params = torch.nn.Parameter(eye.repeat(num_views, 1, 1).contiguous())
        self.lr_init, self.lr_final, self.max_steps = float(lr_init), float(lr_final), max_steps
        self.sparse = sparse
        self.optimizer = torch.optim.Adam([self.params], lr=self.lr_init, eps=1e-15)
        self._seen = torch.zeros(num_views, dtype=torch.bool)  # since the last step
        if sparse:  # the per-photo moments and step counts
            self._m = torch.zeros_like(self.params.detach())
            self._v = torch.zeros_like(self.params.detach())
            self._t = torch.zeros(num_views, dtype=torch.int64)

    @property
    def num_views(self) -> int:
        """The number of photos."""
        return int(self.params.shape[0])

    def matrix(self, index: int) -> torch.Tensor:
        """The [3, 4] transform of photo `index` (detached)."""
        return self.params.detach()[index]

    @torch.no_grad()
    def apply(self, index: int, image: torch.Tensor) -> torch.Tensor:
        """`image` [3, H, W] through photo `index`'s transform."""
        return apply_affine_colour(self.params.detach()[index], image)

    @torch.no_grad()
    def backward(self, index: int, image: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
        """d loss / d image from d loss / d (transformed image); accumulates d loss / d E."""
        E = self.params.detach()[index]
        A = E[:, :3]
        g = grad_out.reshape(3, -1)
        x = image.reshape(3, -1)
        grad = torch.zeros_like(self.params) if self.params.grad is None else self.params.grad
        grad[index, :, :3] += g @ x.T
        grad[index, :, 3] += g.sum(dim=1)
        self.params.grad = grad
        self._seen[index] = True
        return (A.T @ g).reshape(image.shape)

    @torch.no_grad()
    def step(self, iteration: int) -> None:
        """One Adam step at `iteration`'s learning rate, then recentre; clears the gradient."""
        if self.params.grad is None:
            return
        lr = expon_lr(iteration, self.lr_init, self.lr_final, self.max_steps)
        if self.sparse:
            self._sparse_step(lr)
            self.params.grad = None
        else:
            for group in self.optimizer.param_groups:
                group["lr"] = lr
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
            self._seen[:] = False
        self.recentre()

    def _sparse_step(self, lr: float, betas=(0.9, 0.999), eps: float = 1e-15) -> None:
        """Adam on the rows seen since the last step, each on its own step count."""
        rows = torch.nonzero(self._seen).flatten()
        self._seen[rows] = False
        g = self.params.grad[rows]
        self._t[rows] += 1
        t = self._t[rows].to(g.dtype).view(-1, 1, 1)
        m = self._m[rows].mul_(betas[0]).add_(g, alpha=1 - betas[0])
        v = self._v[rows].mul_(betas[1]).addcmul_(g, g, value=1 - betas[1])
        self._m[rows], self._v[rows] = m, v
        m_hat = m / (1 - betas[0] ** t)
        v_hat = v / (1 - betas[1] ** t)
        self.params.data[rows] -= lr * m_hat / (v_hat.sqrt() + eps)

    @torch.no_grad()
    def recentre(self) -> None:
        """Mean transform over the photos := identity (fixes the scene-vs-exposure gauge)."""
        eye = torch.eye(3, 4, dtype=self.params.dtype, device=self.params.device)
        self.params -= self.params.mean(dim=0, keepdim=True) - eye

    def to_json(self, names: Sequence[str]) -> Dict[str, list]:
        """{image name: 3x4 nested list}, upstream's exposure.json."""
        if len(names) != self.num_views:
            raise ValueError(f"names must hold {self.num_views} image names, got {len(names)}")
        E = self.params.detach().cpu().double()
        return {str(n): E[i].tolist() for i, n in enumerate(names)}


NEIGHBOUR_EXPOSURE_K = 3  # training photos averaged (docs/FITTING.md, "A new view's exposure")


class NeighbourExposure:
    """A new view's exposure, predicted from the training photos taken nearest to it.

    A camera's automatic exposure and white balance follow what is in view, so photos taken from
    nearby cameras looking the same way were exposed alike. The prediction for a camera is the
    mean of the ``k`` nearest training photos' transforms (nearest by
    `pose.views.camera_nearness`, the localizer's measure for its source photos), weighted by
    inverse nearness. A mean of affine transforms needs no normalising.

    Args:
        w2cs: the training photos' world-to-camera matrices [4, 4].
        matrices: their [3, 4] transforms, in the same order.
        k: how many nearest photos are averaged (at most all of them).
    """

    def __init__(self, w2cs: Sequence, matrices: Sequence[torch.Tensor],
                 k: int = NEIGHBOUR_EXPOSURE_K):
        check_int(k, "k", 1)
        if len(w2cs) != len(matrices) or len(w2cs) == 0:
            raise ValueError(f"w2cs and matrices must be non-empty and of one length, got "
                             f"{len(w2cs)} and {len(matrices)}")
        self.c2ws = np.stack([invert_rigid(as_rigid(m, f"w2cs[{i}]")) for i, m in enumerate(w2cs)])
        self.matrices = torch.stack([torch.as_tensor(E).detach().cpu().double() for E in matrices])
        if tuple(self.matrices.shape[1:]) != (3, 4):
            raise ValueError(f"matrices must be [3, 4] each, got {list(self.matrices.shape[1:])}")
        self.k = min(int(k), len(w2cs))

    def __call__(self, w2c) -> torch.Tensor:
        """The predicted [3, 4] transform (float64) for a camera ``w2c`` [4, 4]."""
        score, _ = camera_nearness(self.c2ws, invert_rigid(as_rigid(w2c, "w2c")))
        near = np.argsort(score, kind="stable")[: self.k]
        w = 1.0 / (score[near] + 1e-9)
        w = torch.as_tensor(w / w.sum(), dtype=torch.float64)
        return (self.matrices[torch.as_tensor(near)] * w.view(-1, 1, 1)).sum(0)


def apply_affine_colour(E: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """`A image + b` per pixel for E = [A | b] [3, 4] and image [3, H, W]."""
    return (E[:, :3] @ image.reshape(3, -1) + E[:, 3:]).reshape(image.shape)


@torch.no_grad()
def fit_affine_colour(render: torch.Tensor, photo: torch.Tensor,
                      mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Least-squares E = [A | b] [3, 4] with A render + b ~ photo over the pixels of `mask`.

    Args:
        render: [3, H, W] rendered image.
        photo: [3, H, W] photo.
        mask: [1, H, W] in {0, 1} (1 = use the pixel) or None (every pixel).

    Returns:
        [3, 4] float64 transform (the identity when fewer than 16 pixels are usable).
    """
    if render.shape != photo.shape or render.ndim != 3 or render.shape[0] != 3:
        raise ValueError(f"render and photo must both be [3, H, W], got {list(render.shape)} and "
                         f"{list(photo.shape)}")
    X = render.reshape(3, -1).double()
    Y = photo.reshape(3, -1).double()
    if mask is not None:
        keep = mask.reshape(-1) > 0.5
        X, Y = X[:, keep], Y[:, keep]
    f64 = dict(dtype=torch.float64, device=X.device)
    if X.shape[1] < 16:
        return torch.eye(3, 4, **f64)
    Xh = torch.cat([X, torch.ones_like(X[:1])], dim=0)  # [4, N]
    # ridge towards the identity keeps a flat region from giving a degenerate matrix
    lam = 1e-4 * X.shape[1]
    eye = torch.eye(3, 4, **f64)
    lhs = Xh @ Xh.T + lam * torch.eye(4, **f64)
    rhs = Xh @ Y.T + lam * eye.T
    return torch.linalg.solve(lhs, rhs).T
