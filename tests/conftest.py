"""Shared fixtures: the shared data folder, a network guard, seeds."""
from __future__ import annotations

import socket
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]


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


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    yield
