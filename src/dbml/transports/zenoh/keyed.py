"""The parameter store's messages over zenoh's keys, without a session: what is sent and heard.

A write goes out under its parameter's key, and every process that listens merges the newest
write per name, ordered by (stamp, writer); a batch (``set_many``: the optimizer's allocation
of a round) is one message under a batch key. Keys and encodings are the wire schema's
(``dbml.protocol.keys``); the values are a ``Replica``'s.

Ownership keeps a join cheap: the writer of a value's newest write owns it and is the one that
serves it to a newcomer; values whose writer has left (a ``dbml priority`` that exited) are served
by everyone who holds them. A newcomer asks each live process once for what it owns, so a join
costs every other process one query and one answer of its own values, whatever the fleet's size
(the store this replaces answered every query with its whole cache, from every process, for every
process met: replies grew with the cube of the fleet).

No writer's clock can pin a value: a write stamped more than ``MAX_CLOCK_AHEAD_NS`` ahead of the
receiver's clock is refused, and a local write always supersedes what is held. The zenoh sync
(``dbml.transports.zenoh.params``) wires this to a session; the unit tests use plain functions.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
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
from dbml.protocol.schema import lookup
from dbml.transports.overflow import LogOnce
from dbml.transports.replica import Replica, Write

__all__ = ["MAX_CLOCK_AHEAD_NS", "KeyedParams", "Send"]

log = logging.getLogger("dbml.zenoh")

MAX_CLOCK_AHEAD_NS = 30 * 1_000_000_000
"""A write stamped further ahead of this process's clock is refused: a peer's wrong clock (or a
lie) must not make its value win every comparison for good. Fleet clocks agree far better."""
_NS_PER_S = 1e9
_UNKNOWN = "names outside the schema"
"""Their refusals are logged under this one key: a flood of made-up names is one line."""

Send: TypeAlias = Callable[[str, bytes], None]
"""Sends one encoded message under its key to every peer; may block (on the sender thread)."""


class KeyedParams:
    """One process's replica (``replica``, its ``ParamStore``) and its messages, as ``node_id``.

    ``send`` puts one message on the network (called on the replica's sender thread only);
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
        self._warnings = LogOnce(log)
        """Keys whose malformed writes were logged (``MAX_LOGGED_KEYS`` at most)."""
        self.replica = Replica(node_id, send=self._send_write, log=log, clock_ns=clock_ns)

    def _send_write(self, write: Write) -> None:
        """A write of this process as one message: under its name's key, or a batch's."""
        if write.batch:
            # Under the host's batch key, which only its sessions (and those that follow every
            # parameter) hear; never coalesced with another: batches name different sets.
            self._send(batch_key(write.host), encode_batch(write.values, write.stamp, write.writer))
            return
        ((name, value),) = write.values.items()
        self._send(param_key(name), encode_param(value, write.stamp, write.writer))

    # -- what arrives -------------------------------------------------------------------------

    def on_write(self, key: str, data: bytes) -> None:
        """A write received under ``key`` (a parameter's): merged if newer, told."""
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
        if self._known(name) and self._accepts(name, stamp, writer):
            self.replica.merge(name, value, stamp=stamp, writer=writer)

    def on_batch(self, data: bytes) -> None:
        """A batch received: each name merged if newer, and each change told."""
        try:
            values, stamp, writer = decode_batch(data)
        except TransportError as err:
            self._warn(BATCH, str(err))
            return
        if not self._accepts(BATCH, stamp, writer):
            return
        for name, value in values.items():
            if self._known(name):
                self.replica.merge(name, value, stamp=stamp, writer=writer)

    def _known(self, name: str) -> bool:
        """Whether ``name`` is one of the schema's: no other can take a place in the store."""
        if lookup(name) is not None:
            return True
        self._warnings.warning(_UNKNOWN, "ignoring %s and other names outside the schema", name)
        return False

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

    def _warn(self, key: str, reason: str) -> None:
        self._warnings.warning(key, "ignoring %s: %s", key, reason)

    # -- serving ------------------------------------------------------------------------------

    def stamp(self, name: str) -> tuple[int, str] | None:
        """The (stamp, writer) of the newest write of ``name`` known here."""
        held = self.replica.entry(name)
        return None if held is None else (held.stamp, held.writer)

    def owned(self, is_live: Callable[[str], bool], *, prefix: str = "") -> list[tuple[str, bytes]]:
        """What this process serves of the names that start with ``prefix``.

        Its own newest writes, and those whose writer left; deletions too, so a newcomer does
        not revive a deleted value. Only what the prefix selects is encoded: the optimizer owns
        every channel's rate and a robot asks for its own channels', so encoding all of it for
        every question cost O(fleet) a question.
        """
        return [
            (name, encode_param(held.value, held.stamp, held.writer))
            for name, held in self.replica.entries(prefix)
            if held.writer == self.node_id or not is_live(held.writer)
        ]

    def held(self, name: str) -> bytes | None:
        """The newest write of ``name`` held here, whoever owns it (for a write's confirmation)."""
        held = self.replica.entry(name)
        return None if held is None else encode_param(held.value, held.stamp, held.writer)
