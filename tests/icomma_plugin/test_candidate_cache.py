"""The candidate cache's size cap: least recently used files go first, nothing else is touched."""
from __future__ import annotations

import logging
import os
import time

import numpy as np
import pytest

from icomma_plugin.camera import Intrinsics
from icomma_plugin.localization.candidate_cache import (
    CandidateCache,
    DEFAULT_MAX_GB,
    default_max_bytes,
)
from icomma_plugin.localization.candidates import CandidateIndex


def _index(n: int) -> CandidateIndex:
    """A small index of ``n`` cameras (its file grows with ``n``)."""
    return CandidateIndex([np.eye(4)] * n, [f"camera_{i}" for i in range(n)],
                          Intrinsics(32, 24, 30.0, 30.0), [None] * n, 1)


def _age(path, seconds_ago: float) -> None:
    t = time.time() - seconds_ago
    os.utime(path, (t, t))


def test_the_least_recently_used_files_go_first_and_a_load_counts_as_a_use(tmp_path, caplog):
    cache = CandidateCache(tmp_path, max_bytes=0)  # no cap while filling
    keys = []
    for i in range(4):
        fields = {"model": "m", "n": i}
        cache.get_or_build(fields, lambda: _index(50))
        keys.append(CandidateCache.key(fields))
    for i, k in enumerate(keys):  # written in order, the first the oldest
        _age(cache.path(k), 1000 - 100 * i)
    assert cache.load(keys[0]) is not None  # used now: no longer the oldest
    size = cache.path(keys[0]).stat().st_size
    capped = CandidateCache(tmp_path, max_bytes=3 * size + size // 2)
    with caplog.at_level(logging.INFO):
        capped.get_or_build({"model": "m", "n": 99}, lambda: _index(50))
    left = sorted(p.stem for p in tmp_path.glob("*.pt"))
    # five files, room for three: the two least recently used (keys 1 and 2) are gone, with their
    # locks; the one just written and the one just loaded stay
    assert left == sorted([keys[0], keys[3], CandidateCache.key({"model": "m", "n": 99})])
    assert not (tmp_path / f"{keys[1]}.lock").exists()
    assert (tmp_path / f"{keys[0]}.lock").exists()
    assert "least recently used" in caplog.text


def test_only_the_caches_own_files_are_removed(tmp_path):
    cache = CandidateCache(tmp_path, max_bytes=1)  # over the cap after any write
    mine = tmp_path / "model.pt"  # a user's file in a folder given as the cache
    mine.write_bytes(b"x" * 4096)
    other = tmp_path / "notes.json"
    other.write_text("{}")
    old_tmp, new_tmp = tmp_path / ".abc.pt.1.tmp", tmp_path / ".abc.pt.2.tmp"
    old_tmp.write_bytes(b"half")
    new_tmp.write_bytes(b"half")
    _age(old_tmp, 2 * 86400)  # a write that crashed two days ago; the other may be running
    lod = tmp_path / ("lod-" + "0" * 32 + ".pt")
    lod.write_bytes(b"y" * 4096)
    _age(lod, 100)
    cache.get_or_build({"model": "m"}, lambda: _index(3))
    names = sorted(p.name for p in tmp_path.iterdir())
    assert mine.exists() and other.exists() and new_tmp.exists()
    assert not old_tmp.exists() and not lod.exists()
    assert f"{CandidateCache.key({'model': 'm'})}.pt" in names  # the new one is never removed


def test_no_cap_removes_nothing(tmp_path):
    cache = CandidateCache(tmp_path, max_bytes=0)
    for i in range(3):
        cache.get_or_build({"n": i}, lambda: _index(20))
    assert cache.max_bytes is None and cache.prune() == []
    assert len(list(tmp_path.glob("*.pt"))) == 3


def test_the_cap_from_the_environment(monkeypatch, caplog):
    monkeypatch.delenv("ICOMMA_CACHE_MAX_GB", raising=False)
    assert default_max_bytes() == int(DEFAULT_MAX_GB * (1 << 30))
    monkeypatch.setenv("ICOMMA_CACHE_MAX_GB", "0.5")
    assert default_max_bytes() == 1 << 29
    assert CandidateCache("unused").max_bytes == 1 << 29
    monkeypatch.setenv("ICOMMA_CACHE_MAX_GB", "0")
    assert default_max_bytes() is None
    monkeypatch.setenv("ICOMMA_CACHE_MAX_GB", "inf")
    assert default_max_bytes() is None
    monkeypatch.setenv("ICOMMA_CACHE_MAX_GB", "lots")
    with caplog.at_level(logging.WARNING):
        assert default_max_bytes() == int(DEFAULT_MAX_GB * (1 << 30))
    assert "ICOMMA_CACHE_MAX_GB" in caplog.text and "lots" in caplog.text


@pytest.mark.parametrize("bad", [-1, 1.5, "1G", True])
def test_a_bad_cap_names_the_argument(bad):
    with pytest.raises(ValueError, match="max_bytes"):
        CandidateCache("unused", max_bytes=bad)
