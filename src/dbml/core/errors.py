"""Errors raised by dbml.

Every error dbml raises on purpose derives from one root, so a caller can catch them all::

    DbmlError
    ├── SpecError          a value that breaks a channel, link or problem rule
    │   └── ConfigError    a config file that cannot be read or does not follow the schema
    ├── TransportError     middleware missing or failing (runtime layers)
    └── MissingExtraError  an optional dependency not installed; names the extra that brings it

Messages name the field and the value, e.g.
``channel '/r1/camera': frequency.min=30 exceeds frequency.max=10``.
An infeasible budget is not an error: it is an allocation with status ``infeasible``.
"""

from __future__ import annotations

import sys

__all__ = ["ConfigError", "DbmlError", "MissingExtraError", "SpecError", "TransportError"]


class DbmlError(Exception):
    """Root of every error dbml raises on purpose."""


class SpecError(DbmlError, ValueError):
    """A channel, link or problem value breaks a rule of the model."""


class ConfigError(SpecError):
    """A config file cannot be read or does not follow the schema."""


class TransportError(DbmlError):
    """A transport is missing, misconfigured or failed."""


class MissingExtraError(DbmlError, ImportError):
    """A feature needs an optional dependency that this interpreter cannot import.

    ``pip install dbml`` brings the core, the runtime and the zenoh transport only; the message
    names the extra that installs the rest, e.g. ``--plot needs matplotlib, which
    /usr/bin/python3 cannot import: pip install 'dbml[plot]'``. It is an ``ImportError`` too, so
    code that already handles a missing module keeps handling it.
    """

    def __init__(self, what: str, package: str, *, extra: str, hint: str = "") -> None:
        super().__init__(
            f"{what} needs {package}, which {sys.executable} cannot import: "
            f"pip install 'dbml[{extra}]'{f' ({hint})' if hint else ''}"
        )
        self.what = what
        self.package = package
        self.extra = extra
