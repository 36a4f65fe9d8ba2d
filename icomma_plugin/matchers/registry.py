"""Matchers by name or import path, and from a config mapping (the Hydra ``matcher`` group).

A matcher is a `Matcher` subclass that says what it is and needs in class attributes (`name`,
`weight_ids`, `python_modules`, `required_arguments`); a config names it by its import path:

    _target_: my_package.my_matchers.MyMatcher      # conf/matcher/my_matcher.yaml
    max_keypoints: 512                              # its keyword arguments

`matcher_from_config` builds it without Hydra (batch workers in spawned processes get the same
plain mapping), and Hydra's `instantiate` builds the same object from the same yaml. The built-in
matchers also have short names (`BUILTIN_MATCHERS`), for `make_matcher("xfeat")` and for a
mapping with `name` and no `_target_`.
"""
from __future__ import annotations

import importlib
import importlib.util
import inspect
from typing import Any, Callable, Dict, FrozenSet, Mapping, Optional

from .base import Matcher
from .weights import weights_status

__all__ = [
    "BUILTIN_MATCHERS", "HYDRA_KEYS", "available_matchers", "import_target", "make_matcher",
    "matcher_class", "matcher_from_config", "matcher_name",
]

#: Built-in matcher name -> import path of its class (the class's `name` is the same).
BUILTIN_MATCHERS: Dict[str, str] = {
    "xfeat": "icomma_plugin.matchers.xfeat.XFeatMatcher",
    "xfeat_mnn": "icomma_plugin.matchers.xfeat.XFeatMnnMatcher",
    "aliked_lightglue": "icomma_plugin.matchers.lightglue.AlikedLightGlueMatcher",
    "disk_lightglue": "icomma_plugin.matchers.lightglue.DiskLightGlueMatcher",
    "sift": "icomma_plugin.matchers.opencv.SiftMatcher",
    "orb": "icomma_plugin.matchers.opencv.OrbMatcher",
    "loftr": "icomma_plugin.matchers.loftr.LoFTRMatcher",
    "none": "icomma_plugin.matchers.simple.NoneMatcher",
    "fake": "icomma_plugin.matchers.simple.FakeMatcher",
}

#: Hydra's instantiate options: not arguments of the matcher.
HYDRA_KEYS = ("_convert_", "_recursive_", "_partial_")

_IMPORT_PATH_HELP = "an import path 'package.module.Class' (or a factory function)"


def _missing_module_is_prefix(exc: ModuleNotFoundError, module: str) -> bool:
    """Whether ``exc`` says ``module`` (or a package above it) does not exist.

    A module that exists but fails on one of its own imports is a different error.
    """
    missing = exc.name or ""
    return bool(missing) and (module == missing or module.startswith(missing + "."))


def import_target(path: Any, key: str = "_target_") -> Callable[..., Any]:
    """The object at the import path ``path`` ('package.module.Class', nested names allowed).

    Raises:
        ValueError: naming ``key``, when ``path`` is not a dotted path or cannot be imported.
    """
    if not isinstance(path, str) or "." not in path.strip(". "):
        raise ValueError(f"{key}: must be {_IMPORT_PATH_HELP}, got {path!r}")
    parts = path.strip().split(".")
    for split in range(len(parts) - 1, 0, -1):
        module_name = ".".join(parts[:split])
        try:
            obj = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if _missing_module_is_prefix(exc, module_name):
                continue
            raise ValueError(f"{key}: cannot import {path}: {exc}") from exc
        except ImportError as exc:
            raise ValueError(f"{key}: cannot import {path}: {exc}") from exc
        for attr in parts[split:]:
            if not hasattr(obj, attr):
                raise ValueError(
                    f"{key}: cannot import {path}: {obj.__name__} has no attribute {attr!r}"
                )
            obj = getattr(obj, attr)
        if not callable(obj):
            raise ValueError(f"{key}: {path} is a {type(obj).__name__}, not a class or function")
        return obj
    raise ValueError(f"{key}: cannot import {path}: no module {parts[0]!r}")


def _builtin_key(name: str) -> str:
    """The `BUILTIN_MATCHERS` key of ``name`` (case, '-' and '+' forgiven)."""
    key = name.strip().lower().replace("-", "_").replace("+", "_")
    if key not in BUILTIN_MATCHERS:
        raise ValueError(
            f"name must be one of {sorted(BUILTIN_MATCHERS)} or {_IMPORT_PATH_HELP}, got {name!r}"
        )
    return key


def matcher_class(name: Any) -> Callable[..., Any]:
    """The class (or factory) of a built-in matcher name or of an import path.

    Raises:
        ValueError: naming ``name``, when it is neither.
    """
    if not isinstance(name, str):
        raise ValueError(f"name must be a matcher name or import path (str), got "
                         f"{type(name).__name__}")
    if "." in name:
        return import_target(name, "name")
    return import_target(BUILTIN_MATCHERS[_builtin_key(name)])


def _checked_matcher(obj: Any, target: Any, key: str) -> Matcher:
    if not isinstance(obj, Matcher):
        raise ValueError(f"{key}: {getattr(target, '__qualname__', target)!r} built a "
                         f"{type(obj).__name__}, not an icomma_plugin.matchers.Matcher")
    return obj


def make_matcher(name: str, **kwargs) -> Matcher:
    """Build the matcher `name` (a built-in name or an import path) with its keyword arguments.

    See each class for its arguments; common ones (`Matcher`): `min_confidence`,
    `max_matches`, `refine={window, patch, temperature, ...}`, `min_detect_side`.

    Weights are loaded here, from packaged files or user paths only; a missing file raises
    `MissingWeightsError` (a FileNotFoundError and ValueError) with the pip command to fix it.

    Raises:
        ValueError: an unknown ``name``, or the class's own check of an argument.
    """
    target = matcher_class(name)
    return _checked_matcher(target(**kwargs), target, "name")


def accepted_arguments(target: Callable[..., Any]) -> Optional[FrozenSet[str]]:
    """The keyword arguments ``target`` takes; None when it takes any.

    For a class, the ``__init__`` chain is followed while each passes ``**kwargs`` on (as every
    matcher passes its own to `Matcher.__init__`).
    """
    if isinstance(target, type):
        inits = [vars(c)["__init__"] for c in target.__mro__ if "__init__" in vars(c)]
    else:
        inits = [target]
    names = set()
    for init in inits:
        try:
            params = inspect.signature(init).parameters.values()
        except (TypeError, ValueError):  # builtins without a signature
            return None
        kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        names |= {p.name for p in params if p.kind in kinds}
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
            return frozenset(names - {"self"})
    return None


def _named_error(exc: ValueError, key: str, arguments) -> ValueError:
    """``exc`` with its message prefixed by ``key.<argument>`` when it names one, else ``key``."""
    msg = str(exc)
    named = [a for a in sorted(arguments, key=len, reverse=True)
             if msg.startswith((f"{a} ", f"{a}:", f"{a}="))]
    prefix = f"{key}.{named[0]}" if named else key
    try:
        return type(exc)(f"{prefix}: {msg}")
    except TypeError:  # an exception class with another constructor
        return ValueError(f"{prefix}: {msg}")


def _build(target: Callable[..., Any], kwargs: Dict[str, Any], key: str) -> Matcher:
    """``target(**kwargs)``, its errors naming ``key`` and the argument."""
    accepted = accepted_arguments(target)
    what = getattr(target, "__qualname__", repr(target))
    if accepted is not None:
        for arg in kwargs:
            if arg not in accepted:
                raise ValueError(
                    f"{key}.{arg}: {what} takes no argument {arg!r}; it takes {sorted(accepted)}"
                )
    try:
        inspect.signature(target).bind(**kwargs)
    except TypeError as exc:  # a required argument missing
        raise ValueError(f"{key}: {what}: {exc}") from None
    except ValueError:  # no signature to check against
        pass
    try:
        obj = target(**kwargs)
    except ValueError as exc:
        raise _named_error(exc, key, set(kwargs) | set(accepted or ())) from exc
    return _checked_matcher(obj, target, f"{key}._target_")


def _target_of(spec: Dict[str, Any], key: str) -> Callable[..., Any]:
    """The class or factory a spec names; ``name`` is left in ``spec`` only if the target takes it.

    ``_target_`` is imported; without it ``name`` is looked up (a built-in or an import path).
    ``make_matcher`` as the target (the yaml style before import paths) reads as ``name``.
    """
    name = spec.pop("name", None)
    target = spec.pop("_target_", None)
    if target is not None:
        target = import_target(target, f"{key}._target_")
    if target is None or target is make_matcher:
        if name is None:
            raise ValueError(f"{key}: give _target_ ({_IMPORT_PATH_HELP}) or name (one of "
                             f"{sorted(BUILTIN_MATCHERS)})")
        try:
            return matcher_class(name)
        except ValueError as exc:
            raise ValueError(f"{key}.{exc}") from exc
    if name is not None:
        accepted = accepted_arguments(target)
        own = getattr(target, "name", None)
        if accepted is None or "name" in accepted:
            spec["name"] = name
        elif isinstance(own, str) and name != own:
            raise ValueError(f"{key}.name: {name!r}, but {key}._target_ builds the matcher "
                             f"{own!r}; drop name or make it {own!r}")
    return target


def matcher_from_config(spec: Optional[Mapping[str, Any]], key: str = "matcher"
                        ) -> Optional[Matcher]:
    """A matcher from a config mapping (the matcher group); None for no matcher.

    ``None``, ``{}`` or ``name: none`` give None. ``_target_`` is the import path of the class
    (or of a factory function) and the other keys are its keyword arguments, less Hydra's
    `HYDRA_KEYS`, and less ``name`` when the class does not take it (it must then be the class's
    own `name`). Without ``_target_``, ``name`` is a built-in name (`BUILTIN_MATCHERS`) or an
    import path. The mapping is only read (plain dicts pickle, for spawned batch workers).

    Args:
        spec: the mapping (plain Python: ``OmegaConf.to_container`` of a Hydra node).
        key: where the mapping sits in the config, for error messages.

    Raises:
        ValueError: naming the key (``matcher._target_: cannot import ...``,
            ``matcher.max_keypoints: ...``); `MissingWeightsError` (a ValueError) keeps its type.
    """
    if spec is None:
        return None
    if not isinstance(spec, Mapping):
        raise ValueError(f"{key} must be a mapping (_target_ and arguments) or None, got "
                         f"{type(spec).__name__}")
    kwargs = {str(k): v for k, v in spec.items() if k not in HYDRA_KEYS}
    if not kwargs or kwargs.get("name") == "none":
        return None
    reserved = sorted(k for k in kwargs if k.startswith("_") and k != "_target_")
    if reserved:
        raise ValueError(f"{key}.{reserved[0]}: not a matcher argument (Hydra keys other than "
                         f"{list(HYDRA_KEYS)} are not supported)")
    target = _target_of(kwargs, key)
    return _build(target, kwargs, key)


def matcher_name(matcher: Matcher) -> str:
    """The name a matcher is recorded under: its class's `name`, else its import path.

    The class's, not the instance's: ``xfeat`` stays ``xfeat`` when LighterGlue falls back to
    mutual nearest neighbours.
    """
    cls = type(matcher)
    own = next((vars(c)["name"] for c in cls.__mro__ if "name" in vars(c)), None)
    if not isinstance(own, str) or own == Matcher.name:
        return f"{cls.__module__}.{cls.__qualname__}"
    return own


def unavailable_reason(cls: type, weights: Mapping[str, Optional[str]]) -> Optional[str]:
    """Why ``cls`` cannot be built here as is (from its class attributes), or None.

    Args:
        cls: a `Matcher` subclass.
        weights: `weights.weights_status()` (weight id -> None or the reason).
    """
    for weight in getattr(cls, "weight_ids", ()):
        reason = weights.get(weight, f"{cls.__name__}.weight_ids: unknown weight id {weight!r}")
        if reason is not None:
            return reason
    for module, pypi in getattr(cls, "python_modules", {}).items():
        if importlib.util.find_spec(module) is None:
            return f"the Python module {module} is not installed: pip install {pypi}"
    for arg, what in getattr(cls, "required_arguments", {}).items():
        return f"needs {arg}: {what}"
    return None


def available_matchers() -> Dict[str, Optional[str]]:
    """Each built-in matcher's name -> None if it can be built here as is, else the reason.

    The reason (read from the class's `weight_ids`, `python_modules` and `required_arguments`)
    says what to install or pass.
    """
    status = weights_status()
    return {name: unavailable_reason(import_target(path), status)
            for name, path in BUILTIN_MATCHERS.items()}
