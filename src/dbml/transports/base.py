"""The transport interface: what the runtime needs from a middleware, and nothing more.

A transport gives a process five things: publish bytes (with attachment metadata) on a topic,
subscribe to a topic, a parameter store with change notification, the live graph (which host
publishes or subscribes which topic variant) and this process's host identity. ``memory`` is the
in-process test double; ``zenoh`` is the real engine. Both pass one contract test suite.

Topics are ROS-style names (``/r1/camera``). Callbacks may run on a middleware thread: keep them
short and never block in them.
"""

from __future__ import annotations

import enum
import json
import os
import re
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, TypeAlias, runtime_checkable

from dbml.core.errors import TransportError

__all__ = [
    "Closer",
    "GraphEntry",
    "GraphView",
    "Handle",
    "ParamStore",
    "ParamValue",
    "Publisher",
    "Role",
    "Sample",
    "Transport",
    "Variant",
    "check_param_value",
    "check_topic",
    "decode_param",
    "encode_param",
    "param_number",
    "resolve_host",
]

ParamValue: TypeAlias = bool | int | float | str | None
"""A parameter's value; ``None`` means deleted."""

_TOPIC = re.compile(r"^(/[A-Za-z0-9_\-.~]+)+$")
_HOST = re.compile(r"^[A-Za-z0-9_\-.~]+$")


def check_topic(topic: str) -> str:
    """A topic is a ROS-style name: ``/`` then segments of letters, digits and ``_-.~``."""
    if not isinstance(topic, str) or not _TOPIC.match(topic):
        raise TransportError(
            f"topic={topic!r} must look like '/robot/sensor' (segments of letters, digits, _-.~)"
        )
    return topic


def resolve_host(host: str | None = None) -> str:
    """This process's host identity: the argument, else ``DBML_HOST``, else the hostname.

    Test hosts on one machine share a hostname, so the identity must be settable.
    """
    chosen = host or os.environ.get("DBML_HOST") or socket.gethostname()
    if not _HOST.match(chosen):
        raise TransportError(f"host={chosen!r} must be letters, digits and _-.~ only")
    return chosen


class Variant(enum.StrEnum):
    """Which copy of a topic: every message (``full``) or the rate-managed one (``optimized``)."""

    FULL = "full"
    OPTIMIZED = "optimized"

    def key(self, topic: str) -> str:
        return topic if self is Variant.FULL else f"{topic}/optimized"


class Role(enum.StrEnum):
    PUBLISHER = "pub"
    SUBSCRIBER = "sub"


@dataclass(frozen=True, slots=True)
class GraphEntry:
    """One live declaration: ``host`` publishes or subscribes ``topic`` in ``variant``."""

    role: Role
    host: str
    topic: str
    variant: Variant
    uid: str
    """Unique per declaration, so two identical declarations stay two entries."""


@dataclass(frozen=True, slots=True)
class Sample:
    """A received message; ``attachment`` carries the publisher's metadata."""

    topic: str
    payload: bytes
    attachment: bytes | None


class Handle(Protocol):
    """Anything declared that must be undeclared: a subscription, a watch, a graph token."""

    def close(self) -> None: ...


class Publisher(Protocol):
    topic: str

    def put(self, payload: bytes, attachment: bytes | None = None) -> None: ...

    @property
    def has_subscribers(self) -> bool:
        """Whether any subscriber matches, so a full-rate copy nobody reads is never sent."""
        ...

    def close(self) -> None: ...


class ParamStore(Protocol):
    """Parameters under the paper's names, such as ``/r1/camera/dbm/priority``.

    Every process sees every value; the newest write wins; ``watch`` reports every change.
    """

    def set(self, name: str, value: ParamValue) -> None: ...

    def get(self, name: str) -> ParamValue: ...

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]: ...

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle: ...


class GraphView(Protocol):
    """Who publishes and subscribes what, from which host, live."""

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle: ...

    def entries(self) -> frozenset[GraphEntry]: ...

    def watch(self, callback: Callable[[], None]) -> Handle: ...


@runtime_checkable
class Transport(Protocol):
    @property
    def host(self) -> str:
        """This process's host identity."""
        ...

    @property
    def params(self) -> ParamStore: ...

    @property
    def graph(self) -> GraphView: ...

    def declare_publisher(self, topic: str, variant: Variant = Variant.FULL) -> Publisher: ...

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle: ...

    def now(self) -> float:
        """Monotonic seconds; the memory transport's is injectable."""
        ...

    def close(self) -> None: ...


class Closer:
    """A ``Handle`` that runs its action once, on the first ``close()``."""

    def __init__(self, action: Callable[[], None]) -> None:
        self._action: Callable[[], None] | None = action

    def close(self) -> None:
        action, self._action = self._action, None
        if action is not None:
            action()


def param_number(value: ParamValue) -> float | None:
    """A parameter as a number, or None when it is unset or not a number (booleans are not)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def check_param_value(value: object) -> ParamValue:
    if value is not None and not isinstance(value, bool | int | float | str):
        raise TransportError(f"parameter value={value!r} must be a bool, number or string")
    return value


def encode_param(value: ParamValue, stamp_ns: int, writer: str) -> bytes:
    """Wire form of a parameter write: the value, when it was written and by whom."""
    check_param_value(value)
    return json.dumps({"v": value, "t": stamp_ns, "w": writer}).encode()


def decode_param(data: bytes) -> tuple[ParamValue, int, str]:
    try:
        document = json.loads(data)
        value, stamp, writer = document["v"], int(document["t"]), str(document["w"])
    except (ValueError, KeyError, TypeError) as err:
        raise TransportError(f"malformed parameter write {data[:80]!r}") from err
    if value is not None and not isinstance(value, bool | int | float | str):
        raise TransportError(f"malformed parameter value {value!r}")
    return value, stamp, writer
