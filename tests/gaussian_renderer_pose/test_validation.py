"""Bad input raises ValueError (RasterizerInputError).

The message names the argument, the expected and the actual value.
"""
from __future__ import annotations

import pytest
import torch

from gaussian_renderer_pose import rasterize_gaussians
from gaussian_renderer_pose._validate import RasterizerInputError
from tests.helpers.scenes import make_scene


@pytest.fixture
def scene():
    return make_scene(12, height=16, width=20)


def call(scene, settings=None, **overrides):
    kw = {**scene.inputs(), **overrides}
    return rasterize_gaussians(settings=settings or scene.settings("reference"), **kw)


def test_valid_scene_renders(scene):
    out = call(scene)
    assert out.color.shape == (3, 16, 20)


@pytest.mark.parametrize(
    "name,bad,pattern",
    [
        ("means3D", torch.zeros(12, 2), r"means3D must have shape \[\*, 3\], got \[12, 2\]"),
        ("opacities", torch.zeros(11, 1), r"opacities must have shape \[12, 1\], got \[11, 1\]"),
        ("means2D", torch.zeros(12, 3, 1), r"means2D must have shape \[12, 3\]"),
        ("shs", torch.zeros(12, 16), r"shs must have shape \[12, \*, 3\]"),
        (
            "shs",
            torch.zeros(12, 9, 3),
            r"shs must have at least .* 16 coefficients .* got shape \[12, 9, 3\]",
        ),
        ("scales", torch.zeros(12, 4), r"scales must have shape \[12, 3\]"),
        ("rotations", torch.zeros(12, 3), r"rotations must have shape \[12, 4\]"),
        ("means3D", "not a tensor", r"means3D must be a torch.Tensor, got str"),
    ],
)
def test_wrong_shape(scene, name, bad, pattern):
    with pytest.raises(RasterizerInputError, match=pattern):
        call(scene, **{name: bad})


def test_wrong_shape_precomp():
    s = make_scene(5, height=16, width=20, colors="precomp", covariance="precomp")
    with pytest.raises(ValueError, match=r"colors_precomp must have shape \[5, 3\], got \[5, 4\]"):
        call(s, colors_precomp=torch.zeros(5, 4))
    with pytest.raises(
        ValueError, match=r"cov3D_precomp must have shape \[5, 6\], got \[5, 3, 3\]"
    ):
        call(s, cov3D_precomp=torch.zeros(5, 3, 3))


def test_settings_tensor_shapes(scene):
    st = scene.settings("reference")
    for field, bad, pat in [
        ("bg", torch.zeros(4), r"bg must have shape \[3\], got \[4\]"),
        ("viewmatrix", torch.eye(3), r"viewmatrix must have shape \[4, 4\], got \[3, 3\]"),
        ("projmatrix", torch.eye(4)[None], r"projmatrix must have shape \[4, 4\]"),
        ("campos", torch.zeros(1, 3), r"campos must have shape \[3\], got \[1, 3\]"),
    ]:
        with pytest.raises(ValueError, match=pat):
            call(scene, st._replace(**{field: bad}))


def test_dtype(scene):
    with pytest.raises(
        ValueError, match=r"means3D must have dtype float32 or float64, got torch.int64"
    ):
        call(scene, means3D=torch.zeros(12, 3, dtype=torch.long))
    with pytest.raises(
        ValueError,
        match=r"opacities must have the same dtype as means3D \(torch.float32\), got torch.float64",
    ):
        call(scene, opacities=scene.opacities.double())
    with pytest.raises(ValueError, match=r"bg must have the same dtype"):
        call(scene, scene.settings("reference")._replace(bg=scene.bg.double()))


def test_native_backend_requires_float32(native_backend):
    s = make_scene(4, height=16, width=20, dtype=torch.float64)
    with pytest.raises(ValueError, match="float32"):
        call(s, s.settings(native_backend))


def test_device_mismatch(scene):
    with pytest.raises(
        ValueError, match=r"opacities must be on the same device as means3D \(cpu\), got meta"
    ):
        call(scene, opacities=scene.opacities.to("meta"))
    with pytest.raises(ValueError, match=r"viewmatrix must be on the same device"):
        call(scene, scene.settings("reference")._replace(viewmatrix=torch.eye(4, device="meta")))


TENSOR_INPUTS = ["means3D", "means2D", "opacities", "shs", "scales", "rotations"]


@pytest.mark.parametrize("name", TENSOR_INPUTS)
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_inputs(scene, name, value):
    bad = getattr(scene, name).clone()
    bad.view(-1)[3] = value
    with pytest.raises(
        ValueError, match=rf"{name} must contain only finite values, got 1 NaN/Inf entry"
    ):
        call(scene, **{name: bad})


def test_opposite_infinities_are_caught(scene):
    # their sum is NaN, not Inf: the one-reduction fast path must still see them
    bad = scene.shs.clone()
    bad.view(-1)[1], bad.view(-1)[7] = float("inf"), float("-inf")
    with pytest.raises(ValueError, match=r"shs must contain only finite values, got 2 NaN/Inf"):
        call(scene, shs=bad)


def test_finite_entries_whose_sum_overflows_pass():
    from gaussian_renderer_pose._validate import _check_finite

    big = torch.full((4, 3), 3.0e38, dtype=torch.float32)
    assert not torch.isfinite(big.sum())  # the fast path cannot decide: the full scan does
    _check_finite("means3D", big)
    big[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"means3D must contain only finite values, got 1"):
        _check_finite("means3D", big)


@pytest.mark.parametrize("name", ["colors_precomp", "cov3D_precomp"])
def test_non_finite_precomp(name):
    s = make_scene(5, height=16, width=20, colors="precomp", covariance="precomp")
    bad = getattr(s, name).clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match=rf"{name} must contain only finite values"):
        call(s, **{name: bad})


@pytest.mark.parametrize("field", ["bg", "viewmatrix", "projmatrix", "campos"])
def test_non_finite_settings_tensors(scene, field):
    st = scene.settings("reference")
    bad = getattr(st, field).clone(memory_format=torch.contiguous_format)
    bad.view(-1)[0] = float("inf")
    with pytest.raises(ValueError, match=rf"{field} must contain only finite values"):
        call(scene, st._replace(**{field: bad}))


@pytest.mark.parametrize(
    "field,value,pattern",
    [
        ("image_height", 0, r"image_height must be a positive int, got 0"),
        ("image_width", -3, r"image_width must be a positive int, got -3"),
        ("image_width", 20.0, r"image_width must be a positive int, got 20.0"),
        ("image_height", True, r"image_height must be a positive int, got True"),
        ("tanfovx", 0.0, r"tanfovx must be a positive finite number, got 0.0"),
        ("tanfovy", float("nan"), r"tanfovy must be a positive finite number, got nan"),
        ("tanfovx", -1.0, r"tanfovx must be a positive finite number"),
        ("scale_modifier", 0.0, r"scale_modifier must be a positive finite number"),
        ("scale_modifier", float("inf"), r"scale_modifier must be a positive finite number"),
        ("sh_degree", 4, r"sh_degree must be an int in 0..3, got 4"),
        ("sh_degree", -1, r"sh_degree must be an int in 0..3, got -1"),
        ("sh_degree", 1.5, r"sh_degree must be an int in 0..3, got 1.5"),
        ("antialiasing", "yes", r"antialiasing must be a bool"),
        ("backend", "gpu", r"settings.backend must be one of"),
    ],
)
def test_bad_scalar_settings(scene, field, value, pattern):
    with pytest.raises(ValueError, match=pattern):
        call(scene, scene.settings("reference")._replace(**{field: value}))


def test_errors_are_value_errors():
    assert issubclass(RasterizerInputError, ValueError)


def test_bad_settings_type(scene):
    with pytest.raises(ValueError, match="settings must be a GaussianRasterizationSettings"):
        rasterize_gaussians(scene.means3D, scene.opacities, settings=dict(image_height=3))


def test_validate_false_skips_only_the_per_gaussian_scans(scene, monkeypatch):
    import gaussian_renderer_pose._validate as v

    scanned = []
    real = v._check_finite
    monkeypatch.setattr(v, "_check_finite", lambda name, t: (scanned.append(name), real(name, t)))
    full = call(scene)
    assert {"means3D", "opacities", "shs", "scales", "rotations"} <= set(scanned)
    scanned.clear()
    st = scene.settings("reference")
    fast = rasterize_gaussians(settings=st, validate=False, **scene.inputs())
    assert sorted(scanned) == sorted(v.CAMERA_TENSORS)
    for a, b in zip(full, fast):
        assert torch.equal(a, b)


def test_validate_false_keeps_the_cheap_checks(scene):
    st = scene.settings("reference")
    with pytest.raises(ValueError, match=r"means3D must have shape \[\*, 3\], got \[12, 2\]"):
        rasterize_gaussians(settings=st, validate=False,
                            **{**scene.inputs(), "means3D": torch.zeros(12, 2)})
    with pytest.raises(ValueError, match=r"opacities must have the same dtype as means3D"):
        rasterize_gaussians(settings=st, validate=False,
                            **{**scene.inputs(), "opacities": scene.opacities.double()})
    bad = st.viewmatrix.clone(memory_format=torch.contiguous_format)
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"viewmatrix must contain only finite values"):
        rasterize_gaussians(settings=st._replace(viewmatrix=bad), validate=False, **scene.inputs())
    with pytest.raises(ValueError, match=r"validate must be a bool, got 'no'"):
        rasterize_gaussians(settings=st, validate="no", **scene.inputs())
