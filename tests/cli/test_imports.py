"""The command line is the library's edge: no module of the library imports it."""

from __future__ import annotations

import ast
from pathlib import Path

import dbml

PACKAGE = Path(dbml.__file__).parent
EDGE = ("dbml.cli", "dbml.__main__")
"""The command line and ``python -m dbml``, which runs it."""


def _imported(path: Path) -> set[str]:
    """Every dbml module ``path`` imports, at its top or inside a function."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return {name for name in found if name == "dbml" or name.startswith("dbml.")}


def test_no_module_of_the_library_imports_the_command_line() -> None:
    importers = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(("dbml", *path.relative_to(PACKAGE).with_suffix("").parts))
        if module.startswith(EDGE):
            continue
        if any(name == "dbml.cli" or name.startswith("dbml.cli.") for name in _imported(path)):
            importers.append(module)
    assert importers == []


def test_the_check_sees_an_import_of_the_command_line(tmp_path: Path) -> None:
    module = tmp_path / "user.py"
    module.write_text("def run() -> None:\n    from dbml.cli.main import main\n")
    assert "dbml.cli.main" in _imported(module)
