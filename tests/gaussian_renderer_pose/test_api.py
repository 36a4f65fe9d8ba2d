"""Drop-in API of gaussian_renderer_pose vs graphdeco diff-gaussian-rasterization.

Upstream: its late-2024 main.
"""
from __future__ import annotations

import math
import warnings

import pytest
import torch

import gaussian_renderer_pose as grp
from gaussian_renderer_pose import (
    GaussianRasterizationSettings,
    GaussianRasterizer,
    RasterOutput,
    available_backends,
    rasterize_gaussians,
)
from gaussian_renderer_pose import _dispatch
from tests.helpers.paths import REPO
from tests.helpers.scenes import make_scene

UPSTREAM_FIELDS = (
    "image_height", "image_width", "tanfovx", "tanfovy", "bg", "scale_modifier", "viewmatrix",
    "projmatrix", "sh_degree", "campos", "prefiltered", "debug",
)


def test_public_names():
    assert set(grp.__all__) == {
        "GaussianRasterizationSettings",
        "GaussianRasterizer",
        "rasterize_gaussians",
        "RasterOutput",
        "camera_matrices",
        "CameraMatrices",
        "projection_matrix",
        "available_backends",
    }
    for name in grp.__all__:
        assert hasattr(grp, name)


def test_settings_fields_and_defaults():
    assert GaussianRasterizationSettings._fields == UPSTREAM_FIELDS + ("antialiasing", "backend")
    assert GaussianRasterizationSettings._field_defaults == {
        "antialiasing": False,
        "backend": "auto",
    }
    # positional construction exactly as upstream (12 and 13 fields)
    s = make_scene(3)
    st = s.settings()
    st12 = GaussianRasterizationSettings(*st[:12])
    assert st12.antialiasing is False and st12.backend == "auto"
    st13 = GaussianRasterizationSettings(*st[:12], True)
    assert st13.antialiasing is True


def test_forward_returns_upstream_triple():
    s = make_scene(30)
    r = GaussianRasterizer(s.settings("reference"))
    out = r(s.means3D, s.means2D, s.opacities, shs=s.shs, scales=s.scales, rotations=s.rotations)
    assert isinstance(out, tuple) and len(out) == 3
    color, radii, invdepth = out
    assert color.shape == (3, 48, 64) and color.dtype == torch.float32
    assert radii.shape == (30,) and radii.dtype == torch.int32
    assert invdepth.shape == (1, 48, 64) and invdepth.dtype == torch.float32
    full = rasterize_gaussians(settings=s.settings("reference"), **s.inputs())
    assert isinstance(full, RasterOutput)
    torch.testing.assert_close(full.color, color, rtol=0, atol=0)
    torch.testing.assert_close(full.invdepth, invdepth, rtol=0, atol=0)
    assert torch.equal(full.radii, radii)
    # behind/near Gaussians have radius 0
    cat = s.extras["category"]
    assert int(radii[cat == 2].abs().sum()) == 0 and int((radii > 0).sum()) > 0


def test_depth_and_alpha_outputs():
    s = make_scene(40, dtype=torch.float64)
    from gaussian_renderer_pose.reference import rasterize_gaussians_reference

    out = rasterize_gaussians(settings=s.settings("reference"), **s.inputs())
    assert out.depth.shape == out.alpha.shape == (1, 48, 64)
    assert float(out.alpha.min()) >= 0 and float(out.alpha.max()) <= 1
    covered = out.alpha > 1e-6
    assert bool(covered.any()) and bool((~covered).any())  # the scene leaves some background
    st = s.settings("reference")
    from gaussian_renderer_pose.camera import camera_matrices  # noqa: F401

    _, _, _, depth_acc, _ = rasterize_gaussians_reference(
        s.means3D,
        s.means2D,
        s.opacities,
        s.shs,
        None,
        s.scales,
        s.rotations,
        None,
        s.bg,
        st.viewmatrix,
        st.projmatrix,
        st.campos,
        image_height=48,
        image_width=64,
        tanfovx=st.tanfovx,
        tanfovy=st.tanfovy,
        scale_modifier=1.0,
        sh_degree=3,
        prefiltered=False,
        antialiasing=False,
    )
    torch.testing.assert_close(out.depth[covered], (depth_acc / out.alpha)[covered])
    assert float(out.depth[~covered].abs().max()) == 0.0
    # background shows where nothing is drawn
    torch.testing.assert_close(
        out.color[:, ~covered[0]], s.bg[:, None].expand(3, int((~covered).sum()))
    )


def test_xor_rules():
    s = make_scene(5)
    r = GaussianRasterizer(s.settings("reference"))
    cols = torch.rand(5, 3)
    with pytest.raises(ValueError, match="exactly one of either SHs"):
        r(
            s.means3D,
            s.means2D,
            s.opacities,
            shs=s.shs,
            colors_precomp=cols,
            scales=s.scales,
            rotations=s.rotations,
        )
    with pytest.raises(ValueError, match="exactly one of either SHs"):
        r(s.means3D, s.means2D, s.opacities, scales=s.scales, rotations=s.rotations)
    with pytest.raises(ValueError, match="scale/rotation pair"):
        r(s.means3D, s.means2D, s.opacities, shs=s.shs, scales=s.scales)
    with pytest.raises(ValueError, match="scale/rotation pair"):
        r(s.means3D, s.means2D, s.opacities, shs=s.shs, scales=s.scales, rotations=s.rotations,
          cov3D_precomp=torch.rand(5, 6))
    with pytest.raises(ValueError, match="scale/rotation pair"):
        r(s.means3D, s.means2D, s.opacities, shs=s.shs)
    # the functional API enforces the same rules
    with pytest.raises(
        ValueError, match="exactly one of shs / colors_precomp must be given, got both"
    ):
        rasterize_gaussians(
            settings=s.settings("reference"), **{**s.inputs(), "colors_precomp": cols}
        )
    with pytest.raises(
        ValueError, match="scales and rotations must be given together, got rotations=None"
    ):
        rasterize_gaussians(settings=s.settings("reference"), **{**s.inputs(), "rotations": None})


def test_empty_tensors_mean_absent():
    s = make_scene(8, colors="precomp", covariance="precomp")
    r = GaussianRasterizer(s.settings("reference"))
    empty = torch.Tensor([])
    a = r(
        s.means3D,
        s.means2D,
        s.opacities,
        shs=empty,
        colors_precomp=s.colors_precomp,
        scales=empty,
        rotations=empty,
        cov3D_precomp=s.cov3D_precomp,
    )
    b = r(
        s.means3D,
        s.means2D,
        s.opacities,
        colors_precomp=s.colors_precomp,
        cov3D_precomp=s.cov3D_precomp,
    )
    torch.testing.assert_close(a[0], b[0], rtol=0, atol=0)
    # means2D may be empty / None too
    c = r(
        s.means3D,
        empty,
        s.opacities,
        colors_precomp=s.colors_precomp,
        cov3D_precomp=s.cov3D_precomp,
    )
    torch.testing.assert_close(a[0], c[0], rtol=0, atol=0)


def test_mark_visible():
    s = make_scene(50)
    r = GaussianRasterizer(s.settings("reference"))
    pos = s.means3D.clone().requires_grad_(True)
    vis = r.markVisible(pos)
    assert vis.dtype == torch.bool and vis.shape == (50,) and not vis.requires_grad
    z = (s.w2c[:3, :3] @ s.means3D.T + s.w2c[:3, 3:]).T[:, 2]
    assert torch.equal(vis, z > 0.2)
    assert not bool(vis[s.extras["category"] == 2].any())


def test_opacities_flat_accepted():
    s = make_scene(10)
    a = rasterize_gaussians(settings=s.settings("reference"), **s.inputs())
    b = rasterize_gaussians(
        settings=s.settings("reference"), **{**s.inputs(), "opacities": s.opacities[:, 0]}
    )
    torch.testing.assert_close(a.color, b.color, rtol=0, atol=0)


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_zero_gaussians(backend):
    s = make_scene(0)
    leaf = s.means3D.clone().requires_grad_(True)
    bg = s.bg.clone().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = rasterize_gaussians(
            settings=s.settings(backend)._replace(bg=bg), **{**s.inputs(), "means3D": leaf}
        )
    assert out.radii.shape == (0,) and out.radii.dtype == torch.int32
    torch.testing.assert_close(out.color, s.bg[:, None, None].expand(3, 48, 64))
    assert (
        float(out.alpha.detach().abs().max()) == 0 and float(out.invdepth.detach().abs().max()) == 0
    )
    out.color.sum().backward()
    torch.testing.assert_close(bg.grad, torch.full((3,), 48.0 * 64.0))


# ---------------------------------------------------------------------------------------------
# A mock of the 3DGS codebase's gaussian_renderer.render(), with only the import changed.
# ---------------------------------------------------------------------------------------------

class MockGaussianModel:
    """The bits of 3DGS's GaussianModel that render() touches (activations applied in getters)."""

    def __init__(self, scene):
        self.active_sh_degree = 3
        self._xyz = scene.means3D.clone().requires_grad_(True)
        self._features_dc = scene.shs[:, :1].clone().requires_grad_(True)
        self._features_rest = scene.shs[:, 1:].clone().requires_grad_(True)
        self._opacity = torch.logit(scene.opacities).clone().requires_grad_(True)
        self._scaling = torch.log(scene.scales).clone().requires_grad_(True)
        self._rotation = scene.rotations.clone().requires_grad_(True)

    get_xyz = property(lambda self: self._xyz)
    get_features = property(lambda self: torch.cat((self._features_dc, self._features_rest), dim=1))
    get_opacity = property(lambda self: torch.sigmoid(self._opacity))
    get_scaling = property(lambda self: torch.exp(self._scaling))
    get_rotation = property(lambda self: torch.nn.functional.normalize(self._rotation))


class MockCamera:
    def __init__(self, scene):
        from gaussian_renderer_pose import camera_matrices

        cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
        self.image_height, self.image_width = scene.height, scene.width
        self.FoVx = 2 * math.atan(cam.tanfovx)
        self.FoVy = 2 * math.atan(cam.tanfovy)
        self.world_view_transform = cam.viewmatrix
        self.full_proj_transform = cam.projmatrix
        self.camera_center = cam.campos


def render_like_3dgs(viewpoint_camera, pc, bg_color, scaling_modifier=1.0, antialiasing=False):
    """Structure of graphdeco gaussian_renderer.render (late 2024).

    The shs are evaluated by the rasterizer.
    """
    # from diff_gaussian_rasterization import ... -> the only change:
    from gaussian_renderer_pose import GaussianRasterizationSettings, GaussianRasterizer

    screenspace_points = (
        torch.zeros_like(pc.get_xyz, dtype=pc.get_xyz.dtype, requires_grad=True) + 0
    )
    screenspace_points.retain_grad()
    tanfovx = math.tan(viewpoint_camera.FoVx * 0.5)
    tanfovy = math.tan(viewpoint_camera.FoVy * 0.5)
    raster_settings = GaussianRasterizationSettings(
        image_height=int(viewpoint_camera.image_height),
        image_width=int(viewpoint_camera.image_width),
        tanfovx=tanfovx,
        tanfovy=tanfovy,
        bg=bg_color,
        scale_modifier=scaling_modifier,
        viewmatrix=viewpoint_camera.world_view_transform,
        projmatrix=viewpoint_camera.full_proj_transform,
        sh_degree=pc.active_sh_degree,
        campos=viewpoint_camera.camera_center,
        prefiltered=False,
        debug=False,
        antialiasing=antialiasing,
    )
    rasterizer = GaussianRasterizer(raster_settings=raster_settings)
    means3D = pc.get_xyz
    means2D = screenspace_points
    opacity = pc.get_opacity
    scales = pc.get_scaling
    rotations = pc.get_rotation
    shs = pc.get_features
    rendered_image, radii, depth_image = rasterizer(
        means3D=means3D, means2D=means2D, shs=shs, colors_precomp=None, opacities=opacity,
        scales=scales, rotations=rotations, cov3D_precomp=None,
    )
    rendered_image = rendered_image.clamp(0, 1)
    return {
        "render": rendered_image,
        "viewspace_points": screenspace_points,
        "visibility_filter": (radii > 0).nonzero(),
        "radii": radii,
        "depth": depth_image,
    }


@pytest.mark.parametrize(
    "antialiasing,backend", [(False, "reference"), (True, "reference"), (True, "auto")]
)
def test_3dgs_render_training_step(antialiasing, backend, monkeypatch):
    """The 3DGS render() (import changed only) runs forward + backward with training inputs.

    backend 'auto' exercises the native kernel where it is built (else the reference).
    """
    if backend == "reference":
        monkeypatch.setenv(_dispatch.ENV_VAR, "reference")
    else:
        monkeypatch.delenv(_dispatch.ENV_VAR, raising=False)
        warnings.simplefilter("ignore", _dispatch.BackendFallbackWarning)
    s = make_scene(60, height=32, width=40, seed=4)
    pc = MockGaussianModel(s)
    out = render_like_3dgs(
        MockCamera(s), pc, torch.tensor([0.0, 0.0, 0.0]), antialiasing=antialiasing
    )
    gt = torch.rand(3, 32, 40, generator=torch.Generator().manual_seed(0))
    loss = (out["render"] - gt).abs().mean() + 0.1 * out["depth"].mean()
    loss.backward()
    vis = out["visibility_filter"]
    assert vis.shape[1] == 1 and vis.numel() > 0
    g2d = out["viewspace_points"].grad
    assert g2d is not None and g2d.shape == (60, 3)
    # densification statistic of 3DGS: norm of the 2D gradient of visible points
    stat = torch.norm(g2d[vis[:, 0], :2], dim=-1)
    assert float(stat.max()) > 0
    invisible = out["radii"] == 0
    assert float(g2d[invisible].abs().max()) == 0.0
    for name in ("_xyz", "_features_dc", "_features_rest", "_opacity", "_scaling", "_rotation"):
        g = getattr(pc, name).grad
        assert g is not None and bool(torch.isfinite(g).all()) and float(g.abs().max()) > 0, name


# ---------------------------------------------------------------------------------------------
# Backend selection
# ---------------------------------------------------------------------------------------------

def test_available_backends():
    av = available_backends()
    assert set(av) == {"reference", "cpu", "cuda"}
    assert av["reference"] is None
    for k in ("cpu", "cuda"):
        assert av[k] is None or (isinstance(av[k], str) and av[k])


@pytest.fixture
def native_missing(monkeypatch):
    """Pretend the native backends are unavailable (whatever is built here)."""
    monkeypatch.delenv(_dispatch.ENV_VAR, raising=False)
    monkeypatch.setattr(_dispatch, "_warned", set())
    monkeypatch.setattr(_dispatch, "_native_reason", lambda kind: f"pretend {kind} is not built")


def test_explicit_unavailable_backend_raises(native_missing):
    s = make_scene(4)
    with pytest.raises(
        RuntimeError, match="backend 'cpu' requested but unavailable: pretend cpu is not built"
    ):
        rasterize_gaussians(settings=s.settings("cpu"), **s.inputs())
    with pytest.raises(
        RuntimeError, match="backend 'cuda' requested but the inputs are on device 'cpu'"
    ):
        rasterize_gaussians(settings=s.settings("cuda"), **s.inputs())
    assert available_backends()["cpu"] == "pretend cpu is not built"


def test_auto_warns_once_and_falls_back(native_missing):
    s = make_scene(6)
    with pytest.warns(
        _dispatch.BackendFallbackWarning, match="reference backend because .*native cpu backend"
    ) as rec:
        a = rasterize_gaussians(settings=s.settings("auto"), **s.inputs())
        rasterize_gaussians(settings=s.settings("auto"), **s.inputs())
    assert len([w for w in rec if issubclass(w.category, _dispatch.BackendFallbackWarning)]) == 1
    assert "make setup" in str(rec[0].message)
    b = rasterize_gaussians(settings=s.settings("reference"), **s.inputs())
    torch.testing.assert_close(a.color, b.color, rtol=0, atol=0)


def test_auto_uses_native_when_available(monkeypatch, native_backend):
    monkeypatch.delenv(_dispatch.ENV_VAR, raising=False)
    from gaussian_renderer_pose._native import rasterize_gaussians_native

    assert (
        _dispatch.select_backend("auto", torch.device("cpu"), torch.float32)
        is rasterize_gaussians_native
    )
    s = make_scene(50)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = rasterize_gaussians(settings=s.settings("auto"), **s.inputs())
    b = rasterize_gaussians(settings=s.settings("reference"), **s.inputs())
    torch.testing.assert_close(a.color, b.color, rtol=1e-3, atol=1e-3)
    assert torch.equal(a.radii, b.radii)


def test_env_override(monkeypatch):
    s = make_scene(6)
    monkeypatch.setattr(_dispatch, "_warned", set())
    monkeypatch.setenv(_dispatch.ENV_VAR, "reference")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rasterize_gaussians(settings=s.settings("auto"), **s.inputs())
    monkeypatch.setenv(_dispatch.ENV_VAR, "bogus")
    with pytest.raises(ValueError, match="environment variable GRP_BACKEND must be one of"):
        rasterize_gaussians(settings=s.settings("auto"), **s.inputs())


def test_auto_float64_uses_reference_silently(monkeypatch):
    monkeypatch.delenv(_dispatch.ENV_VAR, raising=False)
    monkeypatch.setattr(_dispatch, "_warned", set())
    s = make_scene(6, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = rasterize_gaussians(settings=s.settings("auto"), **s.inputs())
    assert out.color.dtype == torch.float64


def test_import_does_not_compile():
    import subprocess
    import sys

    code = (
        "import sys, gaussian_renderer_pose as g; "
        "assert 'gaussian_renderer_pose._C' not in sys.modules; "
        "assert 'torch.utils.cpp_extension' not in sys.modules, 'cpp_extension imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=str(REPO))
