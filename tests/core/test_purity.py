import ast
import subprocess
import sys
from pathlib import Path

import dbml.estimator

PURE_IMPORTS = {
    "__future__",
    "bisect",
    "collections",
    "collections.abc",
    "dataclasses",
    "enum",
    "heapq",
    "itertools",
    "math",
    "statistics",
    "typing",
}
"""What the estimator may import besides dbml's pure core and itself: no I/O, threads, clocks."""


def _loaded_after(imports: str) -> list[str]:
    """Middleware and the runtime's modules that ``imports`` loads in a fresh interpreter."""
    code = (
        f"import sys, {imports}; "
        "bad = [m for m in sys.modules "
        "if m.split('.')[0] in {'zenoh', 'rospy', 'rosgraph', 'rich', 'rclpy'} "
        "or m.startswith(('dbml.runtime', 'dbml.transports', 'dbml.testbed', 'dbml.cli'))]; "
        "print(','.join(sorted(bad)))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    return [m for m in result.stdout.strip().split(",") if m]


def test_core_imports_no_middleware_runtime_or_threads() -> None:
    assert _loaded_after("dbml.core, dbml.scenarios") == []


def test_the_estimator_and_its_messages_import_no_middleware_runtime_or_threads() -> None:
    """The estimator is pure, and the wire messages need nothing of the runtime."""
    assert _loaded_after("dbml.estimator, dbml.protocol.messages") == []


def test_the_estimator_imports_only_pure_modules() -> None:
    """Read from its source: no module of it reaches for I/O, threads, clocks or the network."""
    package = Path(dbml.estimator.__file__).parent
    modules = sorted(package.glob("*.py"))
    assert len(modules) >= 6
    for path in modules:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                found = [node.module or ""]
            else:
                continue
            for name in found:
                pure = name in PURE_IMPORTS or name.startswith(
                    ("dbml.estimator", "dbml.core.errors", "dbml.core.spec")
                )
                assert pure, f"{path.name} imports {name}"
