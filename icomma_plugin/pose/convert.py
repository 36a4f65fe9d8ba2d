"""Frame conversions, pose error metrics (iComMa) and pose perturbation.

Conventions: docs/CONTRACTS.md and `icomma_plugin/pose/se3.py` (column vectors, OpenCV camera
axes x right / y down / z forward, ``c2w = inv(w2c)``, camera centre = ``c2w[:3, 3]``).

Every function accepts numpy arrays or torch tensors. Unless stated otherwise the result has the
input's kind, dtype and device; metrics are computed in float64.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import numpy as np
import torch

ArrayLike = Union[np.ndarray, torch.Tensor]
GeneratorLike = Union[None, int, np.random.Generator, torch.Generator]

__all__ = [
    "RIGID_ATOL",
    "SAME_POSE_ATOL",
    "as_rigid",
    "invert_rigid",
    "opengl_to_opencv_c2w",
    "opencv_to_opengl_c2w",
    "look_at_c2w",
    "rotation_about_axis",
    "random_rotation_about_axis",
    "random_unit_vector",
    "rotation_error_deg",
    "translation_error",
    "perturb_pose",
    "cameras_extent",
    "rigid_problem",
    "same_pose",
    "same_as_any_mask",
    "same_pose_mask",
]


def _check_mat(T, name: str, allowed=((4, 4),)) -> None:
    if not isinstance(T, (np.ndarray, torch.Tensor)):
        raise ValueError(f"{name} must be a numpy array or torch tensor, got {type(T).__name__}")
    if T.ndim < 2 or tuple(T.shape[-2:]) not in allowed:
        want = " or ".join(f"[..., {a}, {b}]" for a, b in allowed)
        raise ValueError(f"{name} must have shape {want}, got {list(T.shape)}")


def _to_np64(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def invert_rigid(T: ArrayLike) -> ArrayLike:
    """Inverse of rigid transforms ``[..., 4, 4]`` as ``[[R^T, -R^T t], [0, 1]]``.

    Exact for rigid inputs (no general matrix inverse); differentiable for torch inputs.

    Raises:
        ValueError: if ``T`` is not ``[..., 4, 4]``.
    """
    _check_mat(T, "T")
    if isinstance(T, torch.Tensor):
        Rt = T[..., :3, :3].transpose(-1, -2)
        t = -(Rt @ T[..., :3, 3:4])
        return torch.cat([torch.cat([Rt, t], -1), T[..., 3:4, :]], -2)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.array(T, copy=True)
    out[..., :3, :3] = Rt
    out[..., :3, 3:4] = -(Rt @ T[..., :3, 3:4])
    return out


#: Largest ``|R R^T - I|`` of a rotation that is accepted as one, everywhere a pose is read:
#: JSON files store rotations orthonormal to about float32 precision, and text files with 4-6
#: decimals to about 1e-4. One tolerance, so that a pose one reader accepts no other refuses.
RIGID_ATOL = 1e-3


def rigid_problem(T) -> Optional[str]:
    """Why ``T`` is not a rigid ``[4, 4]`` transform (within `RIGID_ATOL`), or None when it is.

    Callers raise their own error type with this reason, naming their argument or file; most
    use :func:`as_rigid`.
    """
    A = _to_np64(T) if isinstance(T, (np.ndarray, torch.Tensor)) else None
    if A is None:
        return f"expected a 4x4 numpy array or torch tensor, got {type(T).__name__}"
    if A.shape != (4, 4):
        return f"expected shape [4, 4], got {list(A.shape)}"
    if not np.all(np.isfinite(A)):
        return "it contains NaN or infinite values"
    R = A[:3, :3]
    if np.abs(R).max() > 2.0:  # no rotation has such an entry (and R R^T could overflow)
        return (f"its rotation part is not a rotation (an entry of magnitude "
                f"{np.abs(R).max():.3g})")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > RIGID_ATOL or np.linalg.det(R) < 0:
        return (f"its rotation part is not a rotation: not orthonormal with det +1 (max "
                f"|R R^T - I| = {err:.2g}, det = {np.linalg.det(R):.4f})")
    if not np.allclose(A[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return f"its last row must be [0, 0, 0, 1], got {A[3].tolist()}"
    return None


def as_rigid(T, what: str, error: type = ValueError) -> np.ndarray:
    """``T`` (4x4, or 3x4 completed with ``0 0 0 1``) as a float64 numpy copy, if it is rigid.

    The one pose check of the project (tolerance `RIGID_ATOL`).

    Raises:
        error: (ValueError unless given) naming ``what``, with the reason.
    """
    try:
        A = _to_np64(T) if isinstance(T, torch.Tensor) else np.array(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise error(f"{what} must be a numeric 4x4 matrix, got {type(T).__name__}") from None
    if A.shape == (3, 4):
        A = np.vstack([A, [0.0, 0.0, 0.0, 1.0]])
    problem = rigid_problem(A)
    if problem is not None:
        raise error(f"{what} must be a rigid 4x4 transform (orthonormal rotation, det +1, last "
                    f"row 0 0 0 1): {problem}")
    return np.array(A, dtype=np.float64, copy=True)


def opengl_to_opencv_c2w(c2w: ArrayLike) -> ArrayLike:
    """Blender/NeRF (OpenGL: y up, z back) c2w -> OpenCV/COLMAP c2w: negate columns 1 and 2.

    This is 3DGS ``readCamerasFromTransforms``' ``c2w[:3, 1:3] *= -1``. The camera centre is
    unchanged. The map is its own inverse (see :func:`opencv_to_opengl_c2w`). Returns a copy.

    Args:
        c2w: ``[..., 4, 4]`` or ``[..., 3, 4]``.
    """
    _check_mat(c2w, "c2w", ((4, 4), (3, 4)))
    out = c2w.clone() if isinstance(c2w, torch.Tensor) else np.array(c2w, copy=True)
    out[..., :3, 1:3] = -out[..., :3, 1:3]
    return out


def opencv_to_opengl_c2w(c2w: ArrayLike) -> ArrayLike:
    """OpenCV c2w -> OpenGL/Blender c2w (same column flip as :func:`opengl_to_opencv_c2w`)."""
    return opengl_to_opencv_c2w(c2w)


def look_at_c2w(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV-axes c2w of a camera at ``eye`` looking at ``target``; image "up" towards ``up``.

    Columns of the rotation: x = normalise(forward x up) (right), y = forward x x (down, i.e.
    against ``up``), z = forward.

    Returns:
        ``[4, 4]`` float64 numpy.

    Raises:
        ValueError: if ``eye == target`` or ``up`` is parallel to the viewing direction.
    """
    eye, target, up = (_to_np64(v).reshape(3) for v in (eye, target, up))
    f = target - eye
    if np.linalg.norm(f) < 1e-12:
        raise ValueError(f"look_at_c2w: eye and target must differ, got eye={eye} target={target}")
    f = f / np.linalg.norm(f)
    x = np.cross(f, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"look_at_c2w: up={up} is parallel to the viewing direction {f}")
    x = x / np.linalg.norm(x)
    y = np.cross(f, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, f, eye
    return c2w


def rotation_about_axis(axis, angle_deg: float) -> np.ndarray:
    """Rotation matrix ``[3, 3]`` float64 (numpy) by ``angle_deg`` degrees about ``axis``.

    Right-hand rule; ``axis`` need not be normalised.

    Raises:
        ValueError: if ``axis`` is zero or not a 3-vector.
    """
    a = _to_np64(axis)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-12:
        raise ValueError(f"axis must be a finite non-zero 3-vector, got {a!r}")
    a = a / np.linalg.norm(a)
    th = math.radians(float(angle_deg))
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


class _Rng:
    """Uniform interface over numpy / torch generators; draws float64 numpy values."""

    def __init__(self, generator: GeneratorLike):
        if isinstance(generator, torch.Generator):
            self.torch_gen, self.np_gen = generator, None
        elif generator is None or isinstance(generator, (int, np.integer)):
            self.torch_gen, self.np_gen = None, np.random.default_rng(generator)
        elif isinstance(generator, np.random.Generator):
            self.torch_gen, self.np_gen = None, generator
        else:
            raise ValueError(
                "generator must be None, an int seed, a numpy Generator or a torch.Generator, "
                f"got {type(generator).__name__}"
            )

    def normal(self, n: int) -> np.ndarray:
        if self.torch_gen is not None:
            return torch.randn(n, generator=self.torch_gen, dtype=torch.float64).numpy()
        return self.np_gen.standard_normal(n)

    def uniform(self, n: int) -> np.ndarray:
        """Uniform in [-1, 1)."""
        if self.torch_gen is not None:
            return torch.rand(n, generator=self.torch_gen, dtype=torch.float64).numpy() * 2 - 1
        return self.np_gen.uniform(-1.0, 1.0, n)

    def direction(self) -> np.ndarray:
        """Uniform direction on the unit sphere (normalised Gaussian)."""
        while True:
            v = self.normal(3)
            n = np.linalg.norm(v)
            if n > 1e-9:
                return v / n


def random_unit_vector(generator: GeneratorLike = None) -> np.ndarray:
    """A direction uniform on the unit sphere (a normalised Gaussian draw), float64 ``[3]``."""
    return _Rng(generator).direction()


def random_rotation_about_axis(
    angle_deg: float, generator: GeneratorLike = None, axis=None
) -> np.ndarray:
    """Rotation by exactly ``angle_deg`` degrees about a uniformly random axis (or ``axis``).

    Args:
        angle_deg: rotation angle in degrees.
        generator: None, an int seed, ``np.random.Generator`` or ``torch.Generator`` (CPU).
        axis: optional fixed axis ``[3]``; then no random number is drawn.

    Returns:
        ``[3, 3]`` float64 numpy rotation.
    """
    if axis is None:
        axis = _Rng(generator).direction()
    return rotation_about_axis(axis, angle_deg)


def _rotation_part(T, name: str) -> np.ndarray:
    _check_mat(T, name, ((3, 3), (3, 4), (4, 4)))
    return _to_np64(T)[..., :3, :3]


def _wrap_metric(value: np.ndarray, like):
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(value, dtype=torch.float64, device=like.device)
    return value


def rotation_error_deg(est: ArrayLike, gt: ArrayLike):
    """Rotation error in degrees: the angle of ``R_est R_gt^T``.

    iComMa's metric (``utils/calculate_error_utils.py``, ``arccos((trace - 1) / 2)``).

    Computed as ``atan2(sin, cos)`` with ``cos = (trace - 1) / 2`` and ``sin`` from the skew part
    ``|vee(R - R^T)| / 2``: the same angle for exact rotations, but well conditioned near 0. The
    arccos form loses all precision there, and on rotations that are orthonormal only to float32
    precision (NeRF-synthetic's ``transform_matrix`` rows: ``R R^T = I`` to ~2e-7) it reads a
    perfect estimate as up to 0.03 degrees off, or as exactly 0 when the trace rounds above 3.

    Pass both as c2w (as iComMa does) or both as w2c: the angle is the same. Computed in float64
    numpy; not meant for gradients.

    Args:
        est: ``[..., 3, 3]``, ``[..., 3, 4]`` or ``[..., 4, 4]`` (only the rotation block is used).
        gt: same, broadcastable against ``est``.

    Returns:
        Angle(s) in [0, 180] with the batch shape: numpy float64 array (0-d for one pose; use
        ``float()``) for numpy input, float64 tensor on ``est``'s device for torch input.
    """
    Re, Rg = _rotation_part(est, "est"), _rotation_part(gt, "gt")
    Rr = np.einsum("...ij,...kj->...ik", Re, Rg)  # R_est @ R_gt^T
    cos = 0.5 * (np.einsum("...ii->...", Rr) - 1.0)
    skew = np.stack([Rr[..., 2, 1] - Rr[..., 1, 2], Rr[..., 0, 2] - Rr[..., 2, 0],
                     Rr[..., 1, 0] - Rr[..., 0, 1]], -1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    return _wrap_metric(np.degrees(np.arctan2(sin, cos)), est)


def translation_error(c2w_est: ArrayLike, c2w_gt: ArrayLike):
    """iComMa translation error: the distance between camera centres.

    ``||c2w_est[:3, 3] - c2w_gt[:3, 3]||`` in scene units. Both arguments must be c2w (a w2c
    translation is not the camera centre).

    Args:
        c2w_est: ``[..., 3, 4]`` or ``[..., 4, 4]``.
        c2w_gt: same, broadcastable against ``c2w_est``.

    Returns:
        As :func:`rotation_error_deg`.
    """
    _check_mat(c2w_est, "c2w_est", ((3, 4), (4, 4)))
    _check_mat(c2w_gt, "c2w_gt", ((3, 4), (4, 4)))
    d = _to_np64(c2w_est)[..., :3, 3] - _to_np64(c2w_gt)[..., :3, 3]
    return _wrap_metric(np.linalg.norm(d, axis=-1), c2w_est)


def perturb_pose(
    c2w: ArrayLike, rot_deg: float, trans, generator: GeneratorLike = None, pivot="camera"
):
    """Perturb camera pose(s) by an exact rotation angle and a translation, for initialisation.

    The rotation is by exactly ``rot_deg`` degrees about a uniformly random axis through the
    camera centre, expressed in the world frame (``R' = R_delta @ R``, centre unchanged), so
    :func:`rotation_error_deg` of the result against ``c2w`` is ``rot_deg`` (for
    ``rot_deg <= 180``). The camera centre is then moved by a world-frame offset:

    - ``trans`` a scalar: offset of norm exactly ``trans`` in a uniformly random direction
      (:func:`translation_error` is ``trans``);
    - ``trans`` a 3-vector ``(tx, ty, tz)``: each component drawn uniformly in ``[-t_i, t_i]``
      (max magnitudes per world axis).

    ``pivot`` chooses the point the rotation turns about: ``"camera"`` (default; rotation and
    translation errors are controlled independently) or ``"origin"`` / a world point ``[3]``
    (iComMa/iNeRF: ``c2w' = T(offset) @ R_delta @ c2w``, the camera orbits the pivot, so an
    object at the pivot stays in view; the centre then also moves by the rotation).

    Args:
        c2w: ``[4, 4]`` or ``[B, 4, 4]`` OpenCV c2w (numpy or torch); batched poses get independent
            draws.
        rot_deg: rotation angle in degrees.
        trans: scalar norm, or per-axis maxima ``[3]`` (world units).
        generator: None, int seed, ``np.random.Generator`` or CPU ``torch.Generator``.
        pivot: ``"camera"``, ``"origin"`` or a world point ``[3]`` to rotate about.

    Returns:
        Perturbed c2w with the input's kind, shape, dtype and device (drawn in float64).

    Raises:
        ValueError: on bad shapes, a negative or non-finite ``trans``/``rot_deg``.
    """
    _check_mat(c2w, "c2w")
    if not math.isfinite(float(rot_deg)):
        raise ValueError(f"rot_deg must be finite, got {rot_deg!r}")
    t = _to_np64(trans)
    if t.shape not in ((), (1,), (3,)) or not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError(
            f"trans must be a non-negative scalar (norm) or 3-vector (per-axis max), got {trans!r}"
        )
    if isinstance(pivot, str):
        if pivot not in ("camera", "origin"):
            raise ValueError(f"pivot must be 'camera', 'origin' or a 3-vector, got {pivot!r}")
        pivot_point = None if pivot == "camera" else np.zeros(3)
    else:
        pivot_point = _to_np64(pivot).reshape(-1)
        if pivot_point.shape != (3,) or not np.all(np.isfinite(pivot_point)):
            raise ValueError(
                f"pivot must be 'camera', 'origin' or a finite 3-vector, got {pivot!r}"
            )
    rng = _Rng(generator)
    T = _to_np64(c2w)
    flat = T.reshape(-1, 4, 4).copy()
    for i in range(flat.shape[0]):
        Rd = rotation_about_axis(rng.direction(), rot_deg)
        if t.shape == (3,):
            offset = rng.uniform(3) * t
        else:
            offset = rng.direction() * float(t.reshape(()))
        centre = flat[i, :3, 3]
        if pivot_point is not None:  # orbit: rotate the centre about the pivot as well
            centre = pivot_point + Rd @ (centre - pivot_point)
        flat[i, :3, :3] = Rd @ flat[i, :3, :3]
        flat[i, :3, 3] = centre + offset
    out = flat.reshape(T.shape)
    if isinstance(c2w, torch.Tensor):
        return torch.as_tensor(out, dtype=c2w.dtype, device=c2w.device)
    return out.astype(c2w.dtype if np.issubdtype(c2w.dtype, np.floating) else np.float64)


def cameras_extent(c2ws) -> float:
    """The scene scale of the project (3DGS ``getNerfppNorm`` radius).

    1.1 x the largest distance of the camera centres from their mean. Every success criterion
    that is relative to the scene uses this, computed on the cameras the model was fitted from.

    Args:
        c2ws: sequence of ``[4, 4]`` (or ``[3, 4]``) camera-to-world matrices, at least one.

    Raises:
        ValueError: on an empty sequence.
    """
    c2ws = list(c2ws)
    if not c2ws:
        raise ValueError("cameras_extent needs at least one camera-to-world matrix, got none")
    c = np.stack([_to_np64(T)[:3, 3] for T in c2ws])
    return float(1.1 * np.linalg.norm(c - c.mean(0), axis=1).max())


#: Two poses closer than this (every entry of the 4x4) are the same camera: the one rule that
#: leaves a query's own camera out of its candidates (a benchmark must not find its answer there).
SAME_POSE_ATOL = 1e-5


def same_pose(c2w_a: np.ndarray, c2w_b: np.ndarray) -> bool:
    """Whether two camera-to-world poses are the same camera (`SAME_POSE_ATOL`)."""
    return bool(same_pose_mask(np.asarray(c2w_a)[None], c2w_b)[0])


def same_pose_mask(c2ws: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """`same_pose` of each of the [N, 4, 4] ``c2ws`` with ``c2w``, in one pass: a bool [N]."""
    return np.isclose(c2ws, c2w, atol=SAME_POSE_ATOL).all(axis=(-2, -1))


def same_as_any_mask(c2ws: Sequence[np.ndarray], others: Sequence[np.ndarray]) -> np.ndarray:
    """For each of ``c2ws``, whether it is `same_pose` as one of ``others``: a bool [N].

    One vectorised pass per pose of ``others`` instead of a call per pair.
    """
    out = np.zeros(len(c2ws), dtype=bool)
    if len(c2ws) == 0:
        return out
    stack = np.stack([np.asarray(c, np.float64) for c in c2ws])
    for other in others:
        out |= same_pose_mask(stack, np.asarray(other, np.float64))
    return out
