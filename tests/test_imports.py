"""No import circle in src/dbml: the graph of who imports whom, read from the source, has no cycle.

Every ``import`` and ``from ... import`` statement counts, wherever it is: at the top, inside a
function (a lazy import still ties the two modules together) or under ``TYPE_CHECKING`` (a
type is part of the module's contract). ``from package import name`` is an edge to the
submodule when ``name`` is one, else to the package.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import dbml

SRC = Path(dbml.__file__).resolve().parent
"""src/dbml."""

KNOWN_CYCLES: frozenset[frozenset[str]] = frozenset()
"""Cycles still to break, each as the set of its modules; the list only shrinks.

A new cycle fails the test; one listed here that no longer exists fails it too (remove it).
"""


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for path in sorted(SRC.rglob("*.py"))}


def imported(name: str, path: Path, known: dict[str, Path]) -> Iterator[str]:
    """The dbml modules that ``name`` (at ``path``) imports, by every statement in it."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in known:
                    yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                if submodule in known:
                    yield submodule
                elif source in known:
                    yield source


def graph() -> dict[str, set[str]]:
    known = modules()
    return {
        name: {target for target in imported(name, path, known) if target != name}
        for name, path in known.items()
    }


def cycles(edges: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []

    def visit(start: str) -> None:
        # Iterative: a deep chain of imports must not hit the recursion limit.
        work: list[tuple[str, Iterator[str]]] = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, targets = work[-1]
            target = next(targets, None)
            if target is not None:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(sorted(edges[target]))))
                elif target in on_stack:
                    low[node] = min(low[node], index[target])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(frozenset(component))

    for name in sorted(edges):
        if name not in index:
            visit(name)
    return found


def test_the_graph_is_read_from_every_statement() -> None:
    edges = graph()
    # A module-level import, a function's lazy one, a TYPE_CHECKING one and a relative one.
    assert "dbml.core.errors" in edges["dbml.transports.base"]
    assert "dbml.transports.zenoh.transport" in edges["dbml.transports.zenoh"]
    assert "dbml.runtime.publisher" in edges["dbml"]


def test_cycles_are_found() -> None:
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e"}}
    assert cycles(edges) == [frozenset({"a", "b", "c"})]


def test_no_module_of_dbml_is_in_an_import_circle() -> None:
    found = set(cycles(graph()))
    new = found - KNOWN_CYCLES
    assert not new, "import circles: " + "; ".join(" <-> ".join(sorted(c)) for c in new)
    assert not KNOWN_CYCLES - found, "listed circles that are gone: remove them from the list"


def test_the_core_imports_nothing_of_dbml_but_itself() -> None:
    """The layers below everything: the core (the model) is what every other package builds on."""
    edges = graph()
    outside = {
        (name, target)
        for name, targets in edges.items()
        if name.startswith("dbml.core")
        for target in targets
        if not target.startswith("dbml.core")
    }
    assert outside == set()
