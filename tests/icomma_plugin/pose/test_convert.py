import math

import numpy as np
import pytest
import torch

from icomma_plugin.pose.convert import (
    invert_rigid,
    look_at_c2w,
    opencv_to_opengl_c2w,
    opengl_to_opencv_c2w,
    perturb_pose,
    random_rotation_about_axis,
    rotation_about_axis,
    rotation_error_deg,
    translation_error,
)
from icomma_plugin.pose.se3 import se3_exp


def _random_rigid(seed=0, n=None):
    xi = torch.randn(*(() if n is None else (n,)), 6, generator=torch.Generator().manual_seed(seed),
                     dtype=torch.float64)
    return se3_exp(xi).numpy()


def test_invert_rigid_numpy_and_torch():
    # Against two independent constructions: the general matrix inverse, and exp(-xi) for
    # T = exp(xi) (batched, float64).
    xi = torch.randn(2, 3, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    T = se3_exp(xi)
    assert torch.allclose(invert_rigid(T), se3_exp(-xi), atol=1e-12)
    assert torch.allclose(invert_rigid(T) @ T, torch.eye(4, dtype=torch.float64).expand(2, 3, 4, 4))
    Tn = _random_rigid(0, 5)
    assert np.allclose(invert_rigid(Tn), np.linalg.inv(Tn), atol=1e-12)
    assert isinstance(invert_rigid(Tn), np.ndarray)
    Tt = torch.from_numpy(Tn).float().requires_grad_()
    inv = invert_rigid(Tt)
    assert inv.dtype == torch.float32
    assert torch.allclose(inv @ Tt, torch.eye(4).expand(5, 4, 4), atol=1e-5)
    inv.sum().backward()
    assert torch.isfinite(Tt.grad).all()


def test_camera_looking_at_origin_opencv():
    # Camera at (0,0,-4) with axes aligned to the world (x right, y down, z forward) sees the
    # origin 4 units straight ahead.
    c2w = np.eye(4)
    c2w[:3, 3] = [0, 0, -4]
    w2c = invert_rigid(c2w)
    assert np.allclose(w2c @ [0, 0, 0, 1], [0, 0, 4, 1])
    # The same pose from look_at with world "up" = -y: image y points along +y (down).
    la = look_at_c2w([0, 0, -4], [0, 0, 0], up=[0, -1, 0])
    assert np.allclose(la, c2w)
    # A world point at +x is to the right of the image centre.
    x_cam = w2c @ [1, 0, 0, 1]
    assert x_cam[0] > 0 and x_cam[2] > 0


def test_look_at_general():
    c2w = look_at_c2w([3.0, -2.0, 1.5], [0.1, 0.2, -0.3], up=[0, 0, 1])
    R = c2w[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    x_cam = invert_rigid(c2w) @ [0.1, 0.2, -0.3, 1]
    assert np.allclose(x_cam[:2], 0, atol=1e-12) and x_cam[2] > 0
    # World up (+z) appears towards the top of the image (negative camera y).
    up_cam = R.T @ [0, 0, 1]
    assert up_cam[1] < 0
    with pytest.raises(ValueError, match="parallel"):
        look_at_c2w([0, 0, 5], [0, 0, 0], up=[0, 0, 1])


def test_opengl_blender_pose_converted():
    # Blender/NeRF camera at (0,0,4) with identity rotation looks down -z with y up.
    c2w_gl = np.eye(4)
    c2w_gl[:3, 3] = [0, 0, 4]
    c2w_cv = opengl_to_opencv_c2w(c2w_gl)
    assert np.allclose(c2w_cv[:3, :3], np.diag([1.0, -1.0, -1.0]))
    assert np.allclose(c2w_cv[:3, 3], [0, 0, 4])
    w2c = invert_rigid(c2w_cv)
    assert np.allclose(w2c @ [0, 0, 0, 1], [0, 0, 4, 1])  # origin in front, on the axis
    assert (w2c @ [0, 1, 0, 1])[1] < 0  # world +y (Blender up here) is up in the image
    assert np.allclose(opencv_to_opengl_c2w(c2w_cv), c2w_gl)
    assert c2w_gl[1, 1] == 1.0  # input untouched
    # Same as 3DGS readCamerasFromTransforms (c2w[:3, 1:3] *= -1), torch too.
    T = _random_rigid(3)
    ref = T.copy()
    ref[:3, 1:3] *= -1
    assert np.allclose(opengl_to_opencv_c2w(T), ref)
    assert torch.allclose(opengl_to_opencv_c2w(torch.from_numpy(T)), torch.from_numpy(ref))


def test_rotation_error_known():
    Rz30 = rotation_about_axis([0, 0, 1], 30.0)
    assert np.isclose(Rz30[0, 0], math.cos(math.radians(30)))
    assert np.isclose(rotation_error_deg(Rz30, np.eye(3)), 30.0)
    T1 = _random_rigid(1)
    T2 = T1.copy()
    T2[:3, :3] = rotation_about_axis([1, 2, 3], 7.5) @ T1[:3, :3]
    assert np.isclose(float(rotation_error_deg(T2, T1)), 7.5, atol=1e-9)
    # Same angle whether both are c2w or both w2c.
    assert np.isclose(float(rotation_error_deg(invert_rigid(T2), invert_rigid(T1))), 7.5, atol=1e-9)
    R180 = rotation_about_axis([0, 1, 0], 180)
    assert np.isclose(float(rotation_error_deg(R180, np.eye(3))), 180)
    assert float(rotation_error_deg(T1, T1)) < 1e-5
    batch = np.stack([rotation_about_axis([0, 0, 1], a) for a in (0, 10, 90)])
    assert np.allclose(rotation_error_deg(batch, np.eye(3)), [0, 10, 90], atol=1e-6)
    out = rotation_error_deg(torch.from_numpy(batch).float(), torch.eye(3))
    assert isinstance(out, torch.Tensor) and out.dtype == torch.float64
    assert torch.allclose(out, torch.tensor([0.0, 10, 90], dtype=torch.float64), atol=0.05)


def test_translation_error_is_camera_centre_distance():
    a, b = np.eye(4), np.eye(4)
    a[:3, 3] = [1, 2, 3]
    b[:3, 3] = [1, 2, 5]
    b[:3, :3] = rotation_about_axis([1, 0, 0], 40)  # rotation must not matter
    assert np.isclose(translation_error(a, b), 2.0)
    assert torch.isclose(translation_error(torch.from_numpy(a), torch.from_numpy(b)),
                         torch.tensor(2.0, dtype=torch.float64))
    with pytest.raises(ValueError, match="c2w_est"):
        translation_error(np.eye(3), b)


@pytest.mark.parametrize("rot_deg", [0.0, 5.0, 30.0, 120.0])
def test_perturb_pose_exact_angle_and_distance(rot_deg):
    c2w = _random_rigid(2)
    out = perturb_pose(c2w, rot_deg, 0.25, np.random.default_rng(1))
    assert out.shape == (4, 4) and out.dtype == np.float64
    assert np.isclose(float(rotation_error_deg(out, c2w)), rot_deg, atol=1e-9)
    assert np.isclose(float(translation_error(out, c2w)), 0.25, atol=1e-12)
    R = out[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_perturb_pose_rotates_about_camera_centre():
    c2w = _random_rigid(4)
    out = perturb_pose(c2w, 20.0, 0.0, 0)
    assert np.allclose(out[:3, 3], c2w[:3, 3])
    assert np.isclose(float(rotation_error_deg(out, c2w)), 20.0)


def test_perturb_pose_per_axis_and_generators():
    c2w = _random_rigid(5)
    outs = np.stack([perturb_pose(c2w, 1.0, [0.1, 0.0, 0.3], s) for s in range(200)])
    d = outs[:, :3, 3] - c2w[:3, 3]
    assert np.all(np.abs(d[:, 0]) <= 0.1) and np.all(np.abs(d[:, 2]) <= 0.3)
    assert np.all(d[:, 1] == 0)
    assert np.abs(d[:, 0]).max() > 0.05  # actually spread over the range
    # Same seed -> same pose; torch in -> torch out with the same dtype.
    assert np.array_equal(perturb_pose(c2w, 10, 0.1, 7), perturb_pose(c2w, 10, 0.1, 7))
    t = torch.from_numpy(c2w).float()
    a = perturb_pose(t, 10, 0.1, torch.Generator().manual_seed(3))
    b = perturb_pose(t, 10, 0.1, torch.Generator().manual_seed(3))
    assert a.dtype == torch.float32 and torch.equal(a, b)
    assert abs(float(rotation_error_deg(a, t)) - 10) < 0.05
    batch = perturb_pose(np.stack([c2w, c2w]), 15, 0.2, 0)
    assert batch.shape == (2, 4, 4) and not np.allclose(batch[0], batch[1])
    assert np.allclose(rotation_error_deg(batch, c2w), 15)


def test_random_axis_is_uniform_ish():
    rng = np.random.default_rng(0)
    axes = []
    for _ in range(300):
        R = random_rotation_about_axis(90.0, rng)
        w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
        axes.append(w / np.linalg.norm(w))
        assert np.isclose(float(rotation_error_deg(R, np.eye(3))), 90.0)
    assert np.all(np.abs(np.mean(axes, 0)) < 0.15)
    fixed = random_rotation_about_axis(45.0, axis=[0, 0, 2])
    assert np.allclose(fixed, rotation_about_axis([0, 0, 1], 45.0))


def test_bad_inputs():
    with pytest.raises(ValueError, match="trans"):
        perturb_pose(np.eye(4), 5, -1.0, 0)
    with pytest.raises(ValueError, match="trans"):
        perturb_pose(np.eye(4), 5, [1, 2], 0)
    with pytest.raises(ValueError, match="c2w"):
        perturb_pose(np.eye(3), 5, 0.1, 0)
    with pytest.raises(ValueError, match="generator"):
        perturb_pose(np.eye(4), 5, 0.1, "seed")
    with pytest.raises(ValueError, match="axis"):
        rotation_about_axis([0, 0, 0], 10)


def test_perturb_pose_origin_pivot_orbits_and_keeps_angle():
    import numpy as np

    from icomma_plugin.pose.convert import look_at_c2w, perturb_pose, rotation_error_deg

    c2w = look_at_c2w(np.array([0.0, -4.0, 1.0]), np.zeros(3))
    out = perturb_pose(c2w, 30.0, 0.0, generator=3, pivot="origin")
    assert abs(rotation_error_deg(out, c2w) - 30.0) < 1e-6
    # Orbiting about the origin keeps the distance to it and the origin stays on the optical axis.
    assert abs(np.linalg.norm(out[:3, 3]) - np.linalg.norm(c2w[:3, 3])) < 1e-9
    origin_cam = np.linalg.inv(out) @ np.array([0.0, 0.0, 0.0, 1.0])
    assert abs(origin_cam[0]) < 1e-9 and abs(origin_cam[1]) < 1e-9 and origin_cam[2] > 0


def test_perturb_pose_rejects_bad_pivot():
    import numpy as np
    import pytest

    from icomma_plugin.pose.convert import perturb_pose

    with pytest.raises(ValueError, match="pivot"):
        perturb_pose(np.eye(4), 10.0, 0.0, pivot="centre")


def test_rotation_error_is_well_conditioned_near_zero_and_on_float32_rotations():
    """Small angles are resolved, and float32-orthonormal rotations read as 0 off themselves.

    arccos would lose the small angles; a rotation that is orthonormal only to float32 precision
    (NeRF-synthetic's matrices) does not read as 0.03 deg off itself.
    """
    R = _random_rigid(7)[:3, :3]
    for deg in (1e-7, 1e-4, 0.01):
        ref = np.vstack([np.hstack([R, np.zeros((3, 1))]), [0, 0, 0, 1]])
        out = perturb_pose(ref, deg, 0.0, 3)
        assert float(rotation_error_deg(out, out)) == 0.0
        assert np.isclose(float(rotation_error_deg(out, ref)), deg, rtol=1e-6, atol=1e-12)
    R32 = R.astype(np.float32).astype(np.float64) * (1 - 2e-7)  # slightly off SO(3)
    assert float(rotation_error_deg(R32, R)) < 1e-4
    flip = R @ np.diag([1.0, -1.0, -1.0])  # a half turn about the camera's x axis
    assert np.isclose(float(rotation_error_deg(flip, R)), 180.0)


def test_same_pose_mask_agrees_with_same_pose():
    """The vectorised test gives `same_pose` of each pose, near the tolerance too."""
    from icomma_plugin.pose.convert import SAME_POSE_ATOL, same_pose, same_pose_mask

    ref = np.eye(4)
    ref[:3, 3] = [0.1, 0.2, 0.3]
    c2ws = np.repeat(ref[None], 6, axis=0)
    c2ws[1, 0, 3] += 0.5 * SAME_POSE_ATOL  # within
    c2ws[2, 1, 3] += 3.0 * SAME_POSE_ATOL  # beyond (plus the relative 1e-5 of 0.2)
    c2ws[3, 0, 1] += 1e-3
    c2ws[4] = np.eye(4)
    mask = same_pose_mask(c2ws, ref)
    assert mask.dtype == bool and mask.shape == (6,)
    assert mask.tolist() == [same_pose(c, ref) for c in c2ws] == [True, True, False, False, False,
                                                                  True]
    assert same_pose_mask(np.zeros((0, 4, 4)), ref).shape == (0,)


def test_same_as_any_mask_is_same_pose_of_every_pair():
    from icomma_plugin.pose.convert import SAME_POSE_ATOL, same_as_any_mask, same_pose

    rng = np.random.default_rng(4)
    others = [np.eye(4) for _ in range(3)]
    for o in others:
        o[:3, 3] = rng.normal(size=3)
    c2ws = [others[1].copy(), others[2] + 0.5 * SAME_POSE_ATOL, others[0] + 3 * SAME_POSE_ATOL,
            np.eye(4)]
    want = [any(same_pose(c, o) for o in others) for c in c2ws]
    assert same_as_any_mask(c2ws, others).tolist() == want == [True, True, False, False]
    assert same_as_any_mask([], others).shape == (0,)
    assert not same_as_any_mask(c2ws, []).any()
