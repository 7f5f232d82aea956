"""Reception reports: what subscribers actually receive, for a bandwidth estimator elsewhere.

A managed subscriber that receives ``[topic]/optimized`` (the copy that crosses the network)
records each frame's sequence number, send time, arrival time and size. A reporter batches these
records and publishes them on ``/dbm/reception`` every ``interval_s``, and at once (once an
interval at most) when a frame took ``EARLY_FLUSH_QUEUE_S`` longer than its topic's quickest,
but only while someone listens (an optimizer started with ``--estimate``), so reporting costs
nothing otherwise.
"""

from __future__ import annotations

import logging
import threading

from dbml.core.errors import TransportError
from dbml.protocol import keys
from dbml.protocol.messages import MAX_NAME_CHARS, MAX_REPORT_FRAMES, ReceivedFrame, ReceptionReport
from dbml.protocol.metadata import MessageMeta
from dbml.runtime.worker import PeriodicWorker
from dbml.transports.base import Sample, Transport
from dbml.transports.overflow import Overflow

__all__ = [
    "EARLY_FLUSH_QUEUE_S",
    "MAX_FRAMES",
    "MAX_TOPICS",
    "REPORT_INTERVAL_S",
    "ReceptionReporter",
]

log = logging.getLogger("dbml.reception")

REPORT_INTERVAL_S = 0.05
"""How often a reporter sends what it recorded: the estimator judges this much and half again
in the past (frames still on their way to it), so it is part of the time to a cut."""
EARLY_FLUSH_QUEUE_S = 0.1
"""A frame that took this much longer than its topic's quickest is flushed at once: the link
may have slowed, and the estimator cuts sooner for it (at most one early flush per
``interval_s``, so a congested link at most doubles the reports)."""
MAX_TOPICS = 4096
"""Topics whose quickest frame is kept; past it the table starts again (any peer publishes)."""
MAX_FRAMES = MAX_REPORT_FRAMES
"""Frames kept between two flushes at most, the most one report carries. A base station that
subscribes to every channel of 160 robots with 4 channels at 30 Hz records about a thousand per
``REPORT_INTERVAL_S``: this is ten times that (a flush late by half a second). What any peer
publishes is recorded, so past this the oldest half is dropped (they are stale by then), logged
once per flood with a count (the flood ends when a flush takes what is left). A frame is about
200 bytes: 2 MB at most."""


class ReceptionReporter:
    """Collects frames from managed subscribers and publishes them in batches."""

    def __init__(self, transport: Transport, *, interval_s: float = REPORT_INTERVAL_S) -> None:
        self._transport = transport
        self._publisher = transport.declare_publisher(keys.RECEPTION_TOPIC)
        self._frames: list[ReceivedFrame] = []
        """Recorded since the last flush, oldest first (``MAX_FRAMES`` at most)."""
        self._full = Overflow("received frames recorded", MAX_FRAMES, log=log, evicts=True)
        self._lock = threading.Lock()
        self._interval_s = interval_s
        self._quickest: dict[str, float] = {}
        """Per topic, the least of arrival minus send time seen: the clocks' offset plus the
        transit of a frame that did not queue."""
        self._early_s = -float("inf")
        """Our clock at the last early flush."""
        self._worker = PeriodicWorker(
            self.flush, interval_s=interval_s, name="dbml-reception", log=log
        )

    def record(self, sample: Sample) -> None:
        """Note one received frame (called on the middleware's thread: cheap, never blocks)."""
        if sample.attachment is None or len(sample.topic) > MAX_NAME_CHARS:
            return  # a name longer than a report carries would cost the whole report
        try:
            meta = MessageMeta.decode(sample.attachment)
        except TransportError:
            return  # not a dbml publisher: nothing to learn about the link from it
        frame = ReceivedFrame(
            sample.topic, meta.seq, meta.sent_ns, self._transport.now(), len(sample.payload)
        )
        took = frame.arrival_s - frame.sent_ns / 1e9
        early = False
        with self._lock:
            if len(self._frames) >= MAX_FRAMES:
                del self._frames[: MAX_FRAMES // 2]
                self._full.refuse(MAX_FRAMES // 2)
            self._frames.append(frame)
            quickest = self._quickest.get(frame.topic)
            if quickest is None and len(self._quickest) >= MAX_TOPICS:
                self._quickest.clear()
            self._quickest[frame.topic] = took if quickest is None else min(quickest, took)
            if (
                quickest is not None
                and took - quickest >= EARLY_FLUSH_QUEUE_S
                and frame.arrival_s - self._early_s >= self._interval_s
            ):
                self._early_s = frame.arrival_s
                early = True
        if early:
            self._worker.wake()  # flush now: the estimator judges this frame sooner

    def flush(self) -> int:
        """Publish what was recorded since the last flush; returns the frames sent."""
        with self._lock:
            frames, self._frames = self._frames, []
        self._full.room(0)
        if not frames or not self._publisher.has_subscribers:
            return 0
        report = ReceptionReport(self._transport.host, self._transport.now(), tuple(frames))
        self._publisher.put(report.encode())
        return len(frames)

    @property
    def alive(self) -> bool:
        """False once its thread died (the command then exits non-zero)."""
        return self._worker.alive

    def start(self) -> ReceptionReporter:
        """Flush every interval on a thread of its own."""
        self._worker.start()
        return self

    def close(self) -> None:
        """Stop flushing and undeclare the report publisher."""
        self._worker.stop()
        self._publisher.close()
