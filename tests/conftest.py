"""Shared fixtures: the shared data folder, the backend a test runs on, a network guard, seeds.

Backends: a test that needs the native CPU kernel asks for ``native_backend`` (a whole module:
``pytestmark = pytest.mark.usefixtures("native_backend")``); a test that runs on each CPU
backend asks for ``backend`` (and ``backend_dtype``); CUDA tests use ``cuda_backend``. Each
skips with the reason where that backend is not built, so no test file decides it for itself.
"""
from __future__ import annotations

import os
import socket
import tempfile
from pathlib import Path
from typing import Optional

import pytest
import torch

# Hypothesis (the reader fuzz tests) keeps its caches out of the repository.
os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY",
                      os.path.join(tempfile.gettempdir(), "icomma-hypothesis"))


# ----------------------------------------------------------------------------- shared data

def shared_data_root() -> Path:
    """Folder of the shared test data (`ICOMMA_SHARED_DATA`, default `../shared/data`)."""
    from icomma_plugin.io.datasets import shared_data_root as root

    return root()


@pytest.fixture
def shared_data() -> Path:
    root = shared_data_root()
    if not (root / "nerf_synthetic" / "lego_400" / "transforms_train.json").is_file():
        pytest.skip(f"shared test data not found at {root} (set ICOMMA_SHARED_DATA)")
    return root


@pytest.fixture
def lego_root(shared_data: Path) -> Path:
    return shared_data / "nerf_synthetic" / "lego_400"


@pytest.fixture
def fox_root() -> Path:
    """The fox phone capture (instant-ngp transforms.json) of the shared data."""
    root = shared_data_root() / "fox"
    if not (root / "transforms.json").is_file():
        pytest.skip(f"fox capture not found at {root} (set ICOMMA_SHARED_DATA)")
    return root


@pytest.fixture(scope="module")
def small_demo(tmp_path_factory) -> Path:
    """A 64x64 demo scene folder (built once per test module)."""
    from icomma_plugin.app.demo_scene import build_demo_scene

    path = tmp_path_factory.mktemp("demo") / "scene"
    build_demo_scene(path, seed=0, width=64, height=64)
    return path


# ----------------------------------------------------------------------------- backends

def _cuda_skip_reason() -> Optional[str]:
    from gaussian_renderer_pose._backend import native_status

    ok, why = native_status("cuda")
    if not torch.cuda.is_available():
        built = "" if ok else f"; {why}"
        return f"no CUDA device (torch.cuda.is_available() is False){built}"
    return None if ok else why


@pytest.fixture
def native_backend() -> str:
    """``"cpu"``, the native CPU kernel; skips the test, with the reason, where it is not built."""
    from gaussian_renderer_pose._backend import native_status

    ok, why = native_status("cpu")
    if not ok:
        pytest.skip(f"native CPU backend not built: {why}")
    return "cpu"


@pytest.fixture
def cuda_backend() -> str:
    """``"cuda"``; skips the test, with the reason, without a CUDA device and a CUDA build."""
    why = _cuda_skip_reason()
    if why is not None:
        pytest.skip(f"CUDA backend not testable here: {why}")
    return "cuda"


@pytest.fixture(params=["reference", "cpu"])
def backend(request) -> str:
    """Each CPU backend in turn: the pure-PyTorch reference, then the native kernel.

    The native run skips where the kernel is not built; the test's tensors should be of
    ``backend_dtype``.
    """
    if request.param == "cpu":
        return request.getfixturevalue("native_backend")
    return request.param


@pytest.fixture
def backend_dtype(backend: str) -> torch.dtype:
    """The dtype ``backend`` is tested in.

    float64 for the reference (exact enough to compare bits and finite differences), float32
    for the native kernel (the only dtype it takes).
    """
    return torch.float64 if backend == "reference" else torch.float32


# ----------------------------------------------------------------------------- process state

class NetworkBlocked(RuntimeError):
    pass


@pytest.fixture
def no_network(monkeypatch):
    """Any attempt to open a network connection fails loudly (weights must load offline)."""

    def refuse(*args, **kwargs):
        raise NetworkBlocked(f"network access attempted during a test: {args!r}")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setenv("KORNIA_DOWNLOAD_TIMEOUT", "1")
    yield


@pytest.fixture
def one_torch_thread():
    """One intra-op thread for the test, restored afterwards.

    On a shared 2-core box, OpenMP threads that spin while waiting make the CPU-heavy tests of
    small images about 3x slower in wall time (measured).
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session", autouse=True)
def _candidate_cache_dir(tmp_path_factory):
    """``ICOMMA_CACHE_DIR`` at a folder of this session: no test writes into ~/.cache.

    The Localizer keeps candidate indices on disk (``localization/candidate_cache.py``); tool runs
    that a test starts as subprocesses inherit the variable. A value set before the session is
    restored afterwards.
    """
    before = os.environ.get("ICOMMA_CACHE_DIR")
    os.environ["ICOMMA_CACHE_DIR"] = str(tmp_path_factory.mktemp("icomma-cache"))
    yield Path(os.environ["ICOMMA_CACHE_DIR"])
    if before is None:
        os.environ.pop("ICOMMA_CACHE_DIR", None)
    else:
        os.environ["ICOMMA_CACHE_DIR"] = before


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield
