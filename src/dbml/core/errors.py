"""Errors raised by dbml.

Every error dbml raises on purpose derives from one root, so a caller can catch them all::

    DbmlError
    ├── SpecError       a value that breaks a channel, link or problem rule
    │   └── ConfigError a config file that cannot be read or does not follow the schema
    └── TransportError  middleware missing or failing (runtime layers)

Messages name the field and the value, e.g.
``channel '/r1/camera': frequency.min=30 exceeds frequency.max=10``.
An infeasible budget is not an error: it is an allocation with status ``infeasible``.
"""

from __future__ import annotations

__all__ = ["ConfigError", "DbmlError", "SpecError", "TransportError"]


class DbmlError(Exception):
    """Root of every error dbml raises on purpose."""


class SpecError(DbmlError, ValueError):
    """A channel, link or problem value breaks a rule of the model."""


class ConfigError(SpecError):
    """A config file cannot be read or does not follow the schema."""


class TransportError(DbmlError):
    """A transport is missing, misconfigured or failed."""
