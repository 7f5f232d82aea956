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
"""

from __future__ import annotations

from dataclasses import dataclass

from dbml.core.errors import SpecError
from dbml.transports.base import TransportPriority

__all__ = [
    "HIGH_PRIORITY",
    "SMALL_MESSAGE_BYTES",
    "URGENT_PRIORITY",
    "TransportQos",
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


def parse_transport_priority(text: str) -> TransportPriority:
    """``"real_time"`` (or ``real-time``, any case) -> the class; a bad name raises naming it."""
    name = text.strip().lower().replace("-", "_")
    try:
        return TransportPriority(name)
    except ValueError:
        choices = ", ".join(p.value for p in TransportPriority)
        raise SpecError(f"transport_priority={text!r} is not one of: {choices}") from None
