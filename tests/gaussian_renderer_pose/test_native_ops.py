"""The native ops torch.ops.grp.*: schemas, opcheck, deterministic saved state.

Their schemas follow the backend contract that _native.py relies on, `torch.library.opcheck`
passes on each (schema, autograd registration, fake kernel against the real kernel, AOT dispatch
with dynamic shapes), and the forward's saved state is a function of its inputs (no
uninitialised memory).
"""
from __future__ import annotations

import inspect

import pytest
import torch

from gaussian_renderer_pose import _backend
from gaussian_renderer_pose.camera import camera_matrices
from tests.helpers.scenes import make_scene

pytestmark = pytest.mark.usefixtures("native_backend")

DEVICES = ["cpu"] + (["cuda"] if _backend.native_status("cuda")[0] else [])
IMAGES = ("color", "invdepth", "depth_acc", "alpha")
STATE = ("radii", "geom", "binning", "tile_ranges", "offsets", "final_T", "last_contrib")


def _ops():
    from gaussian_renderer_pose import _ops

    return _ops


def _names(args):
    return [a.name for a in args]


def test_op_schemas_follow_the_backend_contract():
    from gaussian_renderer_pose._native import rasterize_gaussians_native

    contract = list(inspect.signature(rasterize_gaussians_native).parameters)
    # means3D .. campos, then the optional tensors among the keyword arguments
    tensors = contract[:contract.index("campos") + 1] + ["shs_rest"]
    inputs = [n for n in contract if n != "means2D"]  # means2D only carries a gradient
    ops = _ops()
    fwd, bwd = ops.rasterize_forward._schema, ops.rasterize_backward._schema
    assert _names(fwd.arguments) == inputs
    assert _names(fwd.returns) == [*IMAGES, *STATE]
    assert _names(bwd.arguments) == [*inputs, *STATE, *(f"grad_{n}" for n in IMAGES),
                                     "compute_camera_grad", "compute_gaussian_grads"]
    # _native.py hands the backward's returns to autograd in the order of its tensor inputs
    assert _names(bwd.returns) == [f"grad_{n}" for n in tensors]
    assert _names(ops.mark_visible._schema.arguments) == ["means3D", "viewmatrix", "projmatrix"]


def _op_inputs(device, *, colors="sh", covariance="scale_rot", antialiasing=False, num=24,
               requires_grad=True, split_sh=False):
    """(tensors, settings) of rasterize_forward for a small scene on `device`.

    settings: the scalars, then shs_rest.
    """
    scene = make_scene(num, height=24, width=40, sh_degree=2, seed=7, colors=colors,
                       covariance=covariance, antialiasing=antialiasing)
    cam = camera_matrices(scene.w2c, scene.fx, scene.fy, scene.width, scene.height)
    raw = [scene.means3D, scene.opacities, scene.shs, scene.colors_precomp, scene.scales,
           scene.rotations, scene.cov3D_precomp, scene.bg, cam.viewmatrix, cam.projmatrix,
           cam.campos]
    tensors = [None if t is None else
               t.detach().to(device).contiguous().requires_grad_(requires_grad) for t in raw]
    shs_rest = None
    if split_sh:  # the first SH coefficient in shs, the others in shs_rest (the last argument)
        shs_rest = tensors[2][:, 1:].detach().contiguous().requires_grad_(requires_grad)
        tensors[2] = tensors[2][:, :1].detach().contiguous().requires_grad_(requires_grad)
    settings = (scene.height, scene.width, cam.tanfovx, cam.tanfovy, 1.0, scene.sh_degree, False,
                antialiasing, shs_rest)
    return tensors, settings


FORWARD_CASES = {
    "sh+scale_rot": dict(),
    "precomp colours+cov3D, antialiasing": dict(colors="precomp", covariance="precomp",
                                                antialiasing=True),
    "no Gaussians": dict(num=0),
    "sh in two tensors": dict(split_sh=True),
}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("case", list(FORWARD_CASES))
def test_opcheck_forward(device, case):
    tensors, settings = _op_inputs(device, **FORWARD_CASES[case])
    torch.library.opcheck(_ops().rasterize_forward, (*tensors, *settings))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("case", ["sh+scale_rot", "precomp colours+cov3D, antialiasing",
                                  "sh in two tensors"])
@pytest.mark.parametrize("camera,gaussians", [(True, True), (False, True), (True, False),
                                              (False, False)])
def test_opcheck_backward(device, case, camera, gaussians):
    ops = _ops()
    tensors, settings = _op_inputs(device, **FORWARD_CASES[case])
    with torch.no_grad():
        outs = ops.rasterize_forward(*tensors, *settings)
    H, W = settings[:2]
    g = torch.Generator().manual_seed(3)
    shapes = ((3, H, W), (1, H, W), (1, H, W), (1, H, W))
    grads = [torch.rand(s, generator=g).to(device) for s in shapes]
    torch.library.opcheck(ops.rasterize_backward,
                          (*tensors, *settings, *outs[4:], *grads, camera, gaussians))


@pytest.mark.parametrize("device", DEVICES)
def test_opcheck_mark_visible(device):
    tensors, _ = _op_inputs(device)
    torch.library.opcheck(_ops().mark_visible, (tensors[0], tensors[8], tensors[9]))


def test_ops_are_not_differentiable_themselves():
    # Gradients come from the autograd.Function of _native.py; the raw ops never track them.
    tensors, settings = _op_inputs("cpu")
    outs = _ops().rasterize_forward(*tensors, *settings)
    assert not any(t.requires_grad for t in outs)


@pytest.mark.parametrize("device", DEVICES)
def test_forward_outputs_are_a_function_of_the_inputs(device):
    # The Gaussians behind the camera get a geom record too (zeros): every output, saved state
    # included, is identical across calls even when the allocator hands back dirty memory.
    ops = _ops()
    tensors, settings = _op_inputs(device, num=60, requires_grad=False)
    first = ops.rasterize_forward(*tensors, *settings)
    radii = first[4]
    assert int((radii == 0).sum()) > 0, "the scene should have culled Gaussians"
    for _ in range(4):
        dirty = [torch.full_like(t, float("nan")) if t.is_floating_point() else
                 torch.full_like(t, -7) for t in first]
        del dirty
        again = ops.rasterize_forward(*tensors, *settings)
        for name, a, b in zip([*IMAGES, *STATE], first, again):
            assert torch.equal(a, b), f"{name} differs between two identical calls"


@pytest.mark.parametrize("num", [60, 100_000])  # torch's allocator; the kernel's block cache
@pytest.mark.parametrize("split_sh", [False, True])
def test_backward_gradients_are_a_function_of_the_inputs(num, split_sh):
    # The CPU backward writes the Gaussians' gradients into uninitialised (recycled) memory and
    # zeroes each block's rows itself: a Gaussian that reaches no pixel must still get exact
    # zeros when the memory handed back held NaNs from the call before.
    ops = _ops()
    tensors, settings = _op_inputs("cpu", num=num, requires_grad=False, split_sh=split_sh)
    with torch.no_grad():
        outs = ops.rasterize_forward(*tensors, *settings)
    radii = outs[4]
    assert int((radii == 0).sum()) > 0, "the scene should have Gaussians that reach no pixel"
    H, W = settings[:2]
    g = torch.Generator().manual_seed(5)
    cots = [torch.rand(s, generator=g) for s in ((3, H, W), (1, H, W), (1, H, W), (1, H, W))]

    def gaussian_grads():
        grads = ops.rasterize_backward(*tensors, *settings, *outs[4:], *cots, False, True)
        return [t for i, t in enumerate(grads) if t is not None and i not in (8, 9, 10, 11)]

    first = [t.clone() for t in gaussian_grads()]
    for _ in range(3):
        dirty = gaussian_grads()
        for t in dirty:
            t.fill_(float("nan"))  # handed back to the allocator / block cache full of NaNs
        del dirty
        again = gaussian_grads()
        assert len(again) == len(first)
        for a, b in zip(first, again):
            assert torch.equal(a, b)
            assert not bool(a[radii == 0].any()), "a Gaussian that reaches no pixel got a gradient"
