"""The photo's lens distortion estimated from its matches (``geometry.fit_pose_and_distortion``)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from icomma_plugin.camera import Intrinsics
from icomma_plugin.localization.geometry import (distort_normalised, distortion_shift_px,
                                                 fit_pose_and_distortion, project)
from icomma_plugin.pose.convert import look_at_c2w, perturb_pose, rotation_error_deg
from icomma_plugin.pose.se3 import se3_exp


def _distorted(X, w2c, intr, k):
    """Pixels of world points seen through OpenCV's model ``k`` (k1, k2, p1, p2) of ``intr``."""
    P = X @ w2c[:3, :3].T + w2c[:3, 3]
    xd = distort_normalised(P[:, :2] / P[:, 2:3], k)
    return np.stack([intr.fx * xd[:, 0] + intr.cx_px, intr.fy * xd[:, 1] + intr.cy_px], 1)


def test_distort_normalised_is_opencvs_model():
    import cv2

    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.6, 0.6, (50, 2))
    k = (0.06, -0.08, -0.001, 0.0002)
    pts = np.concatenate([xy, np.ones((50, 1))], 1)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.array(k))
    assert np.allclose(distort_normalised(xy, k), ref.reshape(-1, 2), atol=1e-12)


def _scene(seed):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.0, 1.0, (400, 3)) * [1.4, 1.4, 0.6]
    truth_c2w = look_at_c2w(np.array([0.4, -3.0, 0.8]), np.zeros(3))
    intr = Intrinsics(240, 180, 150.0, 150.0, 118.0, 92.0)
    return rng, X, truth_c2w, intr


def test_the_fit_recovers_a_known_radial_distortion():
    rng, X, truth_c2w, intr = _scene(5)
    k_true = (0.06, -0.08, -0.001, 0.0002)  # fox's phone, about
    x = _distorted(X, np.linalg.inv(truth_c2w), intr, k_true) + rng.normal(0.0, 0.1, (400, 2))
    inside = (x[:, 0] > 0) & (x[:, 0] < intr.width) & (x[:, 1] > 0) & (x[:, 1] < intr.height)
    X, x = X[inside], x[inside]
    start = np.linalg.inv(perturb_pose(truth_c2w, 0.5, 0.02, 5, pivot="camera"))
    free = fit_pose_and_distortion(X, x, start, intr, threshold_px=50.0)
    assert free.coefficients[0] == pytest.approx(k_true[0], abs=0.01)
    assert free.coefficients[1] == pytest.approx(k_true[1], abs=0.03)
    assert free.coefficients[2] == pytest.approx(k_true[2], abs=0.0005)
    assert free.coefficients[3] == pytest.approx(k_true[3], abs=0.0005)
    assert free.rms_px < 0.16 and free.median_px < 0.16
    assert rotation_error_deg(np.linalg.inv(free.w2c), truth_c2w) < 0.02
    # the pose alone takes up most of it (these k1, k2 act almost as a longer focal length over
    # the frame), with a pose further off and a larger residual
    fixed = fit_pose_and_distortion(X, x, start, intr, 50.0, terms=0, max_log_focal=0.0)
    assert fixed.coefficients == (0.0,) * 4 and fixed.focal_scale == 1.0
    assert fixed.rms_px > 1.15 * free.rms_px
    assert free.focal_scale == pytest.approx(1.0, abs=0.003)
    def centre_off(w2c):
        return np.linalg.norm(np.linalg.inv(w2c)[:3, 3] - truth_c2w[:3, 3])

    assert centre_off(fixed.w2c) > 3.0 * centre_off(free.w2c)
    # what the distortion does within the points' reach, in pixels, the same from either fit
    assert free.max_radius == pytest.approx(np.hypot(*((x - [118, 92]) / 150).T).max(), rel=0.2)
    shift = distortion_shift_px(free.coefficients, free.max_radius, intr.fx)
    assert shift == pytest.approx(distortion_shift_px(k_true, free.max_radius, intr.fx), rel=0.15)
    assert shift > 1.0
    assert fit_pose_and_distortion(X[:5], x[:5], start, intr, 50.0) is None  # too few


def test_a_pinhole_photo_fits_no_distortion():
    rng, X, truth_c2w, intr = _scene(6)
    x, _ = project(X, np.linalg.inv(truth_c2w), intr)
    x = x + rng.normal(0.0, 0.3, x.shape)
    start = np.linalg.inv(perturb_pose(truth_c2w, 0.3, 0.01, 2, pivot="camera"))
    free = fit_pose_and_distortion(X, x, start, intr, threshold_px=50.0)
    fixed = fit_pose_and_distortion(X, x, start, intr, threshold_px=50.0, terms=0,
                                    max_log_focal=0.0)
    assert distortion_shift_px(free.coefficients, free.max_radius, intr.fx) < 0.3
    assert free.rms_px > 0.97 * fixed.rms_px  # five more parameters explain little of the noise


def test_a_focal_length_off_is_not_taken_for_a_distortion():
    """Pinhole photos from a camera 6 % longer than given: the focal length takes it up."""
    rng, X, truth_c2w, intr = _scene(9)
    x, _ = project(X, np.linalg.inv(truth_c2w), intr.with_focal_scale(1.06))
    x = x + rng.normal(0.0, 0.1, x.shape)
    start = np.linalg.inv(perturb_pose(truth_c2w, 0.3, 0.01, 3, pivot="camera"))
    free = fit_pose_and_distortion(X, x, start, intr, threshold_px=50.0)
    assert free.focal_scale == pytest.approx(1.06, abs=0.005)
    assert distortion_shift_px(free.coefficients, free.max_radius, intr.fx) < 0.2


def test_the_distortion_fit_ends_where_the_reprojection_error_is_stationary():
    """Finite differences of the cost the fit minimises vanish at its result (Jacobian check)."""
    rng, X, truth_c2w, intr = _scene(7)
    k_true = (-0.1, 0.05, 0.002, -0.001)
    x = _distorted(X, np.linalg.inv(truth_c2w), intr, k_true) + rng.normal(0, 0.3, (400, 2))
    start = np.linalg.inv(perturb_pose(truth_c2w, 1.0, 0.05, 8, pivot="camera"))

    def cost(w2c, k, s, p):  # steps of the twist, the log focal scale and the coefficients
        T = se3_exp(torch.as_tensor(p[:6], dtype=torch.float64)).numpy() @ w2c
        cam = intr.with_focal_scale(s * np.exp(p[6]))
        return float(((_distorted(X, T, cam, np.asarray(k) + p[7:]) - x) ** 2).sum())

    def grad(w2c, k, s):
        g = np.empty(11)
        for j in range(11):
            e = np.zeros(11)
            e[j] = 1e-6
            g[j] = (cost(w2c, k, s, e) - cost(w2c, k, s, -e)) / 2e-6
        return g

    g_start = grad(start, (0.0,) * 4, 1.0)
    fit = fit_pose_and_distortion(X, x, start, intr, threshold_px=1e3)
    g_end = grad(fit.w2c, fit.coefficients, fit.focal_scale)
    assert np.abs(g_end).max() < 1e-4 * np.abs(g_start).max(), (g_start, g_end)
    assert distortion_shift_px(fit.coefficients, fit.max_radius, intr.fx) == pytest.approx(
        distortion_shift_px(k_true, fit.max_radius, intr.fx), rel=0.1)


def test_the_distortion_fit_names_a_wrong_argument():
    _, X, truth_c2w, intr = _scene(8)
    with pytest.raises(ValueError, match="terms must be 0, 1, 2 or 4"):
        fit_pose_and_distortion(X, X[:, :2], np.linalg.inv(truth_c2w), intr, 1.0, terms=3)


def test_a_localization_records_the_lens_check_unless_asked_not_to(demo, xfeat):
    """``signals.distortion`` of the demo's own pinhole query: small.

    None with ``lens_check`` off (tracking's fast mode).
    """
    from icomma_plugin.localization.robust import RobustConfig
    from icomma_plugin.localization.types import Query
    from icomma_plugin.localize import localize

    scene, model, cams = demo
    init = perturb_pose(scene.gt_c2w, 5.0, 0.02, 3, pivot="camera")
    out = {}
    for on in (True, False):
        out[on] = localize(model, Query(scene.load_query(), scene.intrinsics), matcher=xfeat,
                           init_c2w=init, gt_c2w=scene.gt_c2w, cameras=[e.c2w for e in cams],
                           cache_dir=False, config=RobustConfig(lens_check=on))
    sig = out[True].verdict.signals["distortion"]
    assert set(sig) == {"coefficients", "shift_px", "reach", "focal_px", "rms_px",
                        "rms_px_given", "centre"}  # (the demo's camera has no principal point)
    assert len(sig["coefficients"]) == 4 and 0.0 < sig["reach"] < 1.0
    assert sig["coefficients"][2:] == [0.0, 0.0]  # radial alone beside the principal point
    assert np.abs(sig["centre"]).max() < 0.01  # it is the image centre
    assert sig["focal_px"] == pytest.approx(scene.intrinsics.fx, rel=1e-3)
    assert sig["rms_px"] <= sig["rms_px_given"] and sig["shift_px"] < 1.0
    assert "distortion" not in out[False].verdict.signals
    assert np.allclose(out[True].c2w, out[False].c2w)  # a signal: the pose is the same


def test_the_principal_points_move_is_found_from_the_second_order_terms():
    """A photo whose principal point is 3.6 and 1.3 px off the image centre it was given.

    A turn makes up for the move to first order; with k1, k2 beside it the fit finds it to a few
    tenths of a pixel a photo (their median over ten photos within 0.2 px).
    """
    found = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        X = rng.uniform(-1.0, 1.0, (500, 3)) * [1.5, 1.5, 1.0]
        truth_c2w = look_at_c2w(np.array([0.4, -3.0, 0.8]), np.zeros(3))
        given = Intrinsics(270, 480, 344.0, 344.0)  # the centre taken
        true = Intrinsics(270, 480, 344.0, 344.0, given.cx_px + 3.6, given.cy_px + 1.3)
        x, _ = project(X, np.linalg.inv(truth_c2w), true)
        x = x + rng.normal(0.0, 0.3, x.shape)
        inside = (x[:, 0] > 0) & (x[:, 0] < 270) & (x[:, 1] > 0) & (x[:, 1] < 480)
        start = np.linalg.inv(perturb_pose(truth_c2w, 0.3, 0.01, seed, pivot="camera"))
        fit = fit_pose_and_distortion(X[inside], x[inside], start, given, 50.0, terms=2,
                                      centre=True)
        found.append(fit.centre_px)
        assert distortion_shift_px(fit.coefficients, fit.max_radius, 344.0) < 0.5
    found = np.array(found)
    assert np.median(found, axis=0) == pytest.approx([3.6, 1.3], abs=0.2)
    assert found.std(axis=0).max() < 0.6
