"""Glue shared by the command-line tools.

Process settings (threads, seeds), the one-line error exit, and building matchers and optimizer
configs from their Hydra groups (``_target_``).

Process-level settings belong to the tools, not the library: a library call never changes the
process's thread count or seeds.
"""
from __future__ import annotations

import ast
import contextlib
import json
import logging
import os
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import (Any, Callable, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple,
                    TypeVar)

import numpy as np
import torch

T = TypeVar("T")

__all__ = [
    "CheckoutWorker",
    "UserError",
    "apply_overrides",
    "build_matcher",
    "build_optimizer",
    "busy_cores_now",
    "check_backend",
    "choose_threads",
    "container",
    "git_describe",
    "parse_overrides",
    "passive_wait_note",
    "run_or_exit",
    "seed_everything",
    "thread_env",
    "torch_threads",
]


class UserError(ValueError):
    """Bad input from the command line or the config: reported as one line, no traceback."""


def _cpu_times(stat: str = "/proc/stat", cpus: Optional[Iterable[int]] = None
               ) -> Tuple[int, int]:
    """(all, idle) jiffies so far of the machine's CPUs (the ``cpu`` line of ``stat``).

    With ``cpus``, of those CPUs only (their ``cpuN`` lines, summed).
    """
    with open(stat) as f:
        lines = [ln.split() for ln in f]
    if cpus is None:
        wanted = [ln for ln in lines[:1] if ln and ln[0] == "cpu"]
        if not wanted or len(wanted[0]) < 5:
            raise ValueError(f"{stat}: no aggregate cpu line")
    else:
        names = {f"cpu{c}" for c in cpus}
        wanted = [ln for ln in lines if ln and ln[0] in names and len(ln) >= 5]
        if len(wanted) != len(names):
            raise ValueError(f"{stat}: lines of CPUs {sorted(names)} not all found")
    total = idle = 0
    for ln in wanted:
        ticks = [int(v) for v in ln[1:9]]  # user nice system idle iowait irq softirq steal
        total += sum(ticks)
        idle += ticks[3] + (ticks[4] if len(ticks) > 4 else 0)
    return total, idle


def busy_cores_now(seconds: float = 0.2, stat: str = "/proc/stat",
                   cpus: Optional[Iterable[int]] = None) -> Optional[float]:
    """How many cores other work keeps busy now: the non-idle share over ``seconds``.

    Of the whole machine, or of the CPUs ``cpus`` only (the ones this process may run on). This
    process sleeps meanwhile, so its own past work does not count. None where ``stat`` cannot
    be read (not Linux).
    """
    cpus = None if cpus is None else sorted(cpus)
    try:
        all0, idle0 = _cpu_times(stat, cpus)
        time.sleep(seconds)
        all1, idle1 = _cpu_times(stat, cpus)
    except (OSError, ValueError):
        return None
    if all1 <= all0:
        return None
    n = len(cpus) if cpus is not None else (os.cpu_count() or 1)
    return (1.0 - (idle1 - idle0) / (all1 - all0)) * n


def choose_threads(requested: Optional[int] = None) -> int:
    """Torch intra-op thread count: ``requested`` when positive, else automatic.

    Automatic means the cores left free by other work: round(cores - busy), at least 1, with
    busy the 1-minute load average, or the cores busy now (`busy_cores_now`) when that is fewer:
    the load average still counts a run that has just ended (after a 2-thread benchmark it read
    1.3-1.5 on the idle 2-core machine, and the next tool took 1 thread). Intra-op threads that
    share a core with another busy process stall at every OpenMP barrier: on a 2-core machine
    with one other busy process, 2 threads ran the demo ~15x slower than 1 thread (243 s vs
    15 s). A process pinned to some of the machine's cores (a cluster job's slot, ``taskset``)
    looks at those cores only: the machine's load average counts the other jobs' cores too.
    """
    if requested is not None and int(requested) > 0:
        return int(requested)
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    machine = os.cpu_count() or 1
    cores = len(cpus) if cpus else machine
    if cpus and cores < machine:  # pinned: the busy share of our own cores
        now = busy_cores_now(cpus=cpus)
        busy = now if now is not None else 0.0
        return max(1, min(cores, int(cores - busy + 0.5)))
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = 0.0
    if load > 0.5:  # busy, or busy a moment ago: look at now
        now = busy_cores_now()
        if now is not None:
            load = min(load, now)
    return max(1, min(cores, int(cores - load + 0.5)))


#: Environment variables that set how the OpenMP / MKL threads behave (recorded by benchmarks).
THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT",
              "KMP_BLOCKTIME", "OMP_PROC_BIND")


def thread_env() -> Dict[str, str]:
    """The ``THREAD_ENV`` variables that are set, and their values."""
    return {k: os.environ[k] for k in THREAD_ENV if k in os.environ}


def passive_wait_note(threads: int) -> Optional[str]:
    """What ``OMP_WAIT_POLICY=PASSIVE`` costs at ``threads`` threads (None: nothing).

    Passive OpenMP threads sleep between parallel regions, and each of the matcher's thousands
    of small operations a pose waits for them to wake: on the 2-core development machine a lego
    pose took 0.81 s with it and 0.53-0.61 s without, LighterGlue 81 against 29 ms a call
    (docs/SPEED.md, "The OpenMP wait policy").
    """
    if threads < 2 or os.environ.get("OMP_WAIT_POLICY", "").strip().upper() != "PASSIVE":
        return None
    return (f"OMP_WAIT_POLICY=PASSIVE is set: with {threads} threads the matcher's small "
            "operations wait for sleeping threads (a lego pose 1.3-1.9x slower on 2 cores); "
            "unset it unless other busy processes share these cores (docs/SPEED.md)")


@contextlib.contextmanager
def torch_threads(requested: Optional[int] = None) -> Iterator[int]:
    """Use ``choose_threads(requested)`` threads inside the block; restore torch's count after.

    Logs `passive_wait_note` when it applies.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(choose_threads(requested))
    note = passive_wait_note(torch.get_num_threads())
    if note:
        logging.getLogger("icomma").info(note)
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


def check_backend(backend: str) -> str:
    """``backend`` (the renderer group's), when this machine can run it; UserError otherwise."""
    from gaussian_renderer_pose import available_backends
    from icomma_plugin.checks import check_backend_here

    try:
        backend = check_backend_here(backend, "renderer")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if backend == "auto" and available_backends()["cuda"] is None:
        # auto renders where the model is, and models load on the CPU
        logging.getLogger("icomma").info(
            "a CUDA GPU and the CUDA kernel are here: renderer=cuda runs on the GPU "
            "(renderer=auto keeps the model on the CPU)")
    return backend


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch (matcher randomness, sampled perturbations)."""
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def output_dir_of(cfg, default: Path) -> Path:
    """A tool's output folder: ``output.dir`` when given, else ``default`` (Hydra's)."""
    return Path(cfg.output.get("dir") or default)


def run_or_exit(job: Callable[[], T], multirun: bool, log: logging.Logger) -> T:
    """Run a tool's job; bad input (ValueError / FileNotFoundError) becomes one ``error:`` line.

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


def parse_overrides(items: Sequence[str], flag: str = "--set") -> List[Tuple[str, Any]]:
    """``(key, value)`` of each ``key=value`` override of a tool's ``--set``.

    The one syntax of every tool's ``--set``: values are YAML (``0.5``, ``[1.0, 0.5]``, ``null``,
    ``true``), and a Python literal where YAML reads only a string (``(0.2,)``, ``None``).

    Raises:
        ValueError: an item without ``=`` or without a key (naming ``flag``).
    """
    import yaml

    out = []
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"{flag}: expected key=value, got {item!r}")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:  # not YAML ("[1, 2"): a literal, else the text as it is
            value = text
        if isinstance(value, str):
            try:
                value = ast.literal_eval(text.strip())
            except (ValueError, SyntaxError):
                pass
        out.append((key, value))
    return out


def apply_overrides(config: Dict[str, Any], items: Sequence[str], what: str,
                    flag: str = "--set") -> Dict[str, Any]:
    """A copy of the nested dict ``config`` with ``dotted.key=value`` overrides applied.

    Values as :func:`parse_overrides` reads them; a key must exist in ``config`` (``what`` names
    the config in the error).

    Raises:
        ValueError: a malformed item, or a key ``config`` does not have.
    """
    out = json.loads(json.dumps(config))
    for key, value in parse_overrides(items, flag):
        *path, leaf = key.split(".")
        node = out
        for part in path:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            raise ValueError(f"{flag}: {what} has no key {key!r}")
        node[leaf] = value
    return out


def container(node) -> Any:
    """A Hydra/OmegaConf node as plain Python (dicts, lists), interpolations resolved."""
    from omegaconf import OmegaConf

    if node is None:
        return None
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def build_matcher(mcfg, key: str = "matcher") -> Tuple[Any, Optional[str]]:
    """Build the matcher of the matcher group mounted at ``key``.

    A thin call of ``icomma_plugin.matchers.matcher_from_config`` (as the batch workers build
    theirs, from the same plain mapping).

    Returns:
        (matcher, its name); (None, None) for ``none`` or a removed group.

    Raises:
        UserError: a bad group, naming the key (``matcher.checkpoint: ...`` for LoFTR without
            its checkpoint file, ``matcher._target_: cannot import ...``).
    """
    from icomma_plugin.matchers import matcher_from_config, matcher_name

    try:
        matcher = matcher_from_config(container(mcfg), key)
    except ValueError as e:
        raise UserError(str(e)) from e
    return (None, None) if matcher is None else (matcher, matcher_name(matcher))


def build_optimizer(ocfg, key: str = "optimizer"):
    """Build the method config of an optimizer group mounted at ``key``.

    Returns:
        A ``RobustConfig`` or the paper's ``LocalizerConfig``; a group without ``_target_`` is
        read as the paper's config.

    Raises:
        UserError: the config's own ValueError/TypeError, prefixed with ``key``.
    """
    from hydra.utils import instantiate

    from icomma_plugin.localize import LocalizerConfig

    d = container(ocfg)
    if "_target_" not in d:
        return LocalizerConfig.from_dict(d)
    try:
        return instantiate(d, _convert_="all")
    except Exception as e:  # noqa: BLE001 - instantiate wraps the config's own ValueError
        cause = e.__cause__ or e
        if isinstance(cause, (ValueError, TypeError)):
            raise UserError(f"{key}: {cause}") from None
        raise


# ----------------------------------------------------------------------------------------------
# Benchmarks against another checkout (--checkouts)
# ----------------------------------------------------------------------------------------------
class CheckoutWorker:
    """A process that runs ``script --worker ROOT`` with ``root``'s packages on its path.

    The benchmarks' way to time two checkouts in one run: the worker answers JSON requests, one
    line each on stdin / stdout. Its first line must be ``{"package": path}``, the folder of the
    package it imported, which must lie in ``root`` (else the comparison would time the wrong
    code). ``flag`` names the command-line option in the errors.
    """

    def __init__(self, root: Path, script: Path, flag: str):
        self.root = root
        self.flag = flag
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(script).resolve()), "--worker", str(root)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(root),
            env={**os.environ, "PYTHONPATH": str(root)},
        )
        package = Path(self._read()["package"])
        if package.parent != root:
            self.close()
            raise ValueError(f"{flag}: {root} imported {package.name} from {package}")
        self.name = f"{root.name}@{git_describe(root)}"

    def _read(self) -> Dict[str, Any]:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.flag}: the worker for {self.root} exited "
                               f"(rc {self.proc.poll()})")
        return json.loads(line)

    def ask(self, **request) -> Dict[str, Any]:
        """Send one request and return the reply."""
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        """Stop the worker."""
        if self.proc.poll() is None:
            try:
                self.ask(cmd="quit")
            except (BrokenPipeError, RuntimeError):
                pass
            self.proc.wait(timeout=60)


def git_describe(root: Path) -> str:
    """Short commit of ``root`` ("+" when its tracked files differ from it), or "?"."""
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "diff", "--quiet", "HEAD"],
                               capture_output=True).returncode != 0
    except (OSError, subprocess.CalledProcessError):
        return "?"
    return head + ("+" if dirty else "")
