"""The dependency direction of the packages, and no import cycles (read from the sources).

tools -> application (icomma_plugin.app, .benchmark, .fit) -> pictures (icomma_plugin.pictures) ->
core (the rest of icomma_plugin) -> gaussian_renderer_pose. Every import counts, also the ones
inside functions: a lazy import is still a dependency. Only the tools import Hydra
(tests/tools/test_configs.py checks that).
"""
from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("gaussian_renderer_pose", "icomma_plugin")
APPLICATION = ("icomma_plugin.app", "icomma_plugin.benchmark", "icomma_plugin.fit")
PICTURES = ("icomma_plugin.pictures",)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> Dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _imports(name: str, path: Path, modules: Dict[str, Path]) -> Set[str]:
    """The project modules ``name`` imports.

    A name imported from a package counts as the submodule when there is one, else as the
    package.
    """
    deps: Set[str] = set()
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            deps |= {a.name for a in node.names if a.name.split(".")[0] in PACKAGES}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] not in PACKAGES:
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                deps.add(sub if sub in modules else target)
    return {d for d in deps if d in modules and d != name}


def _graph() -> Dict[str, Set[str]]:
    modules = _modules()
    return {m: _imports(m, p, modules) for m, p in modules.items()}


def _cycles(graph: Dict[str, Set[str]]) -> List[List[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on_stack: Set[str] = set()
    out: List[List[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _layer(module: str) -> str:
    if module.startswith("gaussian_renderer_pose"):
        return "rasterizer"
    if module.startswith(APPLICATION):
        return "application"
    if module.startswith(PICTURES):
        return "pictures"
    return "core"


#: What each layer may import.
ALLOWED = {
    "rasterizer": {"rasterizer"},
    "core": {"rasterizer", "core"},
    "pictures": {"rasterizer", "core", "pictures"},
    "application": {"rasterizer", "core", "pictures", "application"},
}


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_the_core_never_imports_application_or_picture_code():
    bad = sorted(f"{m} -> {d}" for m, deps in _graph().items() for d in deps
                 if _layer(d) not in ALLOWED[_layer(m)])
    assert bad == []


def test_the_checks_can_fail():
    """The checks above see a cycle and a core-to-application import when there is one."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _layer("icomma_plugin.app.batch.worker") == "application"
    assert "application" not in ALLOWED[_layer("icomma_plugin.localization.localizer")]
    graph = _graph()
    assert "icomma_plugin.localization.localizer" in graph["icomma_plugin.localize"]
    assert "icomma_plugin.localization.types" in graph["icomma_plugin.localization.state"]
