"""The shape of the code: imports form no circle, point one way (grounder -> scene_export -> reconstruction ->
image2sim_common), reach into no other package's private module, and no module outgrows a room one reads in a sitting.

Read from the source with `ast` (nothing is imported), so a circle that only closes inside a function, where Python
would tolerate it at run time, counts too.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Lowest first: a package may import those below it, never one above.
LAYERS = ("image2sim_common", "reconstruction", "scene_export", "grounder")
MAX_MODULE_LINES = 850  # "about 800": a module past this is split by what it holds


def _modules() -> dict[str, Path]:
    out = {}
    for package in LAYERS:
        for path in sorted((REPO / package).rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The project module `name` lives in (`a.b.c` -> `a.b` when `c` is a name in module `a.b`), or None."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imports(module: str) -> Iterator[tuple[int, str]]:
    """(line, imported project module) for every import in `module`, at any depth (functions, TYPE_CHECKING)."""
    path = MODULES[module]
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _resolve(alias.name)
                if target:
                    yield node.lineno, target
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                target = _resolve(f"{base}.{alias.name}")
                if target and target != module:
                    yield node.lineno, target


GRAPH = {module: sorted({target for _, target in _imports(module)}) for module in MODULES}


def _cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each a circle of imports."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in graph[node]:
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_the_checker_sees_a_circle_and_the_project_modules() -> None:
    """The control: a planted circle is found, and the graph holds the modules and imports it should."""
    assert _cycles({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == [["a", "b", "c"]]
    assert _cycles({"a": ["b"], "b": []}) == []
    assert len(MODULES) > 60
    assert "image2sim_common.outdir" in GRAPH["scene_export._mjcf"]  # a top-level import
    assert "grounder.grounding.pipeline" in GRAPH["grounder.cli.scan"]  # an import inside a function


def test_no_import_circles() -> None:
    assert _cycles(GRAPH) == [], "modules that import each other (move what both need into a third, lower module)"


def test_imports_point_down_the_layers() -> None:
    rank = {package: i for i, package in enumerate(LAYERS)}
    upward = [
        f"{module} -> {target}"
        for module, targets in GRAPH.items()
        for target in targets
        if rank[target.split(".")[0]] > rank[module.split(".")[0]]
    ]
    assert upward == [], f"imports against the direction {' <- '.join(LAYERS)}"


def test_no_package_imports_another_packages_private_module() -> None:
    private = [
        f"{module}:{line} -> {target}"
        for module in MODULES
        for line, target in _imports(module)
        if target.split(".")[0] != module.split(".")[0] and any(p.startswith("_") for p in target.split(".")[1:])
    ]
    assert private == [], "import the package's public names instead (its __init__ / __all__)"


PACKAGES = sorted(module for module, path in MODULES.items() if path.name == "__init__.py")


@pytest.mark.parametrize("package", PACKAGES)
def test_each_package_says_what_it_offers(package: str) -> None:
    init = ast.parse(MODULES[package].read_text())
    assert ast.get_docstring(init), f"{package}/__init__.py has no docstring"
    assert any(
        isinstance(node, ast.Assign) and any(getattr(target, "id", None) == "__all__" for target in node.targets)
        for node in init.body
    ), f"{package}/__init__.py names nothing in __all__"


def test_modules_stay_small() -> None:
    large = {
        module: n for module, path in MODULES.items() if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert large == {}, f"modules over {MAX_MODULE_LINES} lines: split them by what they hold"
