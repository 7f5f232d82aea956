"""Optional dependencies, imported where a feature needs them.

``pip install dbml`` installs what the allocator, the runtime and the zenoh transport need; the
rest comes with an extra (``ros2``, ``secure``, ``plot``), so ``import dbml`` and the commands
that do not need them work without them. A feature that does calls :func:`require` first: its
one-line error names the extra to install.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from dbml.core.errors import MissingExtraError

__all__ = ["EXTRAS", "require"]

EXTRAS = ("plot", "quality", "rclpy", "ros2", "secure", "viz")
"""The extras of ``pip install 'dbml[...]'`` (``all`` and ``dev`` include every one)."""


def require(
    module: str, *, extra: str, what: str, package: str | None = None, hint: str = ""
) -> ModuleType:
    """Import ``module`` for ``what``, or raise ``MissingExtraError`` naming ``extra``.

    ``package`` is the name pip knows (default: ``module``'s top level); ``hint`` another way
    to get it (a sourced ROS 2 brings rclpy). Call it before the
    feature's typed ``import`` lines, so they run only once the module is known to import.
    """
    if extra not in EXTRAS:
        raise ValueError(f"extra={extra!r} is not one of: {', '.join(EXTRAS)}")
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise MissingExtraError(
            what, package or module.partition(".")[0], extra=extra, hint=hint
        ) from err
