"""Process-level settings shared by the command-line tools (torch thread count)."""
from __future__ import annotations

import contextlib
import logging
import os
import sys
from typing import Callable, Iterator, Optional, TypeVar

import torch

T = TypeVar("T")


def choose_threads(requested: Optional[int] = None) -> int:
    """Torch intra-op thread count: `requested` when positive, else automatic.

    Automatic means the cores left free by other work: round(cores - 1-minute load average),
    at least 1. Intra-op threads that share a core with another busy process stall at every
    OpenMP barrier: on a 2-core machine with one other busy process, 2 threads ran the demo ~15x
    slower than 1 thread (243 s vs 15 s).
    """
    if requested is not None and int(requested) > 0:
        return int(requested)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = 0.0
    return max(1, min(cores, int(cores - load + 0.5)))


@contextlib.contextmanager
def torch_threads(requested: Optional[int] = None) -> Iterator[int]:
    """Use `choose_threads(requested)` threads inside the block; restore torch's count after."""
    before = torch.get_num_threads()
    torch.set_num_threads(choose_threads(requested))
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def run_or_exit(job: Callable[[], T], multirun: bool, log: logging.Logger) -> T:
    """Run a tool's job; bad input (ValueError / FileNotFoundError) becomes one `error:` line.

    A single run exits with status 2 after printing the line to stderr; in a multirun sweep the
    error is logged and re-raised so the launcher records the failed job.
    """
    try:
        return job()
    except (ValueError, FileNotFoundError) as e:
        msg = f"error: {e}"
        if multirun:
            log.error(msg)
            raise
        print(msg, file=sys.stderr)
        sys.exit(2)
