"""Argument checks shared by the plugin (as kornia's ``core/check.py``).

Each returns the value (converted: a float, an int, a bool) or raises ValueError whose message
names the argument, says what was expected and shows what was given, e.g. ``lr must be a finite
number > 0, got -1``.

A bool is never accepted as a number (``True`` is an int in Python), and NaN or infinity never
passes a number check.
"""
from __future__ import annotations

import math
import numbers
from typing import Any, Iterable, Optional, Sequence, Tuple

__all__ = ["check_bool", "check_choice", "check_int", "check_pair", "check_real", "is_real"]


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
