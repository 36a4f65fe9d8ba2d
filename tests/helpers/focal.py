"""Checks shared by the tests of a focal length estimated from many photos (batch, sequence)."""
from __future__ import annotations

from typing import Any, Dict

import numpy as np
import pytest


def check_focal_found(docs: Dict[bool, Dict[str, Any]], fx_true: float, given_share: float,
                      what: str) -> None:
    """``docs[False]`` (the estimate off) kept the given focal length; ``docs[True]`` found it.

    Each found row holds the true focal length within 1.5 %, and the median translation error
    falls to under a quarter; the console summary says it was ``estimated from the {what}``.
    """
    from tests.helpers.tools import localize_tool

    held, found = docs[False]["photos"], docs[True]["photos"]
    assert all(r["camera_focal_scale"] == 1.0 for r in held)
    assert docs[True]["summary"]["focal_adoptions"] >= 1
    for r in found:
        assert r["status"] != "failed", r["reason"]
        assert r["camera_focal_scale"] == pytest.approx(1 / given_share, rel=0.015), r
        assert r["intrinsics"]["fx"] == pytest.approx(fx_true, rel=0.015), r
    trans = [np.median([r["trans_err_rel"] for r in rows]) for rows in (held, found)]
    assert trans[1] < 0.25 * trans[0], trans
    assert f"estimated from the {what}" in localize_tool().many_summary(docs[True])
