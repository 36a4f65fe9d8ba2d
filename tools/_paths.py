"""Where the tools' Hydra configs live: in a checkout, an editable install or a regular install.

A regular install ships the configs as package data in ``icomma_tools/conf`` (setup.py); a
checkout and an editable install (whose ``icomma_tools`` is this ``tools/`` folder) use the
repository's ``conf/``. The package's own copy wins, so that an installed tool never picks up an
unrelated ``conf/`` folder beside site-packages.
"""
from __future__ import annotations

from pathlib import Path

_HERE = Path(__file__).resolve().parent

__all__ = ["CONFIG_DIR", "find_config_dir"]


def find_config_dir() -> str:
    """Absolute path of the config folder (Hydra's ``config_path`` accepts it as is).

    Raises:
        FileNotFoundError: neither ``<package>/conf`` nor ``<checkout>/conf`` holds localize.yaml
            (a broken install); the message names both places.
    """
    candidates = (_HERE / "conf", _HERE.parent / "conf")
    for folder in candidates:
        if (folder / "localize.yaml").is_file():
            return str(folder)
    raise FileNotFoundError(
        "icomma's Hydra configs were not found: looked for localize.yaml in "
        + " and ".join(str(c) for c in candidates)
        + " (reinstall with `pip install --no-build-isolation .` from the repository)")


#: The config folder of every Hydra tool: ``@hydra.main(config_path=CONFIG_DIR, ...)``.
CONFIG_DIR = find_config_dir()
