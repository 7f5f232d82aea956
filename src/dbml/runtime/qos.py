"""A channel's transport class: which of the middleware's queues its messages wait in.

The optimizer decides how often a channel sends; this decides which message goes first when
several wait for the same link. A channel's raw priority (``[topic]/dbm/priority``, in [0, 1])
maps onto zenoh's data classes, and a small urgent message is sent ``express`` (unbatched):

| raw priority | message size | class |
|---|---|---|
| >= ``URGENT_PRIORITY`` (0.75) | <= ``SMALL_MESSAGE_BYTES`` | ``interactive_low``, express |
| >= ``URGENT_PRIORITY`` | larger (or not known yet) | ``data_high`` |
| >= ``HIGH_PRIORITY`` (0.25) | any | ``data_high`` |
| below | any | ``data`` (zenoh's default) |

Why: ``real_time`` and ``interactive_high`` stay above every data stream, for dbml's own
control traffic (parameter writes and allocations go at ``interactive_high``) and a user's
explicit choice (an emergency stop); a data stream never reaches them by mapping. Only a small
message may take the interactive class: an 84 KB camera frame there would hold the queue for
its whole wire time (61 ms at 11 Mbit/s), the very wait the class exists to avoid. Priority 0
(no priority set) keeps zenoh's default, so a channel nobody prioritised behaves as before.
``data_low`` and ``background`` are never mapped to: a low priority already lowers a channel's
rate, and starving it in the queue too would only add latency to what little it sends.
Only the interactive classes skip batching: an unbatched message costs a network write of its
own, which cut a managed 64-byte publish from 0.3 to 0.02 of a raw put when every small message
went express (``bench/publish_overhead.py``); an IMU stream needs throughput, an alarm latency.

An explicit ``TransportPriority`` (``--transport-priority``) overrides the mapping.

A zenoh publisher's class is fixed when it is declared, so a channel whose class changes (rare:
a priority event, the first message's size) needs a new publisher: ``QosSwitch`` declares it
and swaps it in without a lock held across the middleware call.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

from dbml.core.errors import SpecError
from dbml.transports.base import Publisher, TransportPriority

__all__ = [
    "HIGH_PRIORITY",
    "SMALL_MESSAGE_BYTES",
    "URGENT_PRIORITY",
    "QosSwitch",
    "TransportQos",
    "channel_qos",
    "explicit_qos",
    "is_small",
    "map_priority",
    "parse_transport_priority",
]

URGENT_PRIORITY = 0.75
"""From this raw priority on, a small message goes in the interactive class."""
HIGH_PRIORITY = 0.25
"""From this raw priority on, a channel's messages go ahead of default data."""
_EXPRESS_CLASSES = frozenset(
    {
        TransportPriority.REAL_TIME,
        TransportPriority.INTERACTIVE_HIGH,
        TransportPriority.INTERACTIVE_LOW,
    }
)
"""The classes for latency: their small messages skip batching."""
SMALL_MESSAGE_BYTES = 4_096
"""Up to this size a message is sent express and may be interactive: one such message takes
under 3 ms on an 11 Mbit/s link, and it fits one zenoh batch with room to spare."""


@dataclass(frozen=True, slots=True)
class TransportQos:
    """How a publisher's messages travel: their class and whether they skip batching."""

    priority: TransportPriority
    express: bool


def map_priority(priority: float, size_bytes: int | None) -> TransportQos:
    """The class of a channel with raw ``priority`` and messages of ``size_bytes`` (None: unknown).

    An unknown size counts as large: a publisher declared before its first message must not
    put a camera frame in the interactive class.
    """
    if priority >= URGENT_PRIORITY and is_small(size_bytes):
        return TransportQos(TransportPriority.INTERACTIVE_LOW, express=True)
    if priority >= HIGH_PRIORITY:
        return TransportQos(TransportPriority.DATA_HIGH, express=False)
    return TransportQos(TransportPriority.DATA, express=False)


def is_small(size_bytes: int | None) -> bool:
    """Whether messages of ``size_bytes`` may skip batching (None, not known yet: no)."""
    return size_bytes is not None and 0 <= size_bytes <= SMALL_MESSAGE_BYTES


def explicit_qos(priority: TransportPriority, size_bytes: int | None) -> TransportQos:
    """An explicit class: small messages of an interactive or real-time class go express."""
    urgent = priority in _EXPRESS_CLASSES
    return TransportQos(priority, express=urgent and is_small(size_bytes))


def channel_qos(
    priority: float, size_bytes: int | None, explicit: TransportPriority | None = None
) -> TransportQos:
    """The class of a channel: ``explicit`` if given (``explicit_qos``), else ``map_priority``."""
    if explicit is not None:
        return explicit_qos(explicit, size_bytes)
    return map_priority(priority, size_bytes)


def parse_transport_priority(text: str) -> TransportPriority:
    """``"real_time"`` (or ``real-time``, any case) -> the class; a bad name raises naming it."""
    name = text.strip().lower().replace("-", "_")
    try:
        return TransportPriority(name)
    except ValueError:
        choices = ", ".join(p.value for p in TransportPriority)
        raise SpecError(f"transport_priority={text!r} is not one of: {choices}") from None


class QosSwitch:
    """The publisher of one class at a time, re-declared when another class is wanted.

    ``declare(qos)`` declares a publisher in ``qos`` (None: the middleware's default) and is
    called without any lock held; ``publisher`` is the one in force, read without a lock by the
    publishing thread. A racing change of class wins over an older one. The publisher a swap
    replaces is retired, not closed at once: a ``put`` that read it just before the swap may
    still be using it; it is closed at the next swap, ``close_retired`` or ``close``.
    """

    def __init__(
        self, declare: Callable[[TransportQos | None], Publisher], qos: TransportQos | None
    ) -> None:
        self._declare = declare
        self._lock = threading.Lock()
        self._qos = self._target = qos
        self._generation = 0
        self._retired: Publisher | None = None
        self.publisher = declare(qos)
        """The publisher in force."""

    @property
    def qos(self) -> TransportQos | None:
        """The class of ``publisher``."""
        with self._lock:
            return self._qos

    def switch(self, wanted: TransportQos | None) -> bool:
        """Declare a publisher in ``wanted`` and swap it in; True if the class in force changed.

        Nothing is declared when ``wanted`` is in force or already being declared, nor when a
        newer call overtook this one while it declared (its publisher is closed again).
        """
        with self._lock:
            if wanted == self._target:  # in force, or being declared
                return False
            self._target = wanted
            self._generation += 1
            if wanted == self._qos:  # back to the class in force: the one in flight is moot
                return False
            generation = self._generation
        fresh = self._declare(wanted)
        with self._lock:
            swapped = generation == self._generation  # else a newer change wins
            if swapped:
                stale, self._retired = self._retired, self.publisher
                self.publisher, self._qos = fresh, wanted
            else:
                stale = fresh
        if stale is not None:
            stale.close()
        return swapped

    def close_retired(self) -> None:
        """Close the publisher the last swap replaced, if any."""
        with self._lock:
            retired, self._retired = self._retired, None
        if retired is not None:
            retired.close()

    def close(self) -> None:
        """Close the retired publisher and the one in force."""
        self.close_retired()
        self.publisher.close()
