"""Every wire message that is not a parameter, typed and encoded in one place.

Parameters (names, types, ranges) are the schema's (``dbml.protocol.schema``); everything else
one dbml process sends another is here, each a frozen dataclass with ``encode`` and ``decode``.
What arrives is untrusted: ``decode`` bounds the message's size before parsing it, then checks
every field's type and range and every collection's length, and its error names the field and
the value. Each section below is one message and stands on its own:

- **the estimator's state** (``EstimatorState``): the value of ``/dbm/estimator_state``, JSON
  text (``SpecError``, as a parameter's value);
- **the link beacon** (``LinkBeacon``, ``Heard``) on ``keys.LINK_TOPIC``: the estimator's word
  on the link to publishers (``TransportError``);
- **the reception report** (``ReceptionReport``, ``ReceivedFrame``) on
  ``keys.RECEPTION_TOPIC``: what a subscriber's host received, for the estimator
  (``TransportError``);
- **the round report** (``RoundReport``, ``ChannelRound``) on ``keys.ROUND_TOPIC``: what each
  optimizer round decided, for the live view and ``dbml monitor`` (``TransportError``).

Dependencies point one way: this module imports the pure estimator (``dbml.estimator``: a
state's ``Phase``, made ``of`` an ``Estimate``) and the rest of ``dbml.protocol``, never the
runtime; the estimator imports nothing of the wire.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from dbml.core.allocation import Status, Strategy
from dbml.core.errors import SpecError, TransportError
from dbml.core.spec import MAX_RATE_HZ, MAX_SIZE_BYTES, check_number, short_repr
from dbml.estimator.base import Estimate, Phase
from dbml.protocol.keys import is_host_name
from dbml.protocol.ladders import parse_encoding
from dbml.protocol.metadata import SEQ_MAX
from dbml.protocol.names import check_topic
from dbml.protocol.schema import MAX_TEXT_CHARS

__all__ = [
    "HEARD_MAX",
    "HEARD_RECENT_MAX",
    "MAX_BEACON_BYTES",
    "MAX_NAME_CHARS",
    "MAX_REASON_CHARS",
    "MAX_REPORTED_CHANNELS",
    "MAX_REPORT_BYTES",
    "MAX_REPORT_FRAMES",
    "MAX_ROUND_BYTES",
    "RELEASE_MAX_CHANNELS",
    "RELEASE_MAX_S",
    "ChannelRound",
    "EstimatorState",
    "Heard",
    "LinkBeacon",
    "ReceivedFrame",
    "ReceptionReport",
    "RoundReport",
]

MAX_REASON_CHARS = 120
"""The longest reason an estimator state carries (a line for a person)."""
MAX_NAME_CHARS = 1024
"""The longest host or topic name a message may carry: four times the longest ROS 2 topic
(247 characters, rmw's ``RMW_TOPIC_MAX_NAME_LENGTH``). Names key what the estimator keeps per
stream and per channel, so a longer one from the network would cost memory for nothing."""
_SEQ_MIN = 0
_SENT_NS_MIN, _SENT_NS_MAX = -(2**63), 2**63 - 1
"""A send time is the metadata's signed 64-bit nanoseconds."""
_ENTRY_BYTES = MAX_NAME_CHARS + 128
"""The most one named entry of a message encodes to: its name, its numbers and punctuation."""
_DECODE_ERRORS = (ValueError, OverflowError, RecursionError, TypeError, KeyError, AttributeError)
"""What untrusted JSON can raise on its way in (``UnicodeDecodeError`` and ``SpecError`` are
``ValueError``s)."""


def _name(value: object, where: str, *, host: bool = False) -> str:
    """A host or topic name from the network: a string of its form, ``MAX_NAME_CHARS`` at most."""
    if not isinstance(value, str) or len(value) > MAX_NAME_CHARS:
        raise ValueError(f"{where}={short_repr(value)} is not a name of at most {MAX_NAME_CHARS}")
    if host and not is_host_name(value):
        raise ValueError(f"{where}={short_repr(value)} is not a host name (letters, digits, _-.~)")
    if not host:
        try:
            check_topic(value)
        except TransportError:
            raise ValueError(f"{where}={short_repr(value)} is not a topic") from None
    return value


def _count(value: object, where: str, maximum: int, minimum: int = 0) -> int:
    """An integer (not a boolean) within ``[minimum, maximum]``."""
    if isinstance(value, bool) or not isinstance(value, int) or not minimum <= value <= maximum:
        raise ValueError(f"{where}={short_repr(value)} is not an integer in [{minimum}, {maximum}]")
    return value


def _document(data: bytes, limit: int) -> Any:
    """JSON from the network, at most ``limit`` bytes of it (checked before parsing)."""
    if len(data) > limit:
        raise ValueError(f"{len(data)} bytes, more than {limit}")
    return json.loads(data)


def _object(value: object, where: str, limit: int | None = None) -> Mapping[str, object]:
    """A JSON object (of at most ``limit`` entries)."""
    if not isinstance(value, dict):
        raise ValueError(f"{where} is not an object")
    if limit is not None and len(value) > limit:
        raise ValueError(f"{where} is not an object of at most {limit} entries")
    return value


def _required(document: Mapping[str, object], name: str) -> object:
    if name not in document:
        raise ValueError(f"{name} is missing")
    return document[name]


# -- the estimator's state: /dbm/estimator_state ----------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class EstimatorState:
    """What the estimator tells others (``/dbm/estimator_state``): its phase and what it measured.

    It travels as JSON (``encode``/``decode``) so that a reader takes fields instead of taking
    text apart; ``text`` is the line a person reads (``dbml monitor``).
    """

    phase: Phase
    received_mbit: float
    queue_delay_s: float
    lost: int
    decided_at_s: float | None = None
    """A decrease's wall-clock time (s) of decision, also in the holds after it while the
    estimate is the cut's: the testbed times a cut by it to the millisecond, where a reader that
    polls the parameter sees it only as often as it polls (and may see only the hold)."""
    reason: str = ""
    """Why the estimator decided as it did, in a few words (may be empty)."""

    @classmethod
    def of(cls, estimate: Estimate, *, decided_at_s: float | None = None) -> EstimatorState:
        """The state of ``estimate``, decided at ``decided_at_s`` (wall clock) if given."""
        return cls(
            phase=estimate.phase,
            received_mbit=estimate.received_mbit,
            queue_delay_s=estimate.queue_delay_s,
            lost=estimate.lost,
            decided_at_s=decided_at_s,
            reason=estimate.reason[:MAX_REASON_CHARS],
        )

    @property
    def text(self) -> str:
        """One readable line: ``decrease: received 3.20 Mbit/s, queueing 40 ms, lost 0 @<s>``."""
        line = (
            f"{self.phase.value}: received {self.received_mbit:.2f} Mbit/s, "
            f"queueing {self.queue_delay_s * 1000:.0f} ms, lost {self.lost}"
        )
        if self.reason:
            line = f"{line} ({self.reason})"
        return line if self.decided_at_s is None else f"{line} @{self.decided_at_s:.3f}"

    def as_json(self) -> dict[str, Any]:
        """The state as a JSON object (rounded: a state is for reading, not for arithmetic)."""
        return {
            "phase": self.phase.value,
            "received_mbit": round(self.received_mbit, 4),
            "queue_delay_s": round(self.queue_delay_s, 4),
            "lost": self.lost,
            "decided_at_s": None if self.decided_at_s is None else round(self.decided_at_s, 3),
            "reason": self.reason,
        }

    def encode(self) -> str:
        """The state as the parameter's value: compact JSON."""
        return json.dumps(self.as_json(), separators=(",", ":"))

    @classmethod
    def from_json(cls, document: object) -> EstimatorState:
        """The state ``as_json`` made; ``SpecError`` naming the field and the value if not."""
        if not isinstance(document, Mapping):
            raise SpecError(f"estimator state={short_repr(document)} is not a JSON object")
        phase = document.get("phase")
        known = _PHASES.get(phase) if isinstance(phase, str) else None
        if known is None:
            raise SpecError(
                f"estimator state: phase={short_repr(phase)} is not one of "
                f"{', '.join(p.value for p in Phase)}"
            )
        lost = document.get("lost")
        if isinstance(lost, bool) or not isinstance(lost, int) or lost < 0:
            raise SpecError(f"estimator state: lost={short_repr(lost)} is not a count")
        decided = document.get("decided_at_s")
        reason = document.get("reason", "")
        if (
            not isinstance(reason, str)
            or len(reason) > MAX_REASON_CHARS
            or not reason.isprintable()
        ):
            raise SpecError(
                f"estimator state: reason={short_repr(reason)} is not a line of at most "
                f"{MAX_REASON_CHARS} printable characters"
            )
        return cls(
            phase=known,
            received_mbit=_state_number(document, "received_mbit"),
            queue_delay_s=_state_number(document, "queue_delay_s"),
            lost=lost,
            decided_at_s=None if decided is None else _state_number(document, "decided_at_s"),
            reason=reason,
        )

    @classmethod
    def decode(cls, text: str) -> EstimatorState:
        """The state ``encode`` wrote; ``SpecError`` naming what is wrong if not."""
        if len(text) > MAX_TEXT_CHARS:
            raise SpecError(
                f"estimator state={short_repr(text)} is longer than {MAX_TEXT_CHARS} characters"
            )
        try:
            document = json.loads(text)
        except (ValueError, RecursionError):
            raise SpecError(f"estimator state={short_repr(text)} is not JSON") from None
        return cls.from_json(document)


_PHASES = {phase.value: phase for phase in Phase}


def _state_number(document: Mapping[str, object], name: str) -> float:
    return check_number(document.get(name), field=name, owner="estimator state", minimum=0.0)


# -- the link beacon: keys.LINK_TOPIC ------------------------------------------------------------

RELEASE_MAX_S = 2.0
"""The latest place in a release order (seconds after the link is back): later ones go
together at it, and a beacon naming one outside ``[0, RELEASE_MAX_S]`` is malformed."""
RELEASE_MAX_CHANNELS = 4096
"""The most channels a release order names (the optimizer allocates at most as many,
``dbml.runtime.optimizer.MAX_CHANNELS``); a beacon naming more is malformed."""
HEARD_MAX = 4096
"""The most channels a beacon names as heard; a beacon naming more is malformed."""
HEARD_RECENT_MAX = 256
"""The most arrivals of one channel a beacon counts (older ones than the release's window are
forgotten): a faster channel's release owes at most this many. A beacon counting more for a
channel is malformed."""
MAX_BEACON_BYTES = (RELEASE_MAX_CHANNELS + HEARD_MAX) * _ENTRY_BYTES + 1024
"""The most bytes a beacon takes: a release order and a ``heard`` of the most channels, each
of the longest name; a larger one is malformed before it is parsed."""


@dataclass(frozen=True, slots=True)
class Heard:
    """What arrived of one channel, as its release after an outage needs to know it.

    With subscribers on several hosts, the one that heard the least: the lowest newest number
    and the most recent frames, so a release never owes less than any of them saw.
    """

    newest_seq: int
    """The sequence number of the newest frame that arrived: later ones may still be in the
    link; earlier ones arrived, or were dropped with a session the outage closed."""
    recent_frames: int
    """Its frames that arrived in the release's window (the last second): they share it."""


@dataclass(frozen=True, slots=True)
class LinkBeacon:
    """The estimator's word on the link: up or down, and the release order after an outage."""

    up: bool
    release_s: Mapping[str, float] = field(default_factory=dict)
    """Per channel, how long after the link is back its held message goes out (0: first)."""
    sent_s: float = 0.0
    """The estimator's clock: a beacon that sat in a buffer through the outage is stale."""
    heard: Mapping[str, Heard] | None = None
    """After an outage, the channels whose frames arrived again, and what of them (None: not
    said). A channel that sent into the dead link waits to be heard before it releases: until
    then its TCP connection still holds that backlog, and a release would queue behind it and
    arrive bunched with it, over the budget. What arrived says what the release owes."""

    def encode(self) -> bytes:
        """The beacon as compact JSON."""
        document: dict[str, Any] = {
            "up": self.up,
            "release_s": dict(self.release_s),
            "sent_s": self.sent_s,
        }
        if self.heard is not None:
            document["heard"] = {
                topic: [h.newest_seq, h.recent_frames] for topic, h in sorted(self.heard.items())
            }
        return json.dumps(document).encode()

    @classmethod
    def decode(cls, data: bytes) -> LinkBeacon:
        """A beacon from its bytes; ``TransportError`` naming what is malformed.

        It comes from the network: ``up`` must be a JSON boolean (``"false"`` is not false),
        every number finite, every release place within ``[0, RELEASE_MAX_S]``, every name a
        topic, every count within its bound, so nothing in it can hold a channel for long or
        break the thread that reads it.
        """
        try:
            document = _object(_document(data, MAX_BEACON_BYTES), "the beacon")
            up = _required(document, "up")
            if not isinstance(up, bool):
                raise TypeError(f"up={short_repr(up)} is not a boolean")
            places = _object(document.get("release_s", {}), "release_s", RELEASE_MAX_CHANNELS)
            release = {
                _name(t, "release_s key"): check_number(
                    v, field=f"release_s[{t!r}]", minimum=0.0, maximum=RELEASE_MAX_S
                )
                for t, v in places.items()
            }
            sent = check_number(document.get("sent_s", 0.0), field="sent_s")
            return cls(up, release, sent, _heard(document.get("heard")))
        except _DECODE_ERRORS as err:
            raise TransportError(f"malformed link beacon {data[:80]!r}: {err}") from err


def _heard(value: object) -> dict[str, Heard] | None:
    """A beacon's ``heard``: absent, or at most ``HEARD_MAX`` ``{topic: [seq, recent]}``.

    Both are integers from 0: ``seq`` at most ``SEQ_MAX``, ``recent`` at most
    ``HEARD_RECENT_MAX``.
    """
    if value is None:
        return None
    heard = {}
    for topic, counts in _object(value, "heard", HEARD_MAX).items():
        match counts:
            case [int() as seq, int() as recent] if (
                not isinstance(seq, bool)
                and not isinstance(recent, bool)
                and 0 <= seq <= SEQ_MAX
                and 0 <= recent <= HEARD_RECENT_MAX
            ):
                heard[_name(topic, "heard key")] = Heard(seq, recent)
            case _:
                raise ValueError(
                    f"heard[{short_repr(topic)}]={short_repr(counts)} is not [newest seq, recent"
                    f" frames], integers from 0 (recent at most {HEARD_RECENT_MAX})"
                )
    return heard


# -- the reception report: keys.RECEPTION_TOPIC -------------------------------------------------

MAX_REPORT_FRAMES = 10_000
"""The most frames one report carries. A base station that subscribes to every channel of 160
robots with 4 channels at 30 Hz receives about a thousand per report interval (0.05 s): this
is ten times that. A report with more is malformed."""
MAX_REPORT_BYTES = (MAX_REPORT_FRAMES + 1) * _ENTRY_BYTES
"""The most bytes a report takes: its most frames, each of the longest topic, and its host;
a larger one is malformed before it is parsed."""
_FRAME_FIELDS = 5


@dataclass(frozen=True, slots=True)
class ReceivedFrame:
    """One frame as a subscriber received it."""

    topic: str
    seq: int
    sent_ns: int
    """The publisher's wall clock."""
    arrival_s: float
    """The reporter's clock (its transport's ``now()``)."""
    size_bytes: int


@dataclass(frozen=True, slots=True)
class ReceptionReport:
    """A batch of frames one host received, with the reporter's clock at sending."""

    host: str
    now_s: float
    frames: tuple[ReceivedFrame, ...]

    def encode(self) -> bytes:
        """The report as JSON bytes."""
        rows = [[f.topic, f.seq, f.sent_ns, f.arrival_s, f.size_bytes] for f in self.frames]
        return json.dumps({"host": self.host, "now_s": self.now_s, "frames": rows}).encode()

    @classmethod
    def decode(cls, data: bytes) -> ReceptionReport:
        """A report from its bytes; ``TransportError`` naming what is malformed.

        Any peer may send one: the host must be a host name, each topic a topic (both at most
        ``MAX_NAME_CHARS``), at most ``MAX_REPORT_FRAMES`` frames, each sequence number within
        the metadata's 64 bits, each time finite, each size within a message's.
        """
        try:
            document = _object(_document(data, MAX_REPORT_BYTES), "the report")
            host = _name(_required(document, "host"), "host", host=True)
            now = check_number(_required(document, "now_s"), field="now_s")
            rows = _required(document, "frames")
            if not isinstance(rows, list) or len(rows) > MAX_REPORT_FRAMES:
                raise ValueError(f"frames is not a list of at most {MAX_REPORT_FRAMES}")
            frames = tuple(_frame(row, f"frames[{k}]") for k, row in enumerate(rows))
            return cls(host, now, frames)
        except _DECODE_ERRORS as err:
            raise TransportError(f"malformed reception report {data[:80]!r}: {err}") from err


def _frame(row: object, where: str) -> ReceivedFrame:
    """One ``[topic, seq, sent_ns, arrival_s, size_bytes]`` row of a report."""
    if not isinstance(row, list) or len(row) != _FRAME_FIELDS:
        raise ValueError(
            f"{where}={short_repr(row)} is not [topic, seq, sent_ns, arrival_s, size_bytes]"
        )
    topic, seq, sent, arrival, size = row
    return ReceivedFrame(
        _name(topic, f"{where}.topic"),
        _count(seq, f"{where}.seq", SEQ_MAX, _SEQ_MIN),
        _count(sent, f"{where}.sent_ns", _SENT_NS_MAX, _SENT_NS_MIN),
        check_number(arrival, field=f"{where}.arrival_s"),
        _count(size, f"{where}.size_bytes", int(MAX_SIZE_BYTES)),
    )


# -- the round report -------------------------------------------------------------------------

MAX_REPORTED_CHANNELS = 4096
"""The most channels a round reports: the most the optimizer tracks (``MAX_CHANNELS``)."""
MAX_ROUND_BYTES = 4 << 20
"""A round report larger than this is refused unread: 4,096 channels take about 1.2 MB."""
_BYTES_PER_S_PER_MBIT = 125_000


def _round_number(
    document: Mapping[str, object],
    field: str,
    *,
    minimum: float = 0.0,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
) -> float:
    """A finite number of a round report's ``document``, within its range."""
    try:
        return check_number(
            document.get(field),
            field=field,
            minimum=minimum,
            maximum=maximum,
            exclusive_minimum=exclusive_minimum,
        )
    except SpecError as err:
        raise TransportError(str(err)) from None


def _round_optional(
    document: Mapping[str, object],
    field: str,
    *,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
) -> float | None:
    """``_round_number``, or None where the field is null (not known)."""
    if document.get(field) is None:
        return None
    return _round_number(document, field, maximum=maximum, exclusive_minimum=exclusive_minimum)


def _round_encoding(value: object) -> str | None:
    """A rung's label (``dbml.protocol.ladders``), or None where absent."""
    if value is None:
        return None
    try:
        parse_encoding(value)
    except SpecError as err:
        raise TransportError(str(err)) from None
    return str(value)


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
    encoding: str | None = None
    """A laddered channel's rung (``x0.5 q80``); its bytes are ``size_bytes``."""
    quality: float | None = None
    """The rung's quality score in [0, 1] (None: no ladder)."""
    sent_hz: float | None = None
    """The rate its publisher last said it sent (None: not said yet)."""

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
            "encoding": self.encoding,  # last: viewers' tables keep the columns they had
            "quality": self.quality,
            "sent_hz": self.sent_hz,
        }

    @classmethod
    def from_json(cls, document: object) -> ChannelRound:
        """A channel of a received report; ``TransportError`` naming a bad field."""
        if not isinstance(document, dict):
            raise TransportError(f"round channel={short_repr(document)} is not an object")
        try:
            topic = _name(document.get("topic"), "round channel topic")
        except ValueError as err:
            raise TransportError(str(err)) from None
        managed = document.get("managed")
        if not isinstance(managed, bool):
            raise TransportError(f"{topic}: managed={short_repr(managed)} is not a boolean")
        try:
            channel = cls(
                topic=topic,
                managed=managed,
                priority=_round_number(document, "priority", maximum=1.0),
                min_hz=_round_number(document, "min_hz", maximum=MAX_RATE_HZ),
                max_hz=_round_number(document, "max_hz", maximum=MAX_RATE_HZ),
                size_bytes=_round_optional(
                    document, "size_bytes", exclusive_minimum=True, maximum=MAX_SIZE_BYTES
                ),
                normalized_priority=_round_optional(document, "normalized_priority", maximum=1.0),
                floor_hz=_round_optional(document, "floor_hz", maximum=MAX_RATE_HZ),
                rate_hz=_round_optional(document, "rate_hz", maximum=MAX_RATE_HZ),
                share=_round_optional(document, "share"),
                encoding=_round_encoding(document.get("encoding")),
                quality=_round_optional(document, "quality", maximum=1.0),
                sent_hz=_round_optional(document, "sent_hz", maximum=MAX_RATE_HZ),
            )
        except TransportError as err:
            raise TransportError(f"{topic}: {err}") from None
        if channel.min_hz > channel.max_hz:
            raise TransportError(
                f"{topic}: min_hz={channel.min_hz!r} is above max_hz={channel.max_hz!r}"
            )
        return channel


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
        """The round's entry of ``topic``, if it reported one (``by_topic`` for many)."""
        return next((c for c in self.channels if c.topic == topic), None)

    def by_topic(self) -> dict[str, ChannelRound]:
        """Every channel's entry, by topic."""
        return {c.topic: c for c in self.channels}

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
        budget = _round_optional(document, "budget_mbit", exclusive_minimum=True)
        rows = tuple(ChannelRound.from_json(c) for c in channels)
        if len({row.topic for row in rows}) < len(rows):
            raise TransportError("round report channels name a topic twice")
        return cls(
            round=counter,
            status=Status(status),
            message=message,
            strategy=Strategy(strategy),
            budget_mbit=budget,
            channels=rows,
        )
