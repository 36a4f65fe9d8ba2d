"""The first-order pose covariance (icomma_plugin.pose.precision).

Checked against finite differences and against the scatter of poses estimated from noisy
observations.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from icomma_plugin.pose.convert import rotation_error_deg
from icomma_plugin.pose.precision import _projection_jacobian, pose_precision, rotation_sigmas
from icomma_plugin.pose.se3 import se3_exp
from tests.helpers.geometry import look_at_c2w

FX, FY, CX, CY = 500.0, 480.0, 320.0, 240.0


def _scene(n=150, seed=0):
    """A camera 4 units from points spread over a 2-unit cube around the origin."""
    rng = np.random.default_rng(seed)
    w2c = np.linalg.inv(look_at_c2w([4.0, 1.0, 0.5]))
    xyz = rng.uniform(-1.0, 1.0, (n, 3))
    return w2c, xyz


def _project(w2c, xyz, fx=FX, fy=FY):
    xc = xyz @ w2c[:3, :3].T + w2c[:3, 3]
    return np.stack([fx * xc[:, 0] / xc[:, 2] + CX, fy * xc[:, 1] / xc[:, 2] + CY], 1)


@pytest.mark.parametrize("focal", ["none", "shared", "separate"])
def test_jacobian_matches_finite_differences_of_the_twist(focal):
    w2c, xyz = _scene(20)
    xc = xyz @ w2c[:3, :3].T + w2c[:3, 3]
    J = _projection_jacobian(xc, FX, FY, focal)
    eps = 1e-6
    cols = []
    for k in range(6):  # precision's columns: rotation, then translation; se3's xi = (tau, omega)
        xi = np.zeros(6)
        xi[3 + k if k < 3 else k - 3] = eps
        step = se3_exp(torch.tensor(xi, dtype=torch.float64)).numpy()
        d = (_project(step @ w2c, xyz) - _project(np.linalg.inv(step) @ w2c, xyz)) / (2 * eps)
        cols.append(np.concatenate([d[:, 0], d[:, 1]]))
    if focal == "shared":
        d = (_project(w2c, xyz, FX + eps, FY + eps) - _project(w2c, xyz, FX - eps, FY - eps))
        cols.append(np.concatenate([d[:, 0], d[:, 1]]) / (2 * eps))
    elif focal == "separate":
        for dfx, dfy in ((eps, 0.0), (0.0, eps)):
            d = (_project(w2c, xyz, FX + dfx, FY + dfy) - _project(w2c, xyz, FX - dfx, FY - dfy))
            cols.append(np.concatenate([d[:, 0], d[:, 1]]) / (2 * eps))
    np.testing.assert_allclose(J, np.stack(cols, 1), rtol=1e-5, atol=1e-4)


def test_rotation_spread_of_estimated_poses_matches_the_prediction():
    """PnP on 200 noisy copies of the observations scatters as the covariance says."""
    w2c, xyz = _scene(60, seed=1)
    xy = _project(w2c, xyz)
    K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
    rng = np.random.default_rng(2)
    sigma = 1.0
    errs, centres = [], []
    rvec0, _ = cv2.Rodrigues(w2c[:3, :3])
    for _ in range(200):
        noisy = xy + rng.normal(0.0, sigma, xy.shape)
        ok, rvec, tvec = cv2.solvePnP(xyz, noisy, K, None, rvec0.copy(), w2c[:3, 3:].copy(),
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        assert ok
        est = np.eye(4)
        est[:3, :3], est[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        errs.append(float(rotation_error_deg(np.linalg.inv(est), np.linalg.inv(w2c))))
        centres.append(np.linalg.norm(-est[:3, :3].T @ est[:3, 3] + w2c[:3, :3].T @ w2c[:3, 3]))
    # the prediction from one noisy copy (its own residuals give sigma)
    p = pose_precision(w2c, FX, FY, CX, CY, xyz, xy + rng.normal(0.0, sigma, xy.shape))
    rms = float(np.sqrt(np.mean(np.square(errs))))
    assert p.rms_px == pytest.approx(sigma, rel=0.15)
    assert p.rot_std_deg == pytest.approx(rms, rel=0.2)
    assert p.centre_std == pytest.approx(float(np.sqrt(np.mean(np.square(centres)))), rel=0.2)
    assert p.points == 60 and not p.focal_free


def test_a_free_focal_length_makes_the_pose_less_certain_and_noise_scales_it():
    w2c, xyz = _scene(80, seed=3)
    rng = np.random.default_rng(4)
    noise = rng.normal(0.0, 1.0, (80, 2))
    xy = _project(w2c, xyz)
    fixed = pose_precision(w2c, FX, FY, CX, CY, xyz, xy + noise)
    free = pose_precision(w2c, FX, FY, CX, CY, xyz, xy + noise, focal="shared")
    both = pose_precision(w2c, FX, FY, CX, CY, xyz, xy + noise, focal="separate")
    assert free.rot_std_deg > fixed.rot_std_deg and free.focal_free
    assert both.rot_std_deg >= free.rot_std_deg * 0.99
    doubled = pose_precision(w2c, FX, FY, CX, CY, xyz, xy + 2 * noise)
    assert doubled.rot_std_deg == pytest.approx(2 * fixed.rot_std_deg, rel=0.05)


def test_bad_input_is_refused_with_the_argument_named():
    w2c, xyz = _scene(10)
    xy = _project(w2c, xyz)
    with pytest.raises(ValueError, match="w2c"):
        pose_precision(np.eye(3), FX, FY, CX, CY, xyz, xy)
    with pytest.raises(ValueError, match="xyz must be"):
        pose_precision(w2c, FX, FY, CX, CY, xyz, xy[:5])
    with pytest.raises(ValueError, match="cannot fix"):
        pose_precision(w2c, FX, FY, CX, CY, xyz[:3], xy[:3])
    with pytest.raises(ValueError, match="focal"):
        pose_precision(w2c, FX, FY, CX, CY, xyz, xy, focal="yes")
    behind = xyz.copy()
    behind[0] = -10 * (np.linalg.inv(w2c)[:3, 2]) + np.linalg.inv(w2c)[:3, 3]
    with pytest.raises(ValueError, match="behind the camera"):
        pose_precision(w2c, FX, FY, CX, CY, behind, xy)
    flat = np.zeros((10, 3))  # every point at one place: nothing fixes the pose
    with pytest.raises(ValueError, match="do not fix the pose"):
        pose_precision(w2c, FX, FY, CX, CY, flat, _project(w2c, flat))


def test_rotation_sigmas_whiten_by_the_covariance_and_ignore_the_worlds_frame():
    w2c, xyz = _scene(60, seed=5)
    rng = np.random.default_rng(6)
    p = pose_precision(w2c, FX, FY, CX, CY, xyz, _project(w2c, xyz) + rng.normal(0, 1, (60, 2)))
    cov = np.array(p.rot_cov)
    assert p.rot_std_deg == pytest.approx(np.degrees(np.sqrt(np.trace(cov))), rel=1e-9)
    evals, evecs = np.linalg.eigh(cov)
    for k in range(3):  # a turn of 2 standard deviations along each principal axis: 2 sigmas
        omega = 2.0 * np.sqrt(evals[k]) * evecs[:, k]
        turned = se3_exp(torch.tensor(np.r_[np.zeros(3), omega])).numpy() @ w2c
        assert rotation_sigmas(turned, w2c, cov) == pytest.approx(2.0, rel=1e-6)
    # the same two poses in a moved, turned and scaled world: the same distance
    omega = 1.5 * np.sqrt(evals[0]) * evecs[:, 0] + np.sqrt(evals[2]) * evecs[:, 2]
    turned = se3_exp(torch.tensor(np.r_[np.zeros(3), omega])).numpy() @ w2c
    S = np.eye(4)
    S[:3, :3] = 2.0 * cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0]
    S[:3, 3] = [1.0, -2.0, 0.5]
    def moved(m):
        c2w = S @ np.linalg.inv(m)
        c2w[:3, :3] /= 2.0  # the camera's axes stay orthonormal
        return np.linalg.inv(c2w)
    assert rotation_sigmas(moved(turned), moved(w2c), cov) == pytest.approx(
        rotation_sigmas(turned, w2c, cov), rel=1e-9)
    assert rotation_sigmas(turned, w2c, cov) == pytest.approx(np.sqrt(1.5 ** 2 + 1.0), rel=1e-6)
    with pytest.raises(ValueError, match="rot_cov must be a positive definite"):
        rotation_sigmas(turned, w2c, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="must be \\[4, 4\\]"):
        rotation_sigmas(turned[:3], w2c, cov)


def _bundle(n_cams=5, n_pts=40, seed=7):
    """Cameras on a ring around points, each observing every point with 0.5 px of noise."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-1.0, 1.0, (n_pts, 3))
    w2cs, intr, focal = [], [], []
    cam, pt, xy = [], [], []
    for c in range(n_cams):
        a = 2 * np.pi * c / (n_cams * 3)
        w2c = np.linalg.inv(look_at_c2w([4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.1 * c]))
        f = FX + 10 * c
        w2cs.append(w2c)
        intr.append([f, f * 0.98, CX, CY])
        focal.append(("none", "shared", "separate")[c % 3])
        uv = _project(w2c, xyz, f, f * 0.98) + rng.normal(0, 0.5, (n_pts, 2))
        cam += [c] * n_pts
        pt += list(range(n_pts))
        xy.append(uv)
    return np.array(w2cs), np.array(intr), focal, xyz, np.array(cam), np.array(pt), np.vstack(xy)


def test_bundle_precision_is_the_schur_complement_of_the_whole_normal_matrix():
    """The points eliminated (sparse, per point) as a dense solve of the whole system does."""
    from icomma_plugin.pose.precision import bundle_precision

    w2cs, intr, focal, xyz, cam, pt, xy = _bundle()
    got = bundle_precision(w2cs, intr, focal, xyz, cam, pt, xy)
    # the reference: the dense Jacobian of every camera parameter and point coordinate
    nf = [{"none": 0, "shared": 1, "separate": 2}[f] for f in focal]
    offs = np.cumsum([0] + [6 + k for k in nf])
    P, M = offs[-1], len(xyz)
    rows, res = [], []
    for k in range(len(cam)):
        c, j = cam[k], pt[k]
        fx, fy, cx, cy = intr[c]
        xc = w2cs[c, :3, :3] @ xyz[j] + w2cs[c, :3, 3]
        Jc = _projection_jacobian(xc[None], fx, fy, focal[c])  # [2, 6 + nf]
        x, y, z = xc
        Jp = np.array([[fx / z, 0, -fx * x / z ** 2], [0, fy / z, -fy * y / z ** 2]])
        Jp = Jp @ w2cs[c, :3, :3]
        row = np.zeros((2, P + 3 * M))
        row[:, offs[c]:offs[c + 1]] = Jc
        row[:, P + 3 * j:P + 3 * j + 3] = Jp
        rows.append(row)
        res += [fx * x / z + cx - xy[k, 0], fy * y / z + cy - xy[k, 1]]
    J = np.vstack(rows)
    H = J.T @ J
    S = H[:P, :P] - H[:P, P:] @ np.linalg.solve(H[P:, P:], H[P:, :P])
    res = np.array(res)
    sigma2 = res @ res / (len(res) - P - 3 * M + 7)
    lam, Q = np.linalg.eigh(S)
    assert np.all(np.abs(lam[:7]) < 1e-12 * lam[-1]) and lam[7] > 1e-11 * lam[-1]  # the gauge
    cov = sigma2 * np.linalg.pinv(S, rcond=1e-13, hermitian=True)
    for c, p in enumerate(got):  # (a weak direction at 6e-10 of the largest: rounding x 1e5)
        blk = cov[offs[c]:offs[c] + 3, offs[c]:offs[c] + 3]
        np.testing.assert_allclose(np.array(p.rot_cov), blk, rtol=1e-4,
                                   atol=1e-4 * np.abs(blk).max())
        assert p.rot_std_deg == pytest.approx(np.degrees(np.sqrt(np.trace(blk))), rel=1e-4)
        assert p.points_free and p.points == 40 and p.focal_free == (focal[c] != "none")
        assert p.rms_px == pytest.approx(np.sqrt(sigma2), rel=1e-9)


def test_bundle_precision_leaves_out_points_seen_once_and_refuses_bad_input():
    from icomma_plugin.pose.precision import MAX_BUNDLE_PARAMS, bundle_precision

    w2cs, intr, focal, xyz, cam, pt, xy = _bundle()
    extra = np.vstack([xyz, [[0.1, 0.2, 0.3]]])  # seen by camera 0 only
    base = bundle_precision(w2cs, intr, focal, xyz, cam, pt, xy)
    more = bundle_precision(w2cs, intr, focal, extra, np.r_[cam, 0], np.r_[pt, 40],
                            np.vstack([xy, [[300.0, 200.0]]]))
    assert [p.rot_cov for p in more] == [p.rot_cov for p in base]
    with pytest.raises(ValueError, match="must agree"):
        bundle_precision(w2cs, intr[:2], focal, xyz, cam, pt, xy)
    with pytest.raises(ValueError, match="obs_xy"):
        bundle_precision(w2cs, intr, focal, xyz, cam, pt[:3], xy)
    with pytest.raises(ValueError, match="per camera"):
        bundle_precision(w2cs, intr, ["none"] * 4 + ["maybe"], xyz, cam, pt, xy)
    with pytest.raises(ValueError, match="obs_point the 40 points"):
        bundle_precision(w2cs, intr, focal, xyz, cam, pt + 1, xy)
    many = np.repeat(w2cs[:1], MAX_BUNDLE_PARAMS // 6 + 1, 0)
    with pytest.raises(ValueError, match="MAX_BUNDLE_PARAMS"):
        bundle_precision(many, np.repeat(intr[:1], len(many), 0), ["none"] * len(many), xyz,
                         cam, pt, xy)


def test_a_camera_tied_to_nothing_else_is_refused():
    """Two groups of cameras that share no point: 14 free directions, not 7."""
    from icomma_plugin.pose.precision import bundle_precision

    w2cs, intr, focal, xyz, cam, pt, xy = _bundle(n_cams=4)
    apart = (cam >= 2) & (pt < 20) | (cam < 2) & (pt >= 20)  # cameras 0-1 see 0-19, 2-3 20-39
    with pytest.raises(ValueError, match="not tied to the rest"):
        bundle_precision(w2cs, intr, ["none"] * 4, xyz, cam[~apart], pt[~apart], xy[~apart])
