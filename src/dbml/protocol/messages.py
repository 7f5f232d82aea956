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
  (``TransportError``).

Dependencies point one way: this module imports the pure estimator (``dbml.estimator``: a
state's ``Phase``, made ``of`` an ``Estimate``) and the rest of ``dbml.protocol``, never the
runtime; the estimator imports nothing of the wire.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from dbml.core.errors import SpecError, TransportError
from dbml.core.spec import MAX_SIZE_BYTES, check_number, short_repr
from dbml.estimator.base import Estimate, Phase
from dbml.protocol.keys import is_host_name
from dbml.protocol.metadata import SEQ_MAX
from dbml.protocol.names import check_topic
from dbml.protocol.schema import MAX_TEXT_CHARS

__all__ = [
    "HEARD_MAX",
    "HEARD_RECENT_MAX",
    "MAX_BEACON_BYTES",
    "MAX_NAME_CHARS",
    "MAX_REPORT_BYTES",
    "MAX_REPORT_FRAMES",
    "RELEASE_MAX_CHANNELS",
    "RELEASE_MAX_S",
    "EstimatorState",
    "Heard",
    "LinkBeacon",
    "ReceivedFrame",
    "ReceptionReport",
]

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

    @classmethod
    def of(cls, estimate: Estimate, *, decided_at_s: float | None = None) -> EstimatorState:
        """The state of ``estimate``, decided at ``decided_at_s`` (wall clock) if given."""
        return cls(
            phase=estimate.phase,
            received_mbit=estimate.received_mbit,
            queue_delay_s=estimate.queue_delay_s,
            lost=estimate.lost,
            decided_at_s=decided_at_s,
        )

    @property
    def text(self) -> str:
        """One readable line: ``decrease: received 3.20 Mbit/s, queueing 40 ms, lost 0 @<s>``."""
        line = (
            f"{self.phase.value}: received {self.received_mbit:.2f} Mbit/s, "
            f"queueing {self.queue_delay_s * 1000:.0f} ms, lost {self.lost}"
        )
        return line if self.decided_at_s is None else f"{line} @{self.decided_at_s:.3f}"

    def as_json(self) -> dict[str, Any]:
        """The state as a JSON object (rounded: a state is for reading, not for arithmetic)."""
        return {
            "phase": self.phase.value,
            "received_mbit": round(self.received_mbit, 4),
            "queue_delay_s": round(self.queue_delay_s, 4),
            "lost": self.lost,
            "decided_at_s": None if self.decided_at_s is None else round(self.decided_at_s, 3),
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
        return cls(
            phase=known,
            received_mbit=_state_number(document, "received_mbit"),
            queue_delay_s=_state_number(document, "queue_delay_s"),
            lost=lost,
            decided_at_s=None if decided is None else _state_number(document, "decided_at_s"),
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
