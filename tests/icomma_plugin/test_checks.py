"""icomma_plugin.checks: values come back converted, and every refusal names the argument."""
from __future__ import annotations

import math

import numpy as np
import pytest

from icomma_plugin.checks import (
    check_bool,
    check_choice,
    check_int,
    check_pair,
    check_real,
    is_real,
)


def test_numbers_are_converted_and_bools_nan_inf_refused():
    assert check_real(3, "x") == 3.0 and isinstance(check_real(np.float32(0.5), "x"), float)
    for bad in (True, math.nan, math.inf, "1", None, [1.0]):
        with pytest.raises(ValueError, match=r"^x must be a finite number, got"):
            check_real(bad, "x")
    assert not is_real(False) and is_real(np.int64(2))


@pytest.mark.parametrize("kw,ok,bad,text", [
    ({"lo": 0.0, "lo_open": True}, 1e-9, 0.0, "> 0"),
    ({"lo": 0.0, "hi": 1.0}, 1.0, 1.01, "in [0, 1]"),
    ({"lo": 0.0, "hi": 1.0, "hi_open": True}, 0.0, 1.0, "in [0, 1)"),
    ({"hi": 5.0}, -3.0, 6.0, "<= 5"),
])
def test_bounds_and_their_wording(kw, ok, bad, text):
    assert check_real(ok, "lam", **kw) == ok
    with pytest.raises(ValueError, match=rf"lam must be a finite number {text[0]}"):
        check_real(bad, "lam", **kw)
    with pytest.raises(ValueError) as e:
        check_real(bad, "lam", **kw)
    assert text in str(e.value) and repr(bad) in str(e.value)


def test_ints_bools_choices_pairs():
    assert check_int(np.int32(4), "n", 1) == 4 and check_int(None, "n", optional=True) is None
    for bad in (1.0, True, 0):
        with pytest.raises(ValueError, match="n must be an int >= 1"):
            check_int(bad, "n", 1)
    assert check_bool(False, "flag") is False
    with pytest.raises(ValueError, match="flag must be a bool"):
        check_bool(0, "flag")
    assert check_choice("cpu", "backend", ("cpu", "cuda")) == "cpu"
    with pytest.raises(ValueError, match=r"backend must be one of \('cpu', 'cuda'\), got 'gpu'"):
        check_choice("gpu", "backend", ("cpu", "cuda"))
    assert check_pair([1, 2], "rot_deg", 0, 180) == (1.0, 2.0)
    for bad in ([2, 1], [1], [0, 200], "ab"):
        with pytest.raises(ValueError, match="rot_deg must be a pair"):
            check_pair(bad, "rot_deg", 0, 180)


def test_tensors_shapes_and_finite_values():
    import torch

    from icomma_plugin.checks import all_finite, check_tensor

    img = torch.rand(3, 4, 5)
    assert check_tensor(img, "image", (3, "H", "W"), floating=True, finite=True) is img
    with pytest.raises(ValueError, match=r"image must be a floating-point tensor of shape \[3, H"):
        check_tensor(img[:1], "image", (3, "H", "W"), floating=True)
    big = torch.full((4,), 3e38)  # finite entries whose sum overflows
    assert all_finite(big) and check_tensor(big, "x", finite=True) is big
    for bad in (float("nan"), float("inf")):
        t = img.clone()
        t[1, 2, 3] = bad
        assert not all_finite(t)
        with pytest.raises(ValueError, match="image contains NaN or infinite values"):
            check_tensor(t, "image", finite=True)
    both = torch.tensor([float("inf"), -float("inf")])  # their sum is NaN
    assert not all_finite(both) and all_finite(torch.zeros(0)) and all_finite(torch.arange(3))
