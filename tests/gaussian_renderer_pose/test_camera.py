"""camera_matrices / projection_matrix: hand-built matrices, principal point, differentiability."""
from __future__ import annotations

import math

import pytest
import torch

from gaussian_renderer_pose import camera_matrices, projection_matrix
from gaussian_renderer_pose.reference.projection import preprocess
from tests.helpers.scenes import random_w2c

F64 = torch.float64


def graphdeco_projection(znear, zfar, fovX, fovY):
    """3DGS utils/graphics_utils.py::getProjectionMatrix, transcribed."""
    tanHalfFovY = math.tan(fovY / 2)
    tanHalfFovX = math.tan(fovX / 2)
    top = tanHalfFovY * znear
    bottom = -top
    right = tanHalfFovX * znear
    left = -right
    P = torch.zeros(4, 4, dtype=F64)
    z_sign = 1.0
    P[0, 0] = 2.0 * znear / (right - left)
    P[1, 1] = 2.0 * znear / (top - bottom)
    P[0, 2] = (right + left) / (right - left)
    P[1, 2] = (top + bottom) / (top - bottom)
    P[3, 2] = z_sign
    P[2, 2] = z_sign * zfar / (zfar - znear)
    P[2, 3] = -(zfar * znear) / (zfar - znear)
    return P


def test_matches_3dgs_camera():
    w2c = random_w2c(torch.Generator().manual_seed(0), dtype=F64)
    W, H, fx, fy = 64, 48, 55.0, 60.0
    cam = camera_matrices(w2c, fx, fy, W, H)
    fovx, fovy = 2 * math.atan(W / (2 * fx)), 2 * math.atan(H / (2 * fy))
    # 3DGS Camera: world_view_transform = W2C^T, full_proj = wvt @ P^T,
    # camera_center = inv(wvt)[3, :3]
    wvt = w2c.T
    proj = graphdeco_projection(0.01, 100.0, fovx, fovy).T
    torch.testing.assert_close(cam.viewmatrix, wvt)
    torch.testing.assert_close(cam.projmatrix, wvt @ proj)
    torch.testing.assert_close(cam.campos, torch.linalg.inv(wvt)[3, :3])
    assert cam.tanfovx == pytest.approx(math.tan(fovx / 2))
    assert cam.tanfovy == pytest.approx(math.tan(fovy / 2))
    torch.testing.assert_close(projection_matrix(cam.tanfovx, cam.tanfovy, dtype=F64),
                               graphdeco_projection(0.01, 100.0, fovx, fovy))
    assert cam.viewmatrix.dtype == F64 and cam.projmatrix.dtype == F64


@pytest.mark.parametrize("cx,cy", [(None, None), (20.25, 30.5), (40.0, 10.0)])
def test_principal_point_lands_at_fx_x_over_z_plus_cx(cx, cy):
    W, H, fx, fy = 64, 48, 55.0, 60.0
    w2c = random_w2c(torch.Generator().manual_seed(1), dtype=F64)
    cam = camera_matrices(w2c, fx, fy, W, H, cx, cy)
    ecx = (W - 1) / 2 if cx is None else cx
    ecy = (H - 1) / 2 if cy is None else cy
    x_cam = torch.tensor([[0.3, -0.2, 2.5], [-0.7, 0.4, 4.0], [0.0, 0.0, 1.0]], dtype=F64)
    c2w = torch.linalg.inv(w2c)
    m = x_cam @ c2w[:3, :3].T + c2w[:3, 3]
    # rasterizer projection (ndc2Pix of hom(m) @ projmatrix), through the reference preprocess
    proj = preprocess(
        m, None, torch.full((3, 1), 0.5, dtype=F64), torch.full((3, 3), 0.1, dtype=F64),
        torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64), None, cam.viewmatrix, cam.projmatrix,
        image_height=H, image_width=W, tanfovx=cam.tanfovx, tanfovy=cam.tanfovy, scale_modifier=1.0,
        antialiasing=False,
    )
    assert proj.ids.tolist() == [0, 1, 2]
    expected = torch.stack(
        [fx * x_cam[:, 0] / x_cam[:, 2] + ecx, fy * x_cam[:, 1] / x_cam[:, 2] + ecy], -1
    )
    # the 1e-7 in p_w moves pixels by ~1e-6
    torch.testing.assert_close(proj.xy, expected, rtol=1e-9, atol=1e-5)
    torch.testing.assert_close(proj.depth, x_cam[:, 2])


def test_offset_entries():
    W, H = 64, 48
    cam = camera_matrices(torch.eye(4, dtype=F64), 50.0, 50.0, W, H, cx=10.0, cy=40.0)
    P = cam.projmatrix.T  # w2c = I
    assert float(P[0, 2]) == pytest.approx((2 * 10.0 + 1 - W) / W)
    assert float(P[1, 2]) == pytest.approx((2 * 40.0 + 1 - H) / H)
    centred = camera_matrices(torch.eye(4, dtype=F64), 50.0, 50.0, W, H)
    assert float(centred.projmatrix[2, 0]) == 0.0 and float(centred.projmatrix[2, 1]) == 0.0


def test_gradcheck_wrt_w2c():
    w2c = random_w2c(torch.Generator().manual_seed(2), dtype=F64).requires_grad_(True)

    def fn(w):
        cam = camera_matrices(w, 40.0, 45.0, 32, 24, 14.0, 12.5)
        return cam.viewmatrix, cam.projmatrix, cam.campos

    assert torch.autograd.gradcheck(fn, (w2c,), eps=1e-6, atol=1e-7)


def test_float32_and_bad_arguments():
    cam = camera_matrices(torch.eye(4), 10.0, 10.0, 8, 6)
    assert cam.projmatrix.dtype == torch.float32
    with pytest.raises(ValueError, match="w2c"):
        camera_matrices(torch.eye(3), 10.0, 10.0, 8, 6)
    with pytest.raises(ValueError, match="fx"):
        camera_matrices(torch.eye(4), 0.0, 10.0, 8, 6)
    with pytest.raises(ValueError, match="height"):
        camera_matrices(torch.eye(4), 10.0, 10.0, 8, 0)
    with pytest.raises(ValueError, match="zfar"):
        projection_matrix(1.0, 1.0, znear=1.0, zfar=0.5)
