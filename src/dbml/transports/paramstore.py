"""The replicated parameter store: every process caches every write, the newest write wins.

A write is published as ``{"v": value, "t": stamp_ns, "w": writer}`` under the key
``dbml/param/<name>`` (``/r1/camera/dbm/priority`` is ``dbml/param/r1/camera/dbm/priority``).
Each process keeps the newest write per name, ordered by (stamp, writer), answers queries from
that cache and, when it meets a new peer, fetches every peer's cache, so a late joiner sees what
was written before it started.

The store knows nothing of the middleware: it is given a function that publishes one write and a
function that fetches the peers' caches, and is fed received writes and queries. The zenoh
transport wires it to a session; the unit tests drive it with plain functions.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import TypeAlias

from dbml.core.errors import TransportError
from dbml.transports.base import Handle, ParamValue, check_param_value, check_topic
from dbml.transports.callbacks import CallbackList

__all__ = [
    "MAX_CLOCK_AHEAD_NS",
    "PARAM_PREFIX",
    "ReplicatedParams",
    "decode_param",
    "encode_param",
    "param_key",
]

log = logging.getLogger("dbml.zenoh")

PARAM_PREFIX = "dbml/param"
"""Where parameter writes live in the key space; the parameter's name follows."""
SYNC_TIMEOUT_S = 2.0
"""How long a fetch of the peers' caches waits for their replies."""
MAX_CLOCK_AHEAD_NS = 30 * 1_000_000_000
"""A write stamped further ahead of this process's clock is refused: a peer's wrong clock (or a
lie) must not make its value win every comparison for good. Fleet clocks agree far better."""
_NS_PER_S = 1e9
_MALFORMED_SHOWN_BYTES = 80
"""How much of a malformed write an error message quotes."""

Publish: TypeAlias = Callable[[str, bytes], None]
"""Sends one encoded write under its key to every peer."""
Fetch: TypeAlias = Callable[[float], Iterable[tuple[str, bytes]]]
"""Asks every peer for its whole cache, waiting up to the given seconds: (key, write) pairs."""


def param_key(name: str) -> str:
    """The key a parameter's writes are published under."""
    return PARAM_PREFIX + check_topic(name)


def encode_param(value: ParamValue, stamp_ns: int, writer: str) -> bytes:
    """Wire form of a parameter write: the value, when it was written and by whom."""
    check_param_value(value)
    return json.dumps({"v": value, "t": stamp_ns, "w": writer}).encode()


def decode_param(data: bytes) -> tuple[ParamValue, int, str]:
    """A write's value, stamp and writer; a malformed one raises ``TransportError``."""
    try:
        document = json.loads(data)
        value, stamp, writer = document["v"], int(document["t"]), str(document["w"])
    except (ValueError, KeyError, TypeError) as err:
        shown = data[:_MALFORMED_SHOWN_BYTES]
        raise TransportError(f"malformed parameter write {shown!r}") from err
    if value is not None and not isinstance(value, bool | int | float | str):
        raise TransportError(f"malformed parameter value {value!r}")
    return value, stamp, writer


class ReplicatedParams:
    """One process's replica of the parameters (a ``ParamStore``), identified by ``node_id``.

    ``publish`` sends this process's writes; ``fetch`` is used by ``sync``; ``clock_ns`` stamps
    writes (wall-clock nanoseconds, so writers on different machines compare).
    """

    def __init__(
        self,
        node_id: str,
        *,
        publish: Publish,
        fetch: Fetch,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.node_id = node_id
        self._publish = publish
        self._fetch = fetch
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._values: dict[str, tuple[ParamValue, int, str]] = {}
        self.watchers: CallbackList[[str, ParamValue]] = CallbackList()

    def _merge(self, name: str, value: ParamValue, stamp: int, writer: str) -> bool:
        with self._lock:
            old = self._values.get(name)
            if old is not None and (old[1], old[2]) >= (stamp, writer):
                return False
            self._values[name] = (value, stamp, writer)
        return True

    def set(self, name: str, value: ParamValue) -> None:
        """Write ``name`` here, send the write to every peer, then notify this process."""
        check_param_value(value)
        key = param_key(name)
        with self._lock:
            # A write supersedes every write known here, also one stamped ahead of our clock
            # (a peer's fast clock), so what this process sets is what it and its watchers see.
            old = self._values.get(name)
            stamp = self._clock_ns() if old is None else max(self._clock_ns(), old[1] + 1)
            self._values[name] = (value, stamp, self.node_id)
        self._publish(key, encode_param(value, stamp, self.node_id))
        self.watchers.fire(name, value)

    def get(self, name: str) -> ParamValue:
        """The newest value known of ``name``; None when unset or deleted."""
        with self._lock:
            entry = self._values.get(name)
        return None if entry is None else entry[0]

    def stamp(self, name: str) -> tuple[int, str] | None:
        """The (stamp, writer) of the newest write of ``name`` known here."""
        with self._lock:
            entry = self._values.get(name)
        return None if entry is None else (entry[1], entry[2])

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        """Every set value whose name starts with ``prefix``."""
        with self._lock:
            return {
                name: value
                for name, (value, _, _) in self._values.items()
                if name.startswith(prefix) and value is not None
            }

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        """Call ``callback(name, value)`` on every change, local or remote."""
        return self.watchers.add(callback)

    # -- the wire -----------------------------------------------------------------------------

    def on_write(self, key: str, data: bytes) -> None:
        """A write received from a peer: merged if newer, and watchers notified."""
        self._accept(key, data, notify=True)

    def _accept(self, key: str, data: bytes, *, notify: bool) -> None:
        try:
            value, stamp, writer = decode_param(data)
        except TransportError as err:
            log.warning("ignoring %s: %s", key, err)
            return
        if writer == self.node_id:
            return  # our own write, already applied in set()
        ahead_ns = stamp - self._clock_ns()
        if ahead_ns > MAX_CLOCK_AHEAD_NS:
            # "Newest stamp wins" must not let a writer's clock (or a lie) pin a value for good.
            log.warning(
                "ignoring %s from %s: stamped %.0f s ahead of this clock (more than %.0f s)",
                key,
                writer[:16],
                ahead_ns / _NS_PER_S,
                MAX_CLOCK_AHEAD_NS / _NS_PER_S,
            )
            return
        name = key[len(PARAM_PREFIX) :]
        if self._merge(name, value, stamp, writer) and notify:
            self.watchers.fire(name, value)

    def replies(self, matches: Callable[[str], bool]) -> list[tuple[str, bytes]]:
        """The answer to a query: every cached write whose key ``matches`` the query."""
        with self._lock:
            values = list(self._values.items())
        replies = []
        for name, (value, stamp, writer) in values:
            key = PARAM_PREFIX + name
            if matches(key):
                replies.append((key, encode_param(value, stamp, writer)))
        return replies

    def sync(self, timeout_s: float = SYNC_TIMEOUT_S) -> None:
        """Fetch every parameter the reachable peers hold (newest wins)."""
        for key, data in self._fetch(timeout_s):
            self._accept(key, data, notify=True)
