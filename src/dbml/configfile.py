"""Reading a config file from disk: the I/O edge in front of the pure ``parse_config``."""

from __future__ import annotations

from pathlib import Path

from dbml.core.config import Config, parse_config
from dbml.core.errors import ConfigError

__all__ = ["load_config"]


def load_config(path: str | Path, *, require_channels: bool = True) -> Config:
    """Read and validate a YAML config; an unreadable file is a ``ConfigError`` naming the path."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise ConfigError(f"config {str(path)!r}: cannot read: {reason}") from None
    return parse_config(text, source=f"config {str(path)!r}", require_channels=require_channels)
