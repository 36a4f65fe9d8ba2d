"""icomma_plugin.heap: freed memory kept in the heap, so that a loop does not fault it in again."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from icomma_plugin import heap

GLIBC = sys.platform.startswith("linux") and os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc")

# The fitter's loss and its gradient at 480x272 (bird's photos), 10 times after 5 warm-up calls
# on 2 threads; prints whether the helper applied and the page faults of the 10 calls. Without it,
# glibc gave each call's 50 MB of temporaries back and faulted them in again (120,000-137,000
# faults); with it, 0-3,825 (a tensor of 1.5 MB now and then, in a thread's own arena).
_LOOP = textwrap.dedent("""
    import resource, sys, torch
    from icomma_plugin.heap import retain_freed_memory
    from icomma_plugin.fit.losses import photometric_loss_and_grad

    torch.set_num_threads(2)
    applied = retain_freed_memory() if sys.argv[1] == "1" else None
    g = torch.Generator().manual_seed(0)
    render, photo = torch.rand(3, 480, 272, generator=g), torch.rand(3, 480, 272, generator=g)
    for _ in range(5):
        photometric_loss_and_grad(render, photo, 0.2)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        photometric_loss_and_grad(render, photo, 0.2)
    print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
""")


def _run_loop(helper: bool, **env) -> tuple:
    full_env = {k: v for k, v in os.environ.items() if k not in heap.USER_SETTINGS}
    full_env.update(env)
    out = subprocess.run([sys.executable, "-c", _LOOP, "1" if helper else "0"], env=full_env,
                         capture_output=True, text=True, check=True, timeout=120)
    applied, faults = out.stdout.split()
    return applied, int(faults)


@pytest.mark.skipif(not GLIBC, reason="the thresholds are glibc's")
def test_the_loss_stops_faulting_its_memory_in():
    applied, kept = _run_loop(True)
    assert applied == "True"
    _, plain = _run_loop(False)
    if plain < 10_000:
        pytest.skip(f"this C library kept the memory without the helper ({plain} faults)")
    assert kept * 10 < plain, (kept, plain)


@pytest.mark.skipif(not GLIBC, reason="the thresholds are glibc's")
def test_the_users_own_settings_are_kept():
    applied, _ = _run_loop(True, MALLOC_TRIM_THRESHOLD_="131072")
    assert applied == "False"


def test_once_a_process(monkeypatch):
    calls = []
    monkeypatch.setattr(heap, "_applied", None)
    monkeypatch.setattr(heap, "_set_thresholds", lambda: calls.append(1) or GLIBC)
    assert heap.retain_freed_memory() is GLIBC
    assert heap.retain_freed_memory() is GLIBC
    assert calls == [1]


def test_the_fitter_keeps_its_memory(monkeypatch):
    from icomma_plugin.fit import trainer
    from icomma_plugin.fit.timing import _probe_trainer

    calls = []
    monkeypatch.setattr(trainer, "retain_freed_memory", lambda: calls.append(1) or True)
    _probe_trainer(num_gaussians=50, side=16)
    assert calls == [1]
