"""Backend selection: "reference" | "cpu" | "cuda" | "auto" (env override ``GRP_BACKEND``).

"auto" picks the native kernel for the device of the inputs when it is usable, else the pure
PyTorch reference, warning ONCE per process per reason. An explicitly requested native backend
that is unusable raises RuntimeError with the reason. The native module is imported lazily.
"""
from __future__ import annotations

import os
import warnings
from typing import Callable, Dict, Optional, Set

import torch

from . import _backend

BACKENDS = ("reference", "cpu", "cuda", "auto")
ENV_VAR = "GRP_BACKEND"

_warned: Set[str] = set()


class BackendFallbackWarning(UserWarning):
    """'auto' fell back to the (slow) pure-PyTorch reference backend."""


def _native_fn() -> Callable:
    from ._native import rasterize_gaussians_native  # lazy: may not exist / not be built

    return rasterize_gaussians_native


def _reference_fn() -> Callable:
    from .reference import rasterize_gaussians_reference

    return rasterize_gaussians_reference


def _native_reason(kind: str) -> Optional[str]:
    """None when the native backend `kind` is usable, else why not."""
    ok, why = _backend.native_status(kind)
    if not ok:
        return why
    try:
        _native_fn()
    except Exception as exc:  # ImportError or anything raised while importing _native
        return f"gaussian_renderer_pose._native could not be imported ({type(exc).__name__}: {exc})"
    return None


def available_backends() -> Dict[str, Optional[str]]:
    """Backend name -> None if usable here, else the reason it is not."""
    return {
        "reference": None,
        "cpu": _native_reason("cpu"),
        "cuda": _native_reason("cuda"),
    }


def requested_backend(backend: str) -> str:
    """The backend name in force: ``GRP_BACKEND`` overrides the settings' value."""
    env = os.environ.get(ENV_VAR, "").strip()
    name = env if env else backend
    if name not in BACKENDS:
        source = f"environment variable {ENV_VAR}" if env else "settings.backend"
        raise ValueError(f"{source} must be one of {BACKENDS}, got {name!r}")
    return name


def _warn_once(reason: str) -> None:
    if reason in _warned:
        return
    _warned.add(reason)
    warnings.warn(
        "gaussian_renderer_pose: using the slow pure-PyTorch reference backend because "
        f"{reason}. To fix: build the native extension (`make setup` or "
        "`python setup.py build_ext --inplace`), or select backend='reference' (or set "
        f"{ENV_VAR}=reference) to silence this warning.",
        BackendFallbackWarning,
        stacklevel=4,
    )


def select_backend(
    backend: str, device: torch.device, dtype: torch.dtype = torch.float32
) -> Callable:
    """Return the backend function for `backend` and tensors on `device` with `dtype`."""
    name = requested_backend(backend)
    if name == "reference":
        return _reference_fn()
    if name in ("cpu", "cuda"):
        if device.type != name:
            raise RuntimeError(
                f"backend {name!r} requested but the inputs are on device {str(device)!r}"
            )
        why = _native_reason(name)
        if why is not None:
            raise RuntimeError(f"backend {name!r} requested but unavailable: {why}")
        if dtype != torch.float32:
            raise ValueError(
                f"means3D (and every tensor input) must be float32 for the native {name!r} "
                f"backend, got {dtype}; use backend='reference' for float64"
            )
        return _native_fn()
    # auto
    if dtype != torch.float32:
        return _reference_fn()  # float64 is the reference's job; no warning needed
    if device.type in ("cpu", "cuda"):
        why = _native_reason(device.type)
        if why is None:
            return _native_fn()
        _warn_once(f"the native {device.type} backend is unavailable: {why}")
    else:
        _warn_once(f"there is no native backend for device type {device.type!r}")
    return _reference_fn()
