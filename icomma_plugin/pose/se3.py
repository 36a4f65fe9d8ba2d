"""Functional SO(3) / SE(3) maths (batched, float32/float64, any device, autograd-safe).

Conventions (stated once here; see docs/CONTRACTS.md):

- Matrices act on column vectors: ``x' = T @ [x, 1]``.
- A twist is ``xi = (rho, phi)`` of shape ``[..., 6]``: translation part ``rho`` first, rotation
  part ``phi`` (axis-angle, radians) second, as in pytorch3d ``se3_exp_map`` and kornia ``Se3``.
- ``se3_exp(xi) = [[R, V rho], [0, 1]]`` with ``R = so3_exp(phi)`` and
  ``V = so3_left_jacobian(phi)``.
- The localizer's pose update is the LEFT perturbation of world-to-camera,
  ``w2c_t = se3_exp(xi) @ w2c_0``: ``xi`` is an increment expressed in the camera frame, so its
  rotation turns the camera about its own centre.

Every closed form with a removable singularity at ``theta = 0`` (``sin t / t``,
``(1 - cos t) / t^2``, ...) switches to its Taylor series below a threshold via ``torch.where``; the
closed-form branch is fed a "safe" angle there, so neither the value nor the gradient is ever NaN
(``torch.where`` back-propagates ``0 * grad`` into the unused branch, which must stay finite).
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "hat",
    "vee",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "se3_exp",
    "se3_log",
]

# Below theta^2 < _SMALL the Taylor branch is used. Truncation error of the series below is
# < theta^8 / 9! ~ 3e-18 there, and the closed forms are still well conditioned above it.
_SMALL = 1e-3


def _check_last(x: torch.Tensor, name: str, shape: tuple) -> None:
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
    if tuple(x.shape[x.ndim - len(shape):]) != shape or x.ndim < len(shape):
        dims = ", ".join(str(s) for s in shape)
        raise ValueError(f"{name} must have shape [..., {dims}], got {list(x.shape)}")


def hat(v: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix of a 3-vector: ``hat(v) @ w == cross(v, w)``.

    Args:
        v: ``[..., 3]``.

    Returns:
        ``[..., 3, 3]``, same dtype/device.

    Raises:
        ValueError: if ``v`` is not a float tensor of shape ``[..., 3]``.
    """
    _check_last(v, "v", (3,))
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def vee(M: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat`: ``[..., 3, 3] -> [..., 3]``.

    Uses the antisymmetric part ``(M - M^T) / 2``, so ``vee(hat(v)) == v`` exactly and a
    non-skew input is projected rather than silently read from one triangle.
    """
    _check_last(M, "M", (3, 3))
    return 0.5 * torch.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]],
        dim=-1,
    )


def _series(x):
    """(A, B, C) by their Taylor series in ``x = theta^2`` (tensors or floats alike)."""
    return (1.0 - x / 6.0 * (1.0 - x / 20.0 * (1.0 - x / 42.0)),
            0.5 - x / 24.0 * (1.0 - x / 30.0 * (1.0 - x / 56.0)),
            1.0 / 6.0 - x / 120.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0)))


def _closed(t2, t, s, half):
    """(A, B, C) in closed form from ``t^2, t, sin t, sin(t/2)`` (tensors or floats alike)."""
    # B = (1 - cos t)/t^2 as 2 sin^2(t/2)/t^2, without the cancellation of 1 - cos t
    return s / t, 2.0 * half * half / t2, (t - s) / (t2 * t)


def _coeffs(theta2: torch.Tensor):
    """(A, B, C) = (sin t/t, (1-cos t)/t^2, (t - sin t)/t^3) of t = sqrt(theta2), NaN-free at 0."""
    small = theta2 < _SMALL
    # theta -> 0: feed the closed form a dummy angle so its (discarded) gradient stays finite.
    t2s = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2s)
    A_cf, B_cf, C_cf = _closed(t2s, t, torch.sin(t), torch.sin(0.5 * t))
    A_ts, B_ts, C_ts = _series(theta2)
    return (
        torch.where(small, A_ts, A_cf),
        torch.where(small, B_ts, B_cf),
        torch.where(small, C_ts, C_cf),
    )


def _eye(like: torch.Tensor) -> torch.Tensor:
    return torch.eye(3, dtype=like.dtype, device=like.device).expand(*like.shape[:-1], 3, 3)


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle ``phi`` (radians) -> rotation matrix.

    Args:
        phi: ``[..., 3]`` float tensor.

    Returns:
        ``R [..., 3, 3]`` = ``I + A K + B K^2`` with ``K = hat(phi)``; exact at 0, smooth
        everywhere.
    """
    _check_last(phi, "phi", (3,))
    A, B, _ = _coeffs((phi * phi).sum(-1))
    K = hat(phi)
    return _eye(phi) + A[..., None, None] * K + B[..., None, None] * (K @ K)


def so3_left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian of SO(3), ``V = I + B K + C K^2`` (the ``V`` in ``t = V rho`` of se3_exp).

    Args:
        phi: ``[..., 3]``.

    Returns:
        ``[..., 3, 3]``.
    """
    _check_last(phi, "phi", (3,))
    _, B, C = _coeffs((phi * phi).sum(-1))
    K = hat(phi)
    return _eye(phi) + B[..., None, None] * K + C[..., None, None] * (K @ K)


def so3_left_jacobian_inv(phi: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`so3_left_jacobian`: ``I - K/2 + D K^2``, valid for ``|phi| < 2 pi``.

    ``D = (1 - (t/2) cot(t/2)) / t^2``; written with ``cot(t/2)`` it stays finite at ``t = pi``.
    """
    _check_last(phi, "phi", (3,))
    theta2 = (phi * phi).sum(-1)
    small = theta2 < _SMALL
    t2s = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2s)
    h = 0.5 * t
    D_cf = (1.0 - h * torch.cos(h) / torch.sin(h)) / t2s
    x = theta2
    D_ts = 1.0 / 12.0 + x / 720.0 + x * x / 30240.0 + x * x * x / 1209600.0
    D = torch.where(small, D_ts, D_cf)
    K = hat(phi)
    return _eye(phi) - 0.5 * K + D[..., None, None] * (K @ K)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix -> axis-angle ``phi`` with ``|phi| <= pi``.

    Three branches, chosen per element with ``torch.where``:

    - near identity (``sin^2 t < 1e-4``, ``cos t > 0``): ``phi = s * asin(|s|)/|s|`` by its
      series in ``|s|^2``, where ``s = vee(R)`` = ``sin(t) * axis`` (smooth, exact at ``R = I``);
    - generic: ``t = atan2(|s|, cos t)``, ``phi = s * t / |s|``;
    - near pi (``cos t < -0.7``): the axis is read from the symmetric part
      ``(R + R^T)/2 - cos(t) I = (1 - cos t) a a^T`` (well conditioned there, unlike ``s``), its
      sign from ``s``. At exactly ``t = pi`` either sign is a valid logarithm.

    Args:
        R: ``[..., 3, 3]`` rotation matrices (not re-orthonormalised).

    Returns:
        ``[..., 3]`` axis-angle, same dtype/device.
    """
    _check_last(R, "R", (3, 3))
    s = vee(R)  # [..., 3] = sin(t) * axis
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    c = ((tr - 1.0) * 0.5).clamp(-1.0, 1.0)
    s2 = (s * s).sum(-1)
    tiny = torch.finfo(R.dtype).tiny

    near_zero = (s2 < 1e-4) & (c > 0)
    near_pi = c < -0.7
    generic = ~(near_zero | near_pi)

    # Generic branch.
    s2g = torch.where(generic, s2, torch.ones_like(s2))
    sng = torch.sqrt(s2g)
    phi_gen = s * (torch.atan2(sng, c) / sng)[..., None]

    # Near identity: asin(x)/x = 1 + x^2/6 + 3x^4/40 + 5x^6/112 + ...
    x = torch.where(near_zero, s2, torch.zeros_like(s2))
    phi_zero = s * (1.0 + x / 6.0 + 3.0 * x * x / 40.0 + 5.0 * x * x * x / 112.0)[..., None]

    # Near pi.
    cp = torch.where(near_pi, c, torch.full_like(c, -1.0))
    S = 0.5 * (R + R.transpose(-1, -2))
    M = (S - cp[..., None, None] * _eye(s)) / (1.0 - cp)[..., None, None]  # = a a^T
    diag = torch.diagonal(M, dim1=-2, dim2=-1)  # [..., 3]
    k = diag.argmax(-1, keepdim=True)  # largest a_k^2 >= 1/3: safe to divide by sqrt
    col = torch.gather(M, -1, k[..., None].expand(*M.shape[:-1], 1)).squeeze(-1)
    akk = torch.gather(diag, -1, k).squeeze(-1)
    a = col / torch.sqrt(akk.clamp_min(1e-3))[..., None]
    sign = torch.where((a * s).sum(-1) < 0, -torch.ones_like(c), torch.ones_like(c))
    snp = torch.sqrt(torch.where(near_pi, s2, torch.zeros_like(s2)).clamp_min(tiny))
    phi_pi = a * (sign * torch.atan2(snp, cp))[..., None]

    return torch.where(
        near_zero[..., None], phi_zero, torch.where(near_pi[..., None], phi_pi, phi_gen)
    )


def se3_exp(xi):
    """Twist ``xi = (rho, phi)`` -> rigid transform ``[[R, V rho], [0, 0, 0, 1]]``.

    Args:
        xi: ``[..., 6]`` float tensor, translation part first; or a numpy array ``[6]`` (the
            host-side solvers' steps: float64 numpy, a tenth of the time of a round trip through
            torch's small operations).

    Returns:
        ``[..., 4, 4]``, same dtype/device (numpy float64 for numpy); exact identity at ``xi = 0``
        with finite gradients.
    """
    if isinstance(xi, np.ndarray):
        return _se3_exp_numpy(xi)
    _check_last(xi, "xi", (6,))
    rho, phi = xi[..., :3], xi[..., 3:]
    A, B, C = _coeffs((phi * phi).sum(-1))
    K = hat(phi)
    K2 = K @ K
    eye = _eye(phi)
    R = eye + A[..., None, None] * K + B[..., None, None] * K2
    V = eye + B[..., None, None] * K + C[..., None, None] * K2
    t = (V @ rho[..., None])  # [..., 3, 1]
    top = torch.cat([R, t], dim=-1)  # [..., 3, 4]
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def _se3_exp_numpy(xi: np.ndarray) -> np.ndarray:
    """:func:`se3_exp` of one twist ``[6]`` in float64 numpy (the same series, closed forms)."""
    xi = np.asarray(xi, np.float64)
    if xi.shape != (6,):
        raise ValueError(f"xi must be a numpy array of shape [6], got {list(xi.shape)}")
    rho, phi = xi[:3], xi[3:]
    x = float(phi @ phi)
    if x < _SMALL:
        A, B, C = _series(x)
    else:
        t = np.sqrt(x)
        A, B, C = _closed(x, t, np.sin(t), np.sin(0.5 * t))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    K2 = K @ K
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + A * K + B * K2
    T[:3, 3] = (np.eye(3) + B * K + C * K2) @ rho
    return T


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Rigid transform ``[..., 4, 4]`` (or ``[..., 3, 4]``) -> twist ``(rho, phi)`` ``[..., 6]``.

    Inverse of :func:`se3_exp` for ``|phi| < pi``; at ``|phi| = pi`` one of the two valid
    logarithms is returned.
    """
    if not isinstance(T, torch.Tensor) or T.ndim < 2 or tuple(T.shape[-2:]) not in ((4, 4), (3, 4)):
        shape = list(T.shape) if isinstance(T, torch.Tensor) else type(T).__name__
        raise ValueError(f"T must be a tensor of shape [..., 4, 4] or [..., 3, 4], got {shape}")
    phi = so3_log(T[..., :3, :3])
    rho = (so3_left_jacobian_inv(phi) @ T[..., :3, 3:4]).squeeze(-1)
    return torch.cat([rho, phi], dim=-1)
