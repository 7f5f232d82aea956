"""Reception reports: what subscribers actually receive, for a bandwidth estimator elsewhere.

A managed subscriber that receives ``[topic]/optimized`` (the copy that crosses the network)
records each frame's sequence number, send time, arrival time and size. A reporter batches these
records and publishes them on ``/dbm/reception`` every ``interval_s``, but only while someone
listens (an optimizer started with ``--estimate``), so reporting costs nothing otherwise.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from typing import Any

from dbml.core.errors import TransportError
from dbml.runtime.metadata import MessageMeta
from dbml.transports.base import Sample, Transport

__all__ = ["RECEPTION_TOPIC", "Frame", "ReceptionReport", "ReceptionReporter"]

log = logging.getLogger("dbml.reception")

RECEPTION_TOPIC = "/dbm/reception"
_MAX_FRAMES = 10_000
"""Frames kept between flushes at most; beyond that the oldest are dropped (nobody reads)."""


@dataclass(frozen=True, slots=True)
class Frame:
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
    frames: tuple[Frame, ...]

    def encode(self) -> bytes:
        rows = [[f.topic, f.seq, f.sent_ns, f.arrival_s, f.size_bytes] for f in self.frames]
        return json.dumps({"host": self.host, "now_s": self.now_s, "frames": rows}).encode()

    @classmethod
    def decode(cls, data: bytes) -> ReceptionReport:
        try:
            document: dict[str, Any] = json.loads(data)
            frames = tuple(
                Frame(str(topic), int(seq), int(sent), float(arrival), int(size))
                for topic, seq, sent, arrival, size in document["frames"]
            )
            return cls(str(document["host"]), float(document["now_s"]), frames)
        except (ValueError, KeyError, TypeError) as err:
            raise TransportError(f"malformed reception report {data[:80]!r}") from err


class ReceptionReporter:
    """Collects frames from managed subscribers and publishes them in batches."""

    def __init__(self, transport: Transport, *, interval_s: float = 0.1) -> None:
        self._transport = transport
        self._interval_s = interval_s
        self._publisher = transport.declare_publisher(RECEPTION_TOPIC)
        self._frames: list[Frame] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def record(self, sample: Sample) -> None:
        """Note one received frame (called on the middleware's thread: cheap, never blocks)."""
        if sample.attachment is None:
            return
        try:
            meta = MessageMeta.decode(sample.attachment)
        except TransportError:
            return  # not a dbml publisher: nothing to learn about the link from it
        frame = Frame(
            sample.topic, meta.seq, meta.sent_ns, self._transport.now(), len(sample.payload)
        )
        with self._lock:
            if len(self._frames) >= _MAX_FRAMES:
                del self._frames[: _MAX_FRAMES // 2]
            self._frames.append(frame)

    def flush(self) -> int:
        """Publish what was recorded since the last flush; returns the frames sent."""
        with self._lock:
            frames, self._frames = self._frames, []
        if not frames or not self._publisher.has_subscribers:
            return 0
        report = ReceptionReport(self._transport.host, self._transport.now(), tuple(frames))
        self._publisher.put(report.encode())
        return len(frames)

    def start(self) -> ReceptionReporter:
        self._thread = threading.Thread(target=self._run, name="dbml-reception", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self._interval_s):
            try:
                self.flush()
            except Exception:  # keep reporting; the next flush retries
                log.exception("reception report failed")

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        self._publisher.close()
