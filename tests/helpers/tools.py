"""The tools as the tests drive them: tools/localize.py as a module, and Hydra composition."""
from __future__ import annotations

import importlib.util
import sys
from types import ModuleType
from typing import Iterable

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from tests.helpers.paths import CONF, REPO

LOCALIZE_TOOL = REPO / "tools" / "localize.py"


def localize_tool() -> ModuleType:
    """tools/localize.py as a module (registered before execution: it defines dataclasses)."""
    name = "icomma_tools_localize"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, LOCALIZE_TOOL)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


def compose(overrides: Iterable[str] = (), name: str = "localize", hydra_config: bool = False):
    """The config ``conf/<name>.yaml`` with ``overrides``, as the tool's command line has it.

    With ``hydra_config`` it keeps the ``hydra`` node (launcher, sweep folders).
    """
    GlobalHydra.instance().clear()  # a tool run in this process may have left Hydra initialized
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose(config_name=name, overrides=list(overrides),
                             return_hydra_config=hydra_config)
