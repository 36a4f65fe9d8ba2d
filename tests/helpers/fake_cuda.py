"""Run CPU code as if some of its tensors lived on a GPU, and record what a GPU would refuse.

CI has no GPU, so the CUDA path of everything around the rasterizer (localizer, matchers, fitter,
tools) would otherwise only run where a GPU is lent. ``fake_cuda()`` is a ``TorchFunctionMode``
that tags tensors "on the GPU" (``.to("cuda")``, ``.cuda()``, a factory with ``device="cuda"``,
any op with a tagged input) and reports them as ``cuda:0`` (``.device``, ``.is_cuda``), while
they stay CPU tensors. It records, with the stack, each operation that a CUDA build would reject:

- an op mixing a tagged tensor with an untagged CPU tensor of one or more dimensions (a 0-dim CPU
  tensor is a scalar to CUDA, and CPU index tensors are allowed in indexing);
- ``.numpy()`` / ``np.asarray`` of a tagged tensor.

The rasterizer's ``"cuda"`` backend runs the native CPU kernel on the tagged tensors. What it
cannot see: tensors made in C++ or inside autograd's backward are tagged only through the
``.grad`` of a tagged leaf; ``torch.Generator(device="cuda")`` and ``torch.cuda.*`` calls are not
emulated. A real GPU run (tools/gpu_check.sh) is the check; this one keeps CI honest in between.
"""
from __future__ import annotations

import contextlib
import traceback
from typing import Any, Iterator, List

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten
from torch.utils.weak import WeakTensorKeyDictionary

CUDA = torch.device("cuda", 0)
_FACTORIES = {"zeros", "ones", "empty", "full", "tensor", "as_tensor", "arange", "linspace",
              "logspace", "eye", "rand", "randn", "randint", "randperm", "zeros_like",
              "ones_like", "empty_like", "full_like", "rand_like", "randn_like", "scalar_tensor",
              "new_zeros", "new_ones", "new_empty", "new_full", "new_tensor"}
_TO_CPU = {"cpu"}
_INDEXING = {"__getitem__", "__setitem__", "index_select", "gather", "take", "index_put_",
             "index_put", "index", "masked_select"}


def _is_cuda(device: Any) -> bool:
    if device is None:
        return False
    if isinstance(device, str):
        return device.startswith("cuda")
    if isinstance(device, torch.device):
        return device.type == "cuda"
    return False


_REAL_GENERATOR = torch.Generator


class _Generator(_REAL_GENERATOR):
    """``torch.Generator`` that takes ``device="cuda"`` (a CPU generator that remembers it)."""

    def __new__(cls, device="cpu"):
        gen = _REAL_GENERATOR.__new__(cls, "cpu")
        gen.on_gpu = _is_cuda(device) or device == "cuda"
        return gen

    def __init__(self, device="cpu"):
        pass


class FakeCuda(TorchFunctionMode):
    """The mode (module docstring); ``violations`` lists (what, stack) pairs."""

    def __init__(self):
        super().__init__()
        self.tagged = WeakTensorKeyDictionary()
        self.violations: List[tuple] = []

    # ------------------------------------------------------------------ tags
    def is_tagged(self, t: Any) -> bool:
        return isinstance(t, torch.Tensor) and t in self.tagged

    def tag(self, out: Any) -> Any:
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor):
                self.tagged[t] = True
        return out

    def _violation(self, what: str) -> None:
        frames = [f for f in traceback.extract_stack()
                  if "site-packages" not in f.filename and not f.filename.endswith("fake_cuda.py")]
        stack = "".join(traceback.format_list(frames[-6:]))
        self.violations.append((what, stack))

    # ------------------------------------------------------------------ dispatch
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        owner = getattr(func, "__self__", None)
        name = getattr(func, "__name__", str(func))
        if owner is torch.Tensor.device and name == "__get__":
            return CUDA if self.is_tagged(args[0]) else func(*args, **kwargs)
        if owner is torch.Tensor.is_cuda and name == "__get__":
            return self.is_tagged(args[0])
        if owner is torch.Tensor.grad and name == "__get__":
            g = func(*args, **kwargs)
            return self.tag(g) if g is not None and self.is_tagged(args[0]) else g
        if name == "__set__":  # an attribute set (``param.data = t``): the tensor takes t's place
            out = func(*args, **kwargs)
            if owner is torch.Tensor.data and isinstance(args[1], torch.Tensor):
                if self.is_tagged(args[1]):
                    self.tagged[args[0]] = True
                elif args[0] in self.tagged:
                    del self.tagged[args[0]]
            return out
        if name == "_has_compatible_shallow_copy_type":
            return func(*args, **kwargs)
        if name in ("numpy", "__array__") and args and self.is_tagged(args[0]):
            self._violation(f"{name}() of a GPU tensor")
            return func(*args, **kwargs)
        if name in ("cuda",):
            return self.tag(args[0].clone())
        if name in _TO_CPU:
            out = func(*args, **kwargs)
            return out.clone() if out is args[0] and self.is_tagged(out) else out
        if name == "to":
            return self._to(func, args, kwargs)
        to_gpu = _is_cuda(kwargs.get("device"))
        if to_gpu:
            kwargs["device"] = "cpu"
        gen = kwargs.get("generator")
        if getattr(gen, "on_gpu", False):
            tensor_in = [t for t in tree_flatten(args)[0] if isinstance(t, torch.Tensor)]
            if not to_gpu and not any(self.is_tagged(t) for t in tensor_in):
                self._violation(f"{name}: a CUDA generator drawing a CPU tensor")
            return self.tag(func(*args, **kwargs))
        inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        tagged = [t for t in inputs if self.is_tagged(t)]
        if name in _FACTORIES and "device" in kwargs and not to_gpu:
            out = func(*args, **kwargs)  # an explicit CPU tensor (of a *_like: the input's tag)
            return out
        if tagged and torch._C._current_autograd_node() is None:
            check = inputs
            if name in _INDEXING:  # CPU indices are allowed; the values must be on the GPU
                check = [args[0]] + ([args[2]] if name == "__setitem__" and len(args) > 2
                                     else [])
            mixed = [t for t in check
                     if isinstance(t, torch.Tensor) and not self.is_tagged(t) and t.dim() > 0]
            if mixed:
                shapes = ", ".join(str(tuple(t.shape)) for t in mixed)
                self._violation(f"{name}: CPU tensor(s) of shape {shapes} with GPU tensors")
        out = func(*args, **kwargs)
        if to_gpu or tagged:
            self.tag(out)
        return out

    def _to(self, func, args, kwargs):
        src = args[0]
        target = kwargs.get("device")
        for a in args[1:]:
            if isinstance(a, (str, torch.device)):
                target = a
            elif isinstance(a, torch.Tensor):
                target = CUDA if self.is_tagged(a) else a.device
        if target is None:  # a dtype change: the device (and its tag) stay
            out = func(*args, **kwargs)
            return self.tag(out) if self.is_tagged(src) else out
        cpu_args = tuple("cpu" if isinstance(a, (str, torch.device)) else
                         (a.dtype if isinstance(a, torch.Tensor) else a) for a in args[1:])
        if "device" in kwargs:
            kwargs["device"] = "cpu"
        out = func(src, *cpu_args, **kwargs)
        if _is_cuda(target):
            if out is src and not self.is_tagged(src):
                out = out.clone()
            return self.tag(out)
        if self.is_tagged(src) and out is src:
            out = out.clone()
        return out


@contextlib.contextmanager
def fake_cuda(monkeypatch) -> Iterator[FakeCuda]:
    """The mode, with the rasterizer's ``"cuda"`` backend served by the native CPU kernel."""
    from gaussian_renderer_pose import _backend

    real = _backend.native_status
    monkeypatch.setattr(_backend, "native_status",
                        lambda kind: real("cpu") if kind == "cuda" else real(kind))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch, "Generator", _Generator)
    mode = FakeCuda()
    new_parameter = torch.nn.Parameter.__new__

    def parameter(cls, data=None, requires_grad=True):  # keeps its data's tag
        out = new_parameter(cls, data, requires_grad)
        return mode.tag(out) if mode.is_tagged(data) else out

    monkeypatch.setattr(torch.nn.Parameter, "__new__", parameter)
    with mode:
        yield mode


def report(mode: FakeCuda, limit: int = 5) -> str:
    """The first ``limit`` distinct violations (by place), each with its stack."""
    seen, lines = set(), []
    for what, stack in mode.violations:
        where = stack.strip().splitlines()[-2:] if stack.strip() else [""]
        key = (what.split(":")[0], tuple(where))
        if key in seen:
            continue
        seen.add(key)
        lines.append(f"{what}\n{stack}")
    shown = "\n".join(lines[:limit])
    return (f"{len(mode.violations)} operations a GPU would refuse, at {len(lines)} places:\n"
            f"{shown}")
