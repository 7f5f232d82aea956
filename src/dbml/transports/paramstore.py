"""The parameter store over a pub/sub network: every process caches, each value's owner serves it.

A write is published under the parameter's key, and every process that listens caches the
newest write per name, ordered by (stamp, writer). A batch (``set_many``: the optimizer's
allocation of a round) is one message. Keys and encodings are the wire schema's
(``dbml.protocol.keys``).

Ownership keeps a join cheap: the writer of a value's newest write owns it and is the one that
serves it to a newcomer; values whose writer has left (a ``dbml priority`` that exited) are served
by everyone who holds them. A newcomer asks each live process once for what it owns, so a join
costs every other process one query and one answer of its own values, whatever the fleet's size
(the store this replaces answered every query with its whole cache, from every process, for every
process met: replies grew with the cube of the fleet).

Writes are sent by the store's own sender thread, in order: ``set`` never blocks its caller,
which may be a middleware callback (a blocking send from there once deadlocked a fleet of 40).
At most ``MAX_QUEUED_WRITES`` wait: a name's newer write replaces its older one still queued,
and past the bound the oldest is dropped (logged once per stall).
No writer's clock can pin a value: a write stamped more than ``MAX_CLOCK_AHEAD_NS`` ahead of the
receiver's clock is refused, and a local write always supersedes what is held.
No peer can fill the memory either: past ``MAX_PARAMS`` names, a write of a new name from the
network is refused (logged once per flood); this process's own writes are always taken.

The store knows nothing of the middleware: it is given a function that sends one message and is
fed what arrives. The zenoh transport wires it to a session; the unit tests use plain functions.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TypeAlias

from dbml.core.errors import TransportError
from dbml.core.spec import short_repr
from dbml.protocol.keys import (
    BATCH,
    PARAM,
    batch_key,
    decode_batch,
    decode_param,
    encode_batch,
    encode_param,
    param_key,
)
from dbml.protocol.names import check_topic
from dbml.transports.base import Handle, ParamValue, check_param_value
from dbml.transports.callbacks import CallbackList
from dbml.transports.overflow import LogOnce, Overflow
from dbml.transports.worker import DEFAULT_SENDER_CAPACITY, FLUSH_TIMEOUT_S, OrderedSender

__all__ = ["MAX_CLOCK_AHEAD_NS", "MAX_PARAMS", "ReplicatedParams"]

log = logging.getLogger("dbml.zenoh")

MAX_CLOCK_AHEAD_NS = 30 * 1_000_000_000
"""A write stamped further ahead of this process's clock is refused: a peer's wrong clock (or a
lie) must not make its value win every comparison for good. Fleet clocks agree far better."""
MAX_QUEUED_WRITES = DEFAULT_SENDER_CAPACITY
"""The most writes waiting for the network: a name's newer write replaces its queued one, so
this bounds batches and distinct names; past it the oldest is dropped (``OrderedSender``)."""
MAX_PARAMS = 65_536
"""The most parameter names held from the network (deletions included: a deleted name is kept,
so a newcomer does not revive it). A fleet of 160 robots with 4 channels writes 7 names per
channel and a dozen global ones, about 4,500: this is 14 times that (the optimizer tracks up to
4,096 channels, 28,672 names). Any peer can write, so past this a write of a new name from the
network is refused, and logged once (a name is never forgotten, so the store stays full);
names held are still updated, and this process's own writes are always taken (its code bounds
them, and read-your-writes and serving what it owns depend on them). A name costs a few hundred
bytes: tens of MB at most."""
_NS_PER_S = 1e9

Send: TypeAlias = Callable[[str, bytes], None]
"""Sends one encoded message under its key to every peer; may block (on the sender thread)."""
_Entry: TypeAlias = tuple[ParamValue, int, str]
"""A held write: value, stamp, writer."""


class ReplicatedParams:
    """One process's replica of the parameters (a ``ParamStore``), identified by ``node_id``.

    ``send`` puts one message on the network (called on the store's sender thread only);
    ``clock_ns`` stamps writes (wall-clock nanoseconds, so writers on different machines compare).
    """

    def __init__(
        self,
        node_id: str,
        *,
        send: Send,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.node_id = node_id
        self._send = send
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._values: dict[str, _Entry] = {}
        """The newest write of each name: up to ``MAX_PARAMS`` from the network, and ours."""
        self._full = Overflow("parameter names", MAX_PARAMS, log=log)
        self._warnings = LogOnce(log)
        """Keys whose malformed writes were logged (``MAX_LOGGED_KEYS`` at most)."""
        self.watchers: CallbackList[[str, ParamValue]] = CallbackList()
        self._sender: OrderedSender[tuple[str, bytes]] = OrderedSender(
            lambda item: self._send(*item),
            name="dbml-param-send",
            log=log,
            capacity=MAX_QUEUED_WRITES,
            describe=lambda item: f"parameter write {item[0]}",
        )

    # -- writing ------------------------------------------------------------------------------

    def _stamp_locked(self, names: list[str]) -> int:
        """A stamp newer than this clock and than every write held of ``names``."""
        stamp = self._clock_ns()
        for name in names:
            old = self._values.get(name)
            if old is not None:
                stamp = max(stamp, old[1] + 1)
        return stamp

    def set(self, name: str, value: ParamValue) -> None:
        """Write ``name`` here, queue the write for every peer, then notify this process.

        A write supersedes every write known here, also one stamped ahead of our clock (a peer's
        fast clock), so what this process sets is what it and its watchers see.
        """
        check_param_value(value)
        key = param_key(name)
        with self._lock:  # queued under the lock: no older stamp can be queued after a newer
            stamp = self._stamp_locked([name])
            self._values[name] = (value, stamp, self.node_id)
            # A name's newest write replaces its older one still queued (one slot per key).
            self._sender.put((key, encode_param(value, stamp, self.node_id)), slot=key)
        self.watchers.fire(name, value)

    def set_many(self, values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
        """Write several names as one message (one stamp), then notify each change.

        ``host``: the batch goes under that host's batch key, which only its sessions (and
        those that follow every parameter) hear.
        """
        if not values:
            return
        key = batch_key(host)  # checks the host
        with self._lock:
            stamp = self._stamp_locked(list(values))
            data = encode_batch(values, stamp, self.node_id)  # checks every name and value
            for name, value in values.items():
                self._values[name] = (value, stamp, self.node_id)
            self._sender.put((key, data))  # never replaced: batches name different sets
        for name, value in values.items():
            self.watchers.fire(name, value)

    def flush(self, timeout_s: float = FLUSH_TIMEOUT_S) -> bool:
        """Wait until every queued write was handed to the network; False after ``timeout_s``."""
        return self._sender.flush(timeout_s)

    def close(self, timeout_s: float = FLUSH_TIMEOUT_S) -> None:
        """Send what is queued (bounded), then stop the sender thread."""
        if not self._sender.close(timeout_s):
            log.warning("closing with parameter writes unsent after %.1f s", timeout_s)

    @property
    def alive(self) -> bool:
        """False once the sender thread died (a failed send does not end it)."""
        return self._sender.alive

    # -- reading ------------------------------------------------------------------------------

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

    # -- what arrives -------------------------------------------------------------------------

    def on_write(self, key: str, data: bytes) -> None:
        """A write received under ``key`` (a parameter's): merged if newer, notified."""
        if not key.startswith(PARAM + "/"):
            self._warn(key, "not a parameter key")
            return
        self.on_value(key[len(PARAM) :], data)

    def on_value(self, name: str, data: bytes) -> None:
        """A write of ``name`` received (published, or an owner's answer): merged if newer."""
        try:
            check_topic(name)
            value, stamp, writer = decode_param(data)
        except TransportError as err:
            self._warn(name, str(err))
            return
        if self._accepts(name, stamp, writer) and self._merge(name, value, stamp, writer):
            self.watchers.fire(name, value)

    def on_batch(self, data: bytes) -> None:
        """A batch received: each name merged if newer, and each change notified."""
        try:
            values, stamp, writer = decode_batch(data)
        except TransportError as err:
            self._warn(BATCH, str(err))
            return
        if not self._accepts(BATCH, stamp, writer):
            return
        for name, value in values.items():
            if self._merge(name, value, stamp, writer):
                self.watchers.fire(name, value)

    def _accepts(self, name: str, stamp: int, writer: str) -> bool:
        if writer == self.node_id:
            return False  # our own write, already applied when it was made
        ahead_ns = stamp - self._clock_ns()
        if ahead_ns > MAX_CLOCK_AHEAD_NS:
            # "Newest stamp wins" must not let a writer's clock (or a lie) pin a value for good.
            self._warn(
                name,
                f"from {short_repr(writer)} stamped {ahead_ns / _NS_PER_S:.0f} s ahead of this "
                f"clock (more than {MAX_CLOCK_AHEAD_NS / _NS_PER_S:.0f} s)",
            )
            return False
        return True

    def _merge(self, name: str, value: ParamValue, stamp: int, writer: str) -> bool:
        """Hold a write from the network if it is newer, and if it names a new name, if room."""
        with self._lock:
            old = self._values.get(name)
            if old is None and len(self._values) >= MAX_PARAMS:
                self._full.refuse()
                return False
            if old is not None and (old[1], old[2]) >= (stamp, writer):
                return False
            self._values[name] = (value, stamp, writer)
        return True

    def _warn(self, key: str, reason: str) -> None:
        self._warnings.warning(key, "ignoring %s: %s", key, reason)

    # -- serving ------------------------------------------------------------------------------

    def owned(self, is_live: Callable[[str], bool]) -> list[tuple[str, bytes]]:
        """What this process serves: its own newest writes, and those whose writer left.

        Deletions are served too, so a newcomer does not revive a deleted value.
        """
        with self._lock:
            entries = list(self._values.items())
        return [
            (name, encode_param(value, stamp, writer))
            for name, (value, stamp, writer) in entries
            if writer == self.node_id or not is_live(writer)
        ]

    def held(self, name: str) -> bytes | None:
        """The newest write of ``name`` held here, whoever owns it (for a write's confirmation)."""
        with self._lock:
            entry = self._values.get(name)
        return None if entry is None else encode_param(*entry)
