"""The layers' import rules, checked on the source (every import statement, those inside
functions included, those only for type checking excepted):

- `rigbus` (the protocol both sides share) imports none of `hil`, `controllers`, `robots`;
- `controllers` (the controller side) imports neither `hil` nor `robots` (robot kinds' controller
  sides are found at run time through `rigbus.robots`);
- a robot's controller side (`robots.<kind>.controller`) imports neither `hil` nor its plant side;
- `hil` reaches the controller side only through its seam, `hil.seam`, and imports no robot
  (it finds them through `rigbus.robots`);
- no import circle: the graph of imports between softhil's modules has no cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("hil", "controllers", "rigbus", "robots")
SEAM = "hil.seam"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {
        module_name(path): path
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
    }


def _type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The softhil modules `name` imports: `from p import m` is module p.m where that is one,
    else p; relative imports resolved; blocks under `if TYPE_CHECKING:` skipped."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                found.add(candidate if candidate in known else base)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return {m for m in found if m.split(".")[0] in PACKAGES}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    found = modules()
    known = set(found)
    return {name: imports(name, path, known) for name, path in found.items()}


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_the_graph_is_read_from_every_layer(graph: dict[str, set[str]]) -> None:
    for package in PACKAGES:
        assert sum(_in(m, package) for m in graph) >= 4, package
    assert "rigbus.protocol" in graph["hil.plant"]  # the reader sees real imports
    assert "robots.planar_arm.controller.config" in graph["robots.planar_arm.plant.rig"]


def test_the_protocol_package_imports_neither_side(graph: dict[str, set[str]]) -> None:
    wrong = {
        (m, i)
        for m, targets in graph.items()
        if _in(m, "rigbus")
        for i in targets
        if not _in(i, "rigbus")
    }
    assert not wrong


def test_the_controller_side_imports_no_plant_and_no_robot(graph: dict[str, set[str]]) -> None:
    wrong = {
        (m, i)
        for m, targets in graph.items()
        if _in(m, "controllers")
        for i in targets
        if _in(i, "hil") or _in(i, "robots")
    }
    assert not wrong


def test_a_robots_controller_side_imports_no_plant(graph: dict[str, set[str]]) -> None:
    sides = [m for m in graph if m.startswith("robots.") and ".controller" in m]
    assert sides
    wrong = {(m, i) for m in sides for i in graph[m] if _in(i, "hil") or ".plant" in i}
    assert not wrong


def test_the_plant_reaches_the_controller_side_only_through_its_seam(
    graph: dict[str, set[str]],
) -> None:
    wrong = {
        (m, i)
        for m, targets in graph.items()
        if _in(m, "hil") and m != SEAM
        for i in targets
        if _in(i, "controllers") or _in(i, "robots")
    }
    assert not wrong
    assert any(_in(i, "controllers") for i in graph[SEAM])


def test_no_import_circle(graph: dict[str, set[str]]) -> None:
    """Tarjan's strongly connected components over the graph: every one a single module
    that does not import itself."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                connect(w)
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
            if len(component) > 1 or v in graph.get(v, ()):
                circles.append(sorted(component))

    import sys

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            connect(v)
    assert not circles
