"""Names a package exports but loads on first use (PEP 562), so importing it stays cheap.

The top-level ``dbml`` exports the runtime without starting it; a transport's package exports
its class without importing its middleware.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping

__all__ = ["lazy_names"]


def lazy_names(package: str, names: Mapping[str, str]) -> Callable[[str], object]:
    """A module ``__getattr__`` for ``package``: each of ``names`` from its module, once.

    ``names`` maps an exported name to the module that defines it; a name loaded is kept in the
    package, so the next lookup does not come back here.
    """

    def __getattr__(name: str) -> object:  # noqa: N807 (PEP 562's name)
        module = names.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
