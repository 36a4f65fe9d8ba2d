"""How precisely 2D-3D observations fix a pinhole camera's pose (first-order covariance).

A registered photo's recorded pose (COLMAP's, for instance) is an estimate from the image points
it observes, each off its projection by about the reconstruction's reprojection error. To first
order, with the 3D points held fixed, the pose's covariance is ``sigma^2 (J^T J)^-1``: ``J`` the
Jacobian of the projections with respect to the pose (and to the focal length where the
reconstruction estimated one per photo), ``sigma^2`` the residuals' variance. The points' own
uncertainty is left out, so this is a lower bound on how far a record may be from the truth: a
localized pose cannot be checked against the record more finely than that (docs/AUDIT.md).

Perturbation: ``w2c <- se3_exp(xi) @ w2c`` with ``xi = (tau, omega)`` (a camera-frame twist,
docs/CONTRACTS.md), to first order ``Xc <- Xc + omega x Xc + tau``; the camera centre moves by
``-R^T tau``. The covariance's columns here are ``omega`` first, then ``tau``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Dict, List

import numpy as np

__all__ = ["MAX_BUNDLE_PARAMS", "WITHIN_SIGMAS", "PosePrecision", "bundle_precision",
           "pose_precision", "rotation_sigmas"]

#: A rotation whose Mahalanobis distance under a pose's rotation covariance is at most this is
#: within that pose's uncertainty: the 99 % quantile of the chi-square law with 3 degrees of
#: freedom is 11.34 = 3.368^2.
WITHIN_SIGMAS = 3.368


@dataclass
class PosePrecision:
    """One camera's pose precision from its observations.

    rot_std_deg: root-mean-square rotation error (the square root of the rotation covariance's
        trace), degrees; the median angle of such an error is about 0.9 times this.
    centre_std: root-mean-square camera-centre error, world units.
    rms_px: the residuals' root-mean-square (the ``sigma`` used), pixels.
    points: observations used.
    focal_free: whether the focal length was a parameter too (one camera per photo).
    rot_cov: [3, 3] covariance of the camera-frame rotation ``omega`` (rad^2), the translation
        and focal length marginalised: an error along a direction the observations fix poorly
        (a turn that a shift of the camera makes up for) is judged by that direction's spread.
    points_free: the points were estimated too (``bundle_precision``: the whole
        reconstruction's uncertainty); False: held fixed (``pose_precision``: a lower bound).
    """

    rot_std_deg: float
    centre_std: float
    rms_px: float
    points: int
    focal_free: bool
    rot_cov: List[List[float]] = field(default_factory=list)
    points_free: bool = False

    def to_json(self) -> Dict[str, Any]:
        """The fields as a JSON-ready dict."""
        return asdict(self)


#: The focal-length parameters of each ``focal`` mode.
_FOCAL_PARAMS = {"none": 0, "shared": 1, "separate": 2}


def _from_covariance(cov: np.ndarray, R: np.ndarray, sigma: float, points: int, focal_free: bool,
                     points_free: bool) -> PosePrecision:
    """A camera's ``PosePrecision`` from its covariance block (twist ``omega, tau`` first)."""
    rot = float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))
    centre = float(np.sqrt(max(np.trace(R.T @ cov[3:6, 3:6] @ R), 0.0)))
    return PosePrecision(rot, centre, sigma, points, focal_free, cov[:3, :3].tolist(),
                         points_free)


def _projection_jacobian(xc: np.ndarray, fx: float, fy: float, focal: str) -> np.ndarray:
    """[2N, P] Jacobian of the pinhole projections of camera-frame points ``xc`` [N, 3].

    Columns: the rotation (3), the translation (3) of the camera-frame twist, then the focal
    parameters (``focal``: "none", "shared" (one f) or "separate" (fx, fy)).
    """
    x, y, z = xc[:, 0], xc[:, 1], xc[:, 2]
    a, b = x / z, y / z
    zero = np.zeros_like(z)
    ju = [fx * -a * b, fx * (1.0 + a * a), fx * -b, fx / z, zero, -fx * a / z]
    jv = [fy * -(1.0 + b * b), fy * a * b, fy * a, zero, fy / z, -fy * b / z]
    if focal == "shared":
        ju.append(a)
        jv.append(b)
    elif focal == "separate":
        ju += [a, zero]
        jv += [zero, b]
    return np.concatenate([np.stack(ju, 1), np.stack(jv, 1)], 0)


def pose_precision(w2c: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                   xyz: np.ndarray, xy: np.ndarray, focal: str = "none") -> PosePrecision:
    """First-order precision of the pose ``w2c`` given its observations (module docstring).

    Args:
        w2c: [4, 4] world-to-camera pose (OpenCV axes).
        fx: focal length along x [px].
        fy: focal length along y [px].
        cx: principal point x, in the pixel convention of ``xy``.
        cy: principal point y, likewise.
        xyz: [N, 3] world points.
        xy: [N, 2] where the photo observed them [px].
        focal: "none" (intrinsics known), "shared" (one focal length estimated with the pose)
            or "separate" (fx and fy estimated).

    Raises:
        ValueError: mismatched shapes, too few points for the parameters, points behind the
            camera, or a degenerate configuration (a singular ``J^T J``).
    """
    w2c = np.asarray(w2c, np.float64)
    xyz, xy = np.asarray(xyz, np.float64), np.asarray(xy, np.float64)
    if w2c.shape != (4, 4):
        raise ValueError(f"w2c must be [4, 4], got {list(w2c.shape)}")
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xy.shape != (len(xyz), 2):
        raise ValueError(f"xyz must be [N, 3] and xy [N, 2] with the same N, got "
                         f"{list(xyz.shape)} and {list(xy.shape)}")
    if focal not in _FOCAL_PARAMS:
        raise ValueError(f"focal must be 'none', 'shared' or 'separate', got {focal!r}")
    n_params = 6 + _FOCAL_PARAMS[focal]
    if 2 * len(xyz) <= n_params:
        raise ValueError(f"{len(xyz)} observations cannot fix {n_params} parameters: at least "
                         f"{n_params // 2 + 1} needed")
    R, t = w2c[:3, :3], w2c[:3, 3]
    xc = xyz @ R.T + t
    if np.any(xc[:, 2] <= 0):
        raise ValueError(f"{int(np.sum(xc[:, 2] <= 0))} of {len(xc)} points lie behind the camera")
    u = fx * xc[:, 0] / xc[:, 2] + cx
    v = fy * xc[:, 1] / xc[:, 2] + cy
    r = np.concatenate([u - xy[:, 0], v - xy[:, 1]])
    J = _projection_jacobian(xc, fx, fy, focal)
    sigma2 = float(r @ r) / (len(r) - n_params)
    jtj = J.T @ J
    if np.linalg.cond(jtj) > 1e14:
        raise ValueError("the observations do not fix the pose (a singular J^T J: too few or "
                         "collinear points)")
    return _from_covariance(sigma2 * np.linalg.inv(jtj), R, float(np.sqrt(sigma2)), len(xyz),
                            focal != "none", points_free=False)


def rotation_sigmas(w2c_est: np.ndarray, w2c_rec: np.ndarray, rot_cov) -> float:
    """Mahalanobis distance of ``w2c_est``'s rotation from ``w2c_rec``'s under ``rot_cov``.

    ``omega = log(R_est R_rec^T)`` (the camera-frame rotation taking the record to the estimate,
    the module's perturbation); ``sqrt(omega^T rot_cov^-1 omega)``. Rotations are compared in
    the cameras' frame, so a similarity transform of the world (a reader's recentring) leaves it
    unchanged. At most ``WITHIN_SIGMAS``: within the record's uncertainty (99 %).

    Raises:
        ValueError: poses that are not [4, 4], or a covariance that is not a positive definite
            [3, 3].
    """
    import torch

    from .se3 import so3_log

    a, b = np.asarray(w2c_est, np.float64), np.asarray(w2c_rec, np.float64)
    if a.shape != (4, 4) or b.shape != (4, 4):
        raise ValueError(f"w2c_est and w2c_rec must be [4, 4], got {list(a.shape)} and "
                         f"{list(b.shape)}")
    cov = np.asarray(rot_cov, np.float64)
    if cov.shape != (3, 3) or not np.all(np.linalg.eigvalsh((cov + cov.T) / 2) > 0):
        raise ValueError(f"rot_cov must be a positive definite [3, 3], got {cov.tolist()}")
    omega = so3_log(torch.as_tensor(a[:3, :3] @ b[:3, :3].T)).numpy()
    return float(np.sqrt(omega @ np.linalg.solve(cov, omega)))


#: A bundle of more camera parameters than this is not inverted (a dense matrix of its size
#: squared): ``bundle_precision`` refuses it and callers fall back to the points held fixed.
MAX_BUNDLE_PARAMS = 8000


def bundle_precision(w2cs, intrinsics, focal, xyz, obs_camera, obs_point, obs_xy):
    """First-order precision of every camera of a reconstruction, its points free.

    As a bundle adjustment sees it, relative to the reconstruction as a whole: the normal matrix
    of all cameras' twists (and focal lengths, per ``focal``) and all points, the points
    eliminated (Schur complement, each point's 3x3 block inverted), inverted without its 7
    smallest eigen-directions, the 7 free directions of a reconstruction (where it sits, how it
    is turned, its scale): the pseudo-inverse, which fixes them by the least change of the
    camera parameters, so each camera's uncertainty is relative to the others'. ``sigma^2``:
    the residuals' variance over the degrees of freedom. Points seen by fewer than two cameras
    are left out (nothing fixes their depth).

    Args:
        w2cs: [C, 4, 4] world-to-camera poses.
        intrinsics: [C, 4] (fx, fy, cx, cy) in the pixel convention of ``obs_xy``.
        focal: per camera "none", "shared" or "separate" (its focal lengths estimated too).
        xyz: [M, 3] points.
        obs_camera: [K] the camera of each observation.
        obs_point: [K] its point.
        obs_xy: [K, 2] where the camera observed the point.

    Returns:
        A ``PosePrecision`` per camera (``points`` its observations used).

    Raises:
        ValueError: mismatched shapes, a point behind a camera that observes it, more than
            ``MAX_BUNDLE_PARAMS`` camera parameters, or more free directions than the 7 of a
            similarity (a camera that shares no point with the others).
    """
    from scipy import sparse

    w2cs = np.asarray(w2cs, np.float64)
    K_ = np.asarray(intrinsics, np.float64)
    xyz = np.asarray(xyz, np.float64)
    cam = np.asarray(obs_camera, np.int64)
    pt = np.asarray(obs_point, np.int64)
    xy = np.asarray(obs_xy, np.float64)
    C = len(w2cs)
    if C < 2:
        raise ValueError(f"a bundle needs at least 2 cameras, got {C}")
    if w2cs.shape != (C, 4, 4) or K_.shape != (C, 4) or len(focal) != C:
        raise ValueError(f"w2cs [C, 4, 4], intrinsics [C, 4] and focal [C] must agree, got "
                         f"{list(w2cs.shape)}, {list(K_.shape)} and {len(focal)}")
    if not (cam.shape == pt.shape == xy.shape[:1]) or xy.shape[1:] != (2,):
        raise ValueError(f"obs_camera, obs_point [K] and obs_xy [K, 2] must agree, got "
                         f"{list(cam.shape)}, {list(pt.shape)} and {list(xy.shape)}")
    bad = [f for f in focal if f not in _FOCAL_PARAMS]
    if bad:
        raise ValueError(f"focal must be 'none', 'shared' or 'separate' per camera, got {bad[0]!r}")
    if len(cam) and (cam.min() < 0 or cam.max() >= C or pt.min() < 0 or pt.max() >= len(xyz)):
        raise ValueError(f"obs_camera must index the {C} cameras and obs_point the {len(xyz)} "
                         "points")
    nf = np.array([_FOCAL_PARAMS[f] for f in focal])
    if int((6 + nf).sum()) > MAX_BUNDLE_PARAMS:
        raise ValueError(f"{int((6 + nf).sum())} camera parameters: more than "
                         f"MAX_BUNDLE_PARAMS={MAX_BUNDLE_PARAMS}")
    track = np.bincount(pt, minlength=len(xyz))
    keep = track[pt] >= 2
    cam, pt, xy = cam[keep], pt[keep], xy[keep]
    R, t = w2cs[cam, :3, :3], w2cs[cam, :3, 3]
    xc = np.einsum("kij,kj->ki", R, xyz[pt]) + t
    if np.any(xc[:, 2] <= 0):
        raise ValueError(f"{int(np.sum(xc[:, 2] <= 0))} observations lie behind their camera")
    fx, fy, cx, cy = (K_[cam, i] for i in range(4))
    x, y, z = xc.T
    r = np.concatenate([fx * x / z + cx - xy[:, 0], fy * y / z + cy - xy[:, 1]])
    n = len(cam)
    # camera columns, padded to 8 (twist, fx, fy); a camera's unused focal columns are zero
    J = _projection_jacobian(xc, fx, fy, "separate")
    A = np.stack([J[:n], J[n:]], 1)  # [K, 2, 8]
    shared = nf[cam] == 1
    A[shared, :, 6] += A[shared, :, 7]  # one focal length: d/df = d/dfx + d/dfy
    A[:, :, 7] *= (nf[cam] == 2)[:, None]
    A[:, :, 6] *= (nf[cam] >= 1)[:, None]
    du = np.stack([fx / z, 0 * z, -fx * x / z ** 2], 1)
    dv = np.stack([0 * z, fy / z, -fy * y / z ** 2], 1)
    B = np.einsum("kai,kij->kaj", np.stack([du, dv], 1), R)  # [K, 2, 3] d/d(world point)
    U = np.zeros((C, 8, 8))
    np.add.at(U, cam, np.einsum("kai,kaj->kij", A, A))
    V = np.zeros((len(xyz), 3, 3))
    np.add.at(V, pt, np.einsum("kai,kaj->kij", B, B))
    used = np.unique(pt)
    Vi = np.zeros_like(V)
    Vi[used] = np.linalg.pinv(V[used], hermitian=True)
    W = np.einsum("kai,kaj->kij", A, B)  # [K, 8, 3]
    rows = (cam[:, None, None] * 8 + np.arange(8)[None, :, None]).repeat(3, 2)
    cols = (pt[:, None, None] * 3 + np.arange(3)[None, None, :]).repeat(8, 1)
    Wsp = sparse.csr_matrix((W.ravel(), (rows.ravel(), cols.ravel())),
                            shape=(C * 8, len(xyz) * 3))
    vr = (np.arange(len(xyz))[:, None, None] * 3 + np.arange(3)[None, :, None]).repeat(3, 2)
    vc = (np.arange(len(xyz))[:, None, None] * 3 + np.arange(3)[None, None, :]).repeat(3, 1)
    Visp = sparse.csr_matrix((Vi.ravel(), (vr.ravel(), vc.ravel())),
                             shape=(len(xyz) * 3, len(xyz) * 3))
    S = -(Wsp @ Visp @ Wsp.T).toarray()
    for c in range(C):
        S[c * 8:(c + 1) * 8, c * 8:(c + 1) * 8] += U[c]
    active = np.concatenate([c * 8 + np.arange(6 + nf[c]) for c in range(C)])
    S = S[np.ix_(active, active)]
    dof = len(r) - len(active) - 3 * len(used) + 7
    if dof <= 0:
        raise ValueError(f"{n} observations cannot fix {len(active)} camera parameters and "
                         f"{len(used)} points")
    sigma2 = float(r @ r) / dof
    # the 7 directions of a similarity transform are free (zero eigenvalues up to rounding); the
    # next ones can be weak but real (a focal length against the distance): drop exactly 7
    lam, Q = np.linalg.eigh((S + S.T) / 2)
    if not lam[7] > 1e3 * np.abs(lam[:7]).max():
        raise ValueError(f"the observations leave more than the 7 directions of a similarity "
                         f"free (eigenvalues {lam[:9].tolist()}): a camera or a part of the "
                         "reconstruction is not tied to the rest")
    cov = sigma2 * (Q[:, 7:] / lam[7:]) @ Q[:, 7:].T
    out, start = [], 0
    counts = np.bincount(cam, minlength=C)
    for c in range(C):
        p = 6 + nf[c]
        out.append(_from_covariance(cov[start:start + p, start:start + p], w2cs[c, :3, :3],
                                    float(np.sqrt(sigma2)), int(counts[c]), bool(nf[c]),
                                    points_free=True))
        start += p
    return out
