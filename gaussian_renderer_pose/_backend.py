"""Lazy loader for the compiled extension `gaussian_renderer_pose._C`.

Importing the package never compiles anything: the extension is built by `setup.py`
(`python setup.py build_ext --inplace`, run by `make setup`). When it is missing or was built
without CUDA, the reason is cached and reported by `native_status`.
"""
from __future__ import annotations

import importlib
from types import ModuleType
from typing import Optional, Tuple

import torch


class NativeUnavailable(RuntimeError):
    """The compiled extension (or the requested device kind in it) is not usable here."""


_module: Optional[ModuleType] = None
_error: Optional[str] = None


def load_native() -> ModuleType:
    """Return the compiled `_C` module, importing it once.

    Raises:
        NativeUnavailable: the module cannot be imported (the message says why).
    """
    global _module, _error
    if _module is not None:
        return _module
    if _error is not None:
        raise NativeUnavailable(_error)
    try:
        _module = importlib.import_module("gaussian_renderer_pose._C")
    except ImportError as exc:  # not built, or built against another torch
        _error = (
            f"native extension gaussian_renderer_pose._C could not be imported ({exc}); "
            "build it with `make setup` or `python setup.py build_ext --inplace`"
        )
        raise NativeUnavailable(_error) from exc
    return _module


def native_status(kind: str) -> Tuple[bool, Optional[str]]:
    """(usable, reason-if-not) for kind 'cpu' or 'cuda'."""
    if kind not in ("cpu", "cuda"):
        raise ValueError(f"kind must be 'cpu' or 'cuda', got {kind!r}")
    try:
        mod = load_native()
    except NativeUnavailable as exc:
        return False, str(exc)
    if kind == "cuda":
        if not getattr(mod, "WITH_CUDA", False):
            why = (
                "torch has no CUDA (torch.version.cuda is None)"
                if torch.version.cuda is None
                else "the extension was built without CUDA (CUDA_HOME unset at build time)"
            )
            return False, f"CUDA backend not built: {why}"
        if not torch.cuda.is_available():
            return False, "CUDA backend built but no CUDA device is available"
    return True, None
