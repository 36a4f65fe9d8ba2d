"""Keep freed memory in the process's heap (glibc's malloc): a loop need not fault it in again.

The fitter's step allocates and frees the same image-sized tensors every step (the loss's SSIM
terms, the render and its gradients: 0.5-7 MB each at 272x480-540x960). glibc's malloc maps a
block above its mmap threshold fresh from the kernel and unmaps it when freed, and gives the
heap's free top back to the kernel above its trim threshold; both thresholds move with what the
process happened to free before. So the same step can page-fault its working memory in every time
in one process and not in another: fox at 540x960 took 177 against 135 ms a step (its loss 88
against 51 ms) depending only on these settings (docs/FITTING.md, "Freed memory kept").

`retain_freed_memory` fixes both: blocks up to `MMAP_THRESHOLD_BYTES` come from the heap, and up
to `TRIM_THRESHOLD_BYTES` of free heap top stay with the process. The price is a resident size
that stays near the process's peak instead of shrinking after it. It is process-wide, so a
library calls it only where it owns the run (the fitter's `Trainer`); nothing happens where the
C library is not glibc, or where the user set ``MALLOC_MMAP_THRESHOLD_`` or
``MALLOC_TRIM_THRESHOLD_`` (glibc's own environment variables: theirs are kept).
"""
from __future__ import annotations

import ctypes
import os
import sys
from typing import Optional

#: glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: glibc's largest mmap threshold on 64-bit systems (4 * 1024 * 1024 * sizeof(long)): larger
#: blocks (a million Gaussians' SH: 190 MB) are still mapped and unmapped on their own
MMAP_THRESHOLD_BYTES = 32 << 20
#: free heap top kept before it is given back
TRIM_THRESHOLD_BYTES = 1 << 30
#: the environment variables of glibc that set the same thresholds
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")

_applied: Optional[bool] = None


def retain_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds for a loop of same-sized allocations (once a process).

    Returns:
        True when the thresholds are set (now or by an earlier call); False where they cannot be
        (not Linux with glibc) or the user set them (`USER_SETTINGS`).
    """
    global _applied
    if _applied is None:
        _applied = _set_thresholds()
    return _applied


def _set_thresholds() -> bool:
    if not sys.platform.startswith("linux") or any(v in os.environ for v in USER_SETTINGS):
        return False
    try:
        libc = ctypes.CDLL(None)  # the symbols of the process: its C library's among them
        if not hasattr(libc, "gnu_get_libc_version"):  # musl & co: a mallopt that does nothing
            return False
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
                and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
