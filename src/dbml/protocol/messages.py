"""Every wire message that is not a parameter, typed and encoded in one place.

Parameters travel through the store (``dbml.protocol.schema``, ``dbml.protocol.keys``); what is
here travels as a message on a topic of dbml's own namespace, as untyped bytes (JSON), like a
channel's data. Each message is a frozen dataclass with ``encode()`` and ``decode()``; what
``decode`` is given came from the network, so it checks every field and raises
``TransportError`` naming the field and the value, never anything else.

| message | topic | sent by | read by |
|---|---|---|---|
| ``RoundReport`` | ``/dbm/optimizer/round`` | the optimizer, every round | view, monitor |
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dbml.core.allocation import Status, Strategy
from dbml.core.errors import SpecError, TransportError
from dbml.core.spec import MAX_RATE_HZ, MAX_SIZE_BYTES, check_number, short_repr
from dbml.protocol.names import check_topic
from dbml.protocol.schema import GLOBAL_PREFIX, MAX_TEXT_CHARS

__all__ = [
    "MAX_REPORTED_CHANNELS",
    "MAX_ROUND_BYTES",
    "ROUND_TOPIC",
    "ChannelRound",
    "RoundReport",
]

ROUND_TOPIC = f"{GLOBAL_PREFIX}/optimizer/round"
"""Where the optimizer says what each round decided."""
MAX_REPORTED_CHANNELS = 4096
"""The most channels a round reports: the most the optimizer tracks (``MAX_CHANNELS``)."""
MAX_ROUND_BYTES = 4 << 20
"""A round report larger than this is refused unread: 4,096 channels take about 1.2 MB."""
_BYTES_PER_S_PER_MBIT = 125_000


def _number(
    document: Mapping[str, object],
    field: str,
    *,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
    optional: bool = False,
) -> float | None:
    """A finite number of ``document``, within its range; None where ``optional`` and null."""
    value = document.get(field)
    if value is None and optional:
        return None
    try:
        return check_number(
            value,
            field=field,
            minimum=minimum,
            maximum=maximum,
            exclusive_minimum=exclusive_minimum,
        )
    except SpecError as err:
        raise TransportError(str(err)) from None


def _required(value: float | None) -> float:
    assert value is not None  # _number returns None only where optional
    return value


@dataclass(frozen=True, slots=True)
class ChannelRound:
    """One live channel in a round: what it declared and what the optimizer made of it.

    ``normalized_priority`` and ``floor_hz`` are eq. 2 and eq. 4 as the allocator used them
    (None for a channel it did not allocate: unmanaged, or not sized yet); ``rate_hz`` is the
    rate pushed (None: none yet); ``share`` is of the budget in use (managed channels only).
    """

    topic: str
    managed: bool
    priority: float
    min_hz: float
    max_hz: float
    size_bytes: float | None = None
    normalized_priority: float | None = None
    floor_hz: float | None = None
    rate_hz: float | None = None
    share: float | None = None

    def as_json(self) -> dict[str, Any]:
        """The channel as a round report carries it (and the live view shows it)."""
        return {
            "topic": self.topic,
            "priority": self.priority,
            "normalized_priority": self.normalized_priority,
            "floor_hz": self.floor_hz,
            "rate_hz": self.rate_hz,
            "min_hz": self.min_hz,
            "max_hz": self.max_hz,
            "size_bytes": self.size_bytes,
            "share": self.share,
            "managed": self.managed,
        }

    @classmethod
    def from_json(cls, document: object) -> ChannelRound:
        """A channel of a received report; ``TransportError`` naming a bad field."""
        if not isinstance(document, dict):
            raise TransportError(f"round channel={short_repr(document)} is not an object")
        topic, managed = document.get("topic"), document.get("managed")
        if not isinstance(topic, str):
            raise TransportError(f"round channel topic={short_repr(topic)} is not a string")
        check_topic(topic)
        if not isinstance(managed, bool):
            raise TransportError(f"{topic}: managed={short_repr(managed)} is not a boolean")
        try:
            return cls(
                topic=topic,
                managed=managed,
                priority=_required(_number(document, "priority", minimum=0.0, maximum=1.0)),
                min_hz=_required(_number(document, "min_hz", minimum=0.0, maximum=MAX_RATE_HZ)),
                max_hz=_required(_number(document, "max_hz", minimum=0.0, maximum=MAX_RATE_HZ)),
                size_bytes=_number(
                    document,
                    "size_bytes",
                    minimum=0.0,
                    exclusive_minimum=True,
                    maximum=MAX_SIZE_BYTES,
                    optional=True,
                ),
                normalized_priority=_number(
                    document, "normalized_priority", minimum=0.0, maximum=1.0, optional=True
                ),
                floor_hz=_number(
                    document, "floor_hz", minimum=0.0, maximum=MAX_RATE_HZ, optional=True
                ),
                rate_hz=_number(
                    document, "rate_hz", minimum=0.0, maximum=MAX_RATE_HZ, optional=True
                ),
                share=_number(document, "share", minimum=0.0, optional=True),
            )
        except TransportError as err:
            raise TransportError(f"{topic}: {err}") from None


@dataclass(frozen=True, slots=True)
class RoundReport:
    """What one optimizer round decided, as it said it: the view and the monitor read this.

    They never allocate again: what they show is what the optimizer used (its links, its frame
    headroom, its estimate), not what the values they hold would give.
    """

    round: int
    """The optimizer's round counter (``/dbm/round``, its heartbeat)."""
    status: Status
    message: str
    strategy: Strategy
    budget_mbit: float | None
    """What was allocatable: the estimate, else bandwidth times utilization (None: no budget)."""
    channels: tuple[ChannelRound, ...]

    @property
    def allocated_mbit(self) -> float:
        """What the managed channels' rates add up to, in Mbit/s."""
        total = sum(
            c.rate_hz * c.size_bytes
            for c in self.channels
            if c.managed and c.rate_hz is not None and c.size_bytes is not None
        )
        return total / _BYTES_PER_S_PER_MBIT

    def channel(self, topic: str) -> ChannelRound | None:
        """The round's entry of ``topic``, if it reported one."""
        return next((c for c in self.channels if c.topic == topic), None)

    def as_json(self) -> dict[str, Any]:
        """The report as a document (the live view's ``/dbm/allocation`` adds nothing to it)."""
        return {
            "round": self.round,
            "status": self.status.value,
            "status_message": self.message,
            "strategy": self.strategy.value,
            "budget_mbit": self.budget_mbit,
            "allocated_mbit": self.allocated_mbit,
            "channels": [c.as_json() for c in self.channels],
        }

    def encode(self) -> bytes:
        """Compact JSON."""
        return json.dumps(self.as_json(), separators=(",", ":")).encode()

    @classmethod
    def decode(cls, data: bytes) -> RoundReport:
        """A report from its bytes; ``TransportError`` naming what is malformed."""
        if len(data) > MAX_ROUND_BYTES:
            raise TransportError(f"round report of {len(data)} bytes (more than {MAX_ROUND_BYTES})")
        try:
            document = json.loads(data)
        except (ValueError, RecursionError) as err:
            raise TransportError(f"round report {data[:80]!r} is not JSON") from err
        if not isinstance(document, dict):
            raise TransportError(f"round report={short_repr(document)} is not an object")
        counter = document.get("round")
        if not isinstance(counter, int) or isinstance(counter, bool) or counter < 0:
            raise TransportError(f"round report round={short_repr(counter)} is not a count")
        status, strategy, message = (
            document.get("status"),
            document.get("strategy"),
            document.get("status_message"),
        )
        if not isinstance(status, str) or status not in {s.value for s in Status}:
            raise TransportError(f"round report status={short_repr(status)} is not a status")
        if not isinstance(strategy, str) or strategy not in {s.value for s in Strategy}:
            raise TransportError(f"round report strategy={short_repr(strategy)} is not a strategy")
        if not isinstance(message, str) or len(message) > MAX_TEXT_CHARS:
            raise TransportError(f"round report status_message={short_repr(message)} is not text")
        channels = document.get("channels")
        if not isinstance(channels, list) or len(channels) > MAX_REPORTED_CHANNELS:
            raise TransportError(
                f"round report channels={short_repr(channels)} is not a list of at most "
                f"{MAX_REPORTED_CHANNELS}"
            )
        budget = _number(
            document, "budget_mbit", minimum=0.0, exclusive_minimum=True, optional=True
        )
        return cls(
            round=counter,
            status=Status(status),
            message=message,
            strategy=Strategy(strategy),
            budget_mbit=budget,
            channels=tuple(ChannelRound.from_json(c) for c in channels),
        )
