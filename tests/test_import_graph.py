"""The package's import graph: imports run one way, and there is no import cycle.

recipes -> trainers -> {runs, world_model, objectives, modules, envs, data, collectors};
analysis reads run folders through ``runs.layout`` and is imported by nothing in the package.
The graph is read from the source with :mod:`ast` (every import, also those inside functions
and ``TYPE_CHECKING`` blocks, unless a test says otherwise), so nothing is imported here.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "torchrl_mbmf"
NAME = PACKAGE.name

#: The floors below the training loop: they never import ``trainers``.
LOWER = ("runs", "world_model", "objectives", "modules", "envs", "data", "collectors")
#: Top-level modules every floor may use.
LEAVES = ("checks", "device", "keys", "methods", "moved", "offscreen")
#: Consumers of the package that nothing in it imports.
CONSUMERS = ("analysis", "baselines")


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.Module, module_scope: bool) -> list[ast.Import | ast.ImportFrom]:
    """Every import, or only those run when the module is imported (``module_scope``)."""
    if not module_scope:
        return [n for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)]
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import | ast.ImportFrom):
                found.append(node)
            elif isinstance(node, ast.If):
                if not _is_type_checking(node):
                    visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                for block in (
                    node.body,
                    node.orelse,
                    node.finalbody,
                    *(h.body for h in node.handlers),
                ):
                    visit(block)

    visit(tree.body)
    return found


def _imported_modules(name: str, module_scope: bool = False) -> set[str]:
    """The package's modules that module ``name`` imports (a submodule when one is named)."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets: set[str] = set()
    for node in _import_nodes(ast.parse(path.read_text()), module_scope):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
            continue
        base = node.module or ""
        if node.level:
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
        for alias in node.names:
            sub = f"{base}.{alias.name}"
            targets.add(sub if sub in MODULES else base)
    return {t for t in targets if t == NAME or t.startswith(NAME + ".")} - {name}


def _floor(module: str) -> str:
    """The subpackage (or top-level module) a module belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _floor_graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for name in MODULES:
        floor = _floor(name)
        graph.setdefault(floor, set()).update(
            _floor(t) for t in _imported_modules(name) if _floor(t) != floor
        )
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_is_read():
    graph = _floor_graph()
    assert {"runs", "world_model", "collectors", "objectives"} <= graph["trainers"]
    assert "runs" in graph["analysis"] and "modules" in graph["envs"]


def test_cycles_are_found():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize("floor", [*LOWER, *LEAVES, *CONSUMERS])
def test_nothing_below_the_loop_imports_it(floor):
    offenders = sorted(
        f"{name} -> {target}"
        for name in MODULES
        if _floor(name) == floor
        for target in _imported_modules(name)
        if _floor(target) == "trainers"
    )
    assert not offenders, f"imports run recipes -> trainers -> {LOWER}: {offenders}"


def test_nothing_in_the_package_imports_its_consumers():
    offenders = sorted(
        f"{name} -> {target}"
        for name in MODULES
        for target in _imported_modules(name)
        if _floor(target) in CONSUMERS and _floor(name) != _floor(target)
    )
    assert not offenders


def test_leaf_modules_import_no_floor():
    for leaf in LEAVES:
        assert not _imported_modules(f"{NAME}.{leaf}"), leaf


def test_no_cycle_between_subpackages():
    assert _cycles(_floor_graph()) == []


def test_no_cycle_between_modules_at_import_time():
    graph = {name: _imported_modules(name, module_scope=True) for name in MODULES}
    assert _cycles(graph) == []


def _layout_names() -> dict[str, str]:
    """The run folder's file names: ``runs.layout``'s upper-case string constants."""
    tree = ast.parse(MODULES[f"{NAME}.runs.layout"].read_text())
    names = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant):
            value = node.value.value
            for target in node.targets:
                if isinstance(target, ast.Name) and target.id.isupper() and isinstance(value, str):
                    names[value] = target.id
    return names


def _code_strings(tree: ast.Module) -> list[ast.Constant]:
    """String constants outside docstrings."""
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    return [
        node
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and id(node) not in docstrings
    ]


#: (file, literal): written by the analysis into its own folders, not read from a run folder.
OWN_FILES = {("world_model_job.py", "summary.json")}


def test_analysis_reads_run_folders_through_the_layout():
    names = _layout_names()
    assert {"config.yaml", "policy.pt", "checkpoints"} <= set(names)
    runs_modules, literals = set(), []
    for name, path in MODULES.items():
        if _floor(name) != "analysis":
            continue
        runs_modules |= {t for t in _imported_modules(name) if _floor(t) == "runs"}
        for node in _code_strings(ast.parse(path.read_text())):
            if node.value in names and (path.name, node.value) not in OWN_FILES:
                literals.append(
                    f"{path.name}:{node.lineno} {node.value!r} (runs.layout.{names[node.value]})"
                )
    # the layout names every file; export holds the policy file's reader (load_policy)
    assert runs_modules <= {f"{NAME}.runs.layout", f"{NAME}.runs.export"}, runs_modules
    assert not literals, f"use the names of runs.layout: {literals}"
