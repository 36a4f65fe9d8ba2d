"""Argument checks shared by the plugin (as kornia's ``core/check.py``).

Each returns the value (converted: a float, an int, a bool) or raises ValueError whose message
names the argument, says what was expected and shows what was given, e.g. ``lr must be a finite
number > 0, got -1``.

A bool is never accepted as a number (``True`` is an int in Python), and NaN or infinity never
passes a number check.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Dict, Iterable, Mapping, Optional, Sequence, Tuple, Union

__all__ = [
    "HYDRA_KEYS",
    "all_finite",
    "check_bool",
    "check_choice",
    "check_int",
    "check_pair",
    "check_real",
    "check_tensor",
    "config_from_dict",
    "is_real",
]

#: Keys Hydra's instantiate reads; a config group composed with ``_target_`` still builds with
#: :func:`config_from_dict`.
HYDRA_KEYS = ("_target_", "_convert_", "_recursive_", "_partial_")


def is_real(value: Any) -> bool:
    """A finite real number that is not a bool (numpy scalars included)."""
    return (isinstance(value, numbers.Real) and not isinstance(value, bool)
            and math.isfinite(float(value)))


def _bounds(lo, hi, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi:g}"
    return ""


def _in_bounds(v: float, lo, hi, lo_open: bool, hi_open: bool) -> bool:
    if lo is not None and (v <= lo if lo_open else v < lo):
        return False
    if hi is not None and (v >= hi if hi_open else v > hi):
        return False
    return True


def check_real(
    value: Any,
    name: str,
    lo: Optional[float] = None,
    hi: Optional[float] = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    optional: bool = False,
) -> Optional[float]:
    """``value`` as a float, finite and within the bounds (None passes when ``optional``)."""
    if value is None and optional:
        return None
    if not is_real(value) or not _in_bounds(float(value), lo, hi, lo_open, hi_open):
        what = (
            "a finite number" + _bounds(lo, hi, lo_open, hi_open) + (" or None" if optional else "")
        )
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return float(value)


def check_int(value: Any, name: str, lo: Optional[int] = None, hi: Optional[int] = None, *,
              optional: bool = False) -> Optional[int]:
    """``value`` as an int within ``[lo, hi]`` (None passes when ``optional``)."""
    if value is None and optional:
        return None
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool)) \
            or not _in_bounds(int(value), lo, hi, False, False):
        what = "an int" + _bounds(lo, hi, False, False) + (" or None" if optional else "")
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return int(value)


def check_bool(value: Any, name: str) -> bool:
    """``value`` when it is a bool, else ValueError naming ``name``."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be a bool (true / false), got {value!r}")
    return value


def check_choice(value: Any, name: str, choices: Iterable[Any]) -> Any:
    """``value`` when it is one of ``choices``, else ValueError naming ``name``."""
    choices = tuple(choices)
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


def check_backend_here(backend: str, name: str = "backend") -> str:
    """``backend`` when this machine can run it; ValueError naming ``name`` and why otherwise.

    ``auto`` and ``reference`` run everywhere; ``cpu`` and ``cuda`` need their native kernel built
    (and, for ``cuda``, a visible GPU). Checked where a job starts, so that a machine without a GPU
    refuses ``cuda`` at once with the reason, not at its first render.
    """
    from gaussian_renderer_pose import available_backends
    from gaussian_renderer_pose._dispatch import BACKENDS

    backend = check_choice(backend, name, BACKENDS)
    why = available_backends().get(backend)
    if why is not None:
        raise ValueError(f"{name}={backend!r} cannot run here: {why} (use auto, or cpu)")
    return backend


def check_pair(value: Any, name: str, lo: Optional[float] = None, hi: Optional[float] = None,
               ordered: bool = True) -> Tuple[float, float]:
    """A pair of finite numbers within the bounds (``ordered``: first <= second)."""
    ok = isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2 \
        and all(is_real(v) and _in_bounds(float(v), lo, hi, False, False) for v in value)
    if ok and ordered:
        ok = float(value[0]) <= float(value[1])
    if not ok:
        what = (
            "a pair of finite numbers"
            + _bounds(lo, hi, False, False)
            + (" [lo, hi] with lo <= hi" if ordered else "")
        )
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return float(value[0]), float(value[1])


def check_tensor(value: Any, name: str, shape: Optional[Sequence[Union[int, str]]] = None, *,
                 floating: bool = False, finite: bool = False, optional: bool = False):
    """``value`` when it is a torch tensor of ``shape`` (kornia's ``KORNIA_CHECK_SHAPE`` style).

    Args:
        value: the tensor.
        name: the argument's name, for the message.
        shape: the sizes, an int for a fixed size or a letter for a free one; the same letter
            must have the same size everywhere (``(3, "H", "W")``, ``(1, "H", "W")``).
        floating: it must have a floating-point dtype.
        finite: no NaN or infinity.
        optional: None passes.

    Raises:
        ValueError: naming ``name``, what was expected and what was given.
    """
    import torch

    if value is None and optional:
        return None
    want = "" if shape is None else " of shape [" + ", ".join(str(d) for d in shape) + "]"
    kind = "a floating-point tensor" if floating else "a torch tensor"
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name} must be {kind}{want}, got {type(value).__name__}")
    if shape is not None:
        sizes: Dict[str, int] = {}
        ok = value.ndim == len(shape)
        for d, n in zip(shape, value.shape if ok else ()):
            if isinstance(d, str):
                ok = ok and sizes.setdefault(d, int(n)) == int(n)
            else:
                ok = ok and int(d) == int(n)
        if not ok:
            raise ValueError(f"{name} must be {kind}{want}, got shape {list(value.shape)}")
    if floating and not value.is_floating_point():
        raise ValueError(f"{name} must be {kind}{want}, got dtype {value.dtype}")
    if finite and not all_finite(value):
        raise ValueError(f"{name} contains NaN or infinite values")
    return value


def all_finite(value) -> bool:
    """No NaN or infinity in the tensor ``value``.

    A finite sum proves every entry finite (NaN and infinities propagate into it): one
    reduction, and the element-wise scan only when the sum is not finite (a NaN or an infinity,
    or finite entries whose sum overflows). The rasterizer's input check does the same.
    """
    import torch

    if value.numel() == 0 or not value.is_floating_point():
        return True
    with torch.no_grad():
        return bool(torch.isfinite(value.sum())) or bool(torch.isfinite(value).all())


def config_from_dict(cls, d: Optional[Mapping[str, Any]], where: Optional[str] = None):
    """A config dataclass ``cls`` from a plain (nested) mapping: the one way configs are read.

    Hydra's keys (`HYDRA_KEYS`) are dropped; nested dataclass fields are built from mappings;
    lists become tuples; an int given for a float field becomes a float.

    Raises:
        ValueError: ``d`` is not a mapping, or has keys ``cls`` does not know (the message names
            ``where`` and lists the known keys); the dataclass's own checks.
    """
    where = where or cls.__name__
    if d is None:
        d = {}
    if not isinstance(d, Mapping):
        raise ValueError(f"{where} must be a mapping, got {type(d).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    d = {k: v for k, v in d.items() if k not in HYDRA_KEYS}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ValueError(f"unknown {where} keys {unknown}; known keys: {sorted(fields)}")
    kw = {}
    for k, v in d.items():
        f = fields[k]
        default = (f.default_factory() if f.default_factory is not dataclasses.MISSING
                   else f.default)
        if dataclasses.is_dataclass(default) and isinstance(v, Mapping):
            v = config_from_dict(type(default), v, f"{where}.{k}")
        elif isinstance(v, list):
            v = tuple(v)
        elif isinstance(default, float) and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        kw[k] = v
    return cls(**kw)
