"""Where a live view goes (``--foxglove [HOST:]PORT``, ``--record FILE.mcap``), checked up front.

Pure and free of foxglove-sdk: the command line checks the flags before a run starts, and a
role process of the demo or the testbed gets them as text in its spec.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from dbml.core.errors import DbmlError

__all__ = ["DEFAULT_HOST", "MAX_PORT", "ViewEndpoint", "ViewTarget", "parse_endpoint"]

DEFAULT_HOST = "127.0.0.1"
"""Where ``--foxglove PORT`` listens: this machine only, unless a host is given."""
MAX_PORT = 65535
_ENDPOINT = re.compile(r"^(?:(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):)?(?P<port>[0-9]+)$")


@dataclass(frozen=True, slots=True)
class ViewEndpoint:
    """Where the WebSocket server listens; port 0 picks a free one."""

    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


def parse_endpoint(text: str, *, field: str = "--foxglove") -> ViewEndpoint:
    """``[HOST:]PORT`` (``8765``, ``0.0.0.0:8765``, ``[::1]:8765``), or ``DbmlError`` naming it."""
    match = _ENDPOINT.match(text)
    if match is None:
        raise DbmlError(f"{field}={text!r} must be [HOST:]PORT, e.g. 8765 or 0.0.0.0:8765")
    port = int(match.group("port"))
    if port > MAX_PORT:
        raise DbmlError(f"{field}={text!r}: the port must be in 0-{MAX_PORT}")
    host = match.group("host") or DEFAULT_HOST
    return ViewEndpoint(host.strip("[]"), port)


@dataclass(frozen=True, slots=True)
class ViewTarget:
    """A live view's server and recording (either may be None, not both)."""

    endpoint: ViewEndpoint | None
    record: Path | None

    @classmethod
    def from_flags(cls, foxglove: str | None, record: str | None) -> ViewTarget | None:
        """The flags' target, None without either; ``DbmlError`` naming a bad one.

        The recording's path is made absolute (a role process may run elsewhere) and its
        directory must exist; a file there is replaced, a directory is refused.
        """
        endpoint = None if foxglove is None else parse_endpoint(foxglove)
        path = None
        if record is not None:
            path = Path(record).expanduser().absolute()
            if path.is_dir():
                raise DbmlError(f"--record={record!r} is a directory: name a file (demo.mcap)")
            if not path.parent.is_dir():
                raise DbmlError(f"--record={record!r}: directory {str(path.parent)!r} not found")
        if endpoint is None and path is None:
            return None
        return cls(endpoint, path)

    @property
    def foxglove_flag(self) -> str | None:
        """``--foxglove``'s text (a role's spec carries it)."""
        return None if self.endpoint is None else str(self.endpoint)

    @property
    def record_flag(self) -> str | None:
        """``--record``'s text, absolute."""
        return None if self.record is None else str(self.record)
