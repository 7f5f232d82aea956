"""The reports that travel from a run's processes to the runner: the operator's, a bridge's.

Every ``TICK_S`` the operator reports the frames that arrived since its last report and the
parameters in force: one JSON object per line, with named keys (a frame is
``{"robot": 0, "seq": 12, "sent_s": ..., "arrival_s": ..., "size_bytes": ..., "rate_hz": ...}``).
Both sides go through :class:`OperatorReport`, so the writer and the reader cannot drift apart;
a malformed report raises ``SpecError`` naming the field and the value.

At its end a bridge reports how its publishes went (:class:`PublishReport`), where the
middleware's publisher times them (rclpy's): the runner keeps it with the run's recording.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dbml.core.errors import SpecError
from dbml.core.spec import check_number, short_repr
from dbml.experiment.analysis import Arrival, Tick
from dbml.protocol.messages import EstimatorState

__all__ = ["PUBLISH_REPORT", "TICK", "OperatorReport", "PublishReport", "PublishTiming"]

TICK = "tick"
"""The operator's report's ``type``, beside the roles' ``ready`` and ``done``."""
PUBLISH_REPORT = "publish_stats"
"""The ``type`` of a bridge's report of its publishes."""
_OWNER = "operator report"
_PUBLISH_OWNER = "publish report"


@dataclass(frozen=True, slots=True)
class OperatorReport:
    """One tick of the operator: the parameters it saw and the frames that arrived since."""

    tick: Tick
    frames: tuple[Arrival, ...] = ()

    def encode(self) -> dict[str, Any]:
        """The report as one JSON-able message (``harness.child.emit_json``)."""
        tick = self.tick
        return {
            "type": TICK,
            "t": tick.t_s,
            "frames": [_encode_frame(frame) for frame in self.frames],
            "allocated_hz": list(tick.allocated_hz),
            "budget_mbit": tick.budget_mbit,
            "estimate_mbit": tick.estimate_mbit,
            "estimator": None if tick.estimator is None else tick.estimator.as_json(),
            "variants": list(tick.variants),
            "encodings": list(tick.encodings),
        }

    @classmethod
    def decode(cls, message: Mapping[str, Any]) -> OperatorReport:
        """The report ``encode`` made; ``SpecError`` naming the field and the value if not."""
        if message.get("type") != TICK:
            raise SpecError(f"{_OWNER}: type={short_repr(message.get('type'))} is not {TICK!r}")
        frames = _items(message, "frames")
        estimator = message.get("estimator")
        tick = Tick(
            t_s=_number(message.get("t"), "t"),
            allocated_hz=tuple(
                _optional_number(value, f"allocated_hz[{k}]")
                for k, value in enumerate(_items(message, "allocated_hz"))
            ),
            budget_mbit=_optional_number(message.get("budget_mbit"), "budget_mbit"),
            estimate_mbit=_optional_number(message.get("estimate_mbit"), "estimate_mbit"),
            estimator=None if estimator is None else EstimatorState.from_json(estimator),
            variants=tuple(
                _text(value, f"variants[{k}]")
                for k, value in enumerate(_items(message, "variants"))
            ),
            encodings=tuple(
                None if value is None else _text(value, f"encodings[{k}]")
                for k, value in enumerate(message.get("encodings") or [])
            ),
        )
        return cls(
            tick, tuple(_decode_frame(frame, f"frames[{k}]") for k, frame in enumerate(frames))
        )


@dataclass(frozen=True, slots=True)
class PublishTiming:
    """How one publisher's ``publish()`` calls went (the middleware's own statistics)."""

    topic: str
    """The middleware's topic (``[topic]/optimized``)."""
    published: int
    dropped: int
    """Calls the middleware refused (counted, never passed on)."""
    max_ms: float | None
    p99_ms: float | None


@dataclass(frozen=True, slots=True)
class PublishReport:
    """A bridge's report at its end: each publisher's timing (none where none is kept)."""

    publishers: tuple[PublishTiming, ...] = ()

    def encode(self) -> dict[str, Any]:
        """The report as one JSON-able message."""
        return {
            "type": PUBLISH_REPORT,
            "publishers": [
                {
                    "topic": p.topic,
                    "published": p.published,
                    "dropped": p.dropped,
                    "max_ms": p.max_ms,
                    "p99_ms": p.p99_ms,
                }
                for p in self.publishers
            ],
        }

    @classmethod
    def decode(cls, message: Mapping[str, Any]) -> PublishReport:
        """The report ``encode`` made; ``SpecError`` naming the field and the value if not."""
        kind = message.get("type")
        if kind != PUBLISH_REPORT:
            raise SpecError(f"{_PUBLISH_OWNER}: type={short_repr(kind)} is not {PUBLISH_REPORT!r}")
        return cls(
            tuple(
                _decode_timing(row, f"publishers[{k}]")
                for k, row in enumerate(_items(message, "publishers", _PUBLISH_OWNER))
            )
        )


def _decode_timing(document: object, field: str) -> PublishTiming:
    owner = _PUBLISH_OWNER
    if not isinstance(document, Mapping):
        raise SpecError(f"{owner}: {field}={short_repr(document)} is not a JSON object")
    return PublishTiming(
        topic=_text(document.get("topic"), f"{field}.topic", owner),
        published=_count(document.get("published"), f"{field}.published", owner),
        dropped=_count(document.get("dropped"), f"{field}.dropped", owner),
        max_ms=_optional_number(document.get("max_ms"), f"{field}.max_ms", owner),
        p99_ms=_optional_number(document.get("p99_ms"), f"{field}.p99_ms", owner),
    )


def _encode_frame(frame: Arrival) -> dict[str, Any]:
    return {
        "robot": frame.robot,
        "seq": frame.seq,
        "sent_s": frame.sent_s,
        "arrival_s": frame.arrival_s,
        "size_bytes": frame.size_bytes,
        "rate_hz": frame.rate_hz,
        "ssim": frame.ssim,
    }


def _decode_frame(document: object, field: str) -> Arrival:
    if not isinstance(document, Mapping):
        raise SpecError(f"{_OWNER}: {field}={short_repr(document)} is not a JSON object")
    seq = document.get("seq")
    return Arrival(
        robot=_count(document.get("robot"), f"{field}.robot"),
        seq=None if seq is None else _count(seq, f"{field}.seq"),
        sent_s=_optional_number(document.get("sent_s"), f"{field}.sent_s"),
        arrival_s=_number(document.get("arrival_s"), f"{field}.arrival_s"),
        size_bytes=_count(document.get("size_bytes"), f"{field}.size_bytes"),
        rate_hz=_optional_number(document.get("rate_hz"), f"{field}.rate_hz"),
        ssim=_optional_number(document.get("ssim"), f"{field}.ssim"),
    )


def _items(message: Mapping[str, Any], field: str, owner: str = _OWNER) -> list[object]:
    value = message.get(field)
    if not isinstance(value, list):
        raise SpecError(f"{owner}: {field}={short_repr(value)} is not a list")
    return value


def _number(value: object, field: str, owner: str = _OWNER) -> float:
    return check_number(value, field=field, owner=owner)


def _optional_number(value: object, field: str, owner: str = _OWNER) -> float | None:
    return None if value is None else _number(value, field, owner)


def _count(value: object, field: str, owner: str = _OWNER) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise SpecError(f"{owner}: {field}={short_repr(value)} is not a count")
    return value


def _text(value: object, field: str, owner: str = _OWNER) -> str:
    if not isinstance(value, str):
        raise SpecError(f"{owner}: {field}={short_repr(value)} is not a string")
    return value
