"""Reception reports: what a reporter keeps between flushes is bounded."""

from __future__ import annotations

import logging

import pytest

from dbml.protocol.metadata import pack_meta
from dbml.runtime.reception import MAX_FRAMES, MAX_TOPICS, ReceptionReporter
from dbml.transports import MemoryNetwork, MemoryTransport, Sample


def test_frames_recorded_between_flushes_are_bounded_and_a_flood_is_said_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Frames any peer publishes are recorded: unflushed, the oldest half goes, said once."""
    reporter = ReceptionReporter(MemoryTransport(MemoryNetwork(), host="op"))  # not started
    frames = 3 * MAX_FRAMES
    with caplog.at_level(logging.WARNING, logger="dbml.reception"):
        for seq in range(frames):
            reporter.record(Sample("/r1/camera", b"x", pack_meta(seq, 0, 1.0)))
            assert len(reporter._frames) <= MAX_FRAMES
        assert reporter._frames[-1].seq == frames - 1  # the newest are kept
        reporter.flush()  # takes what is left: the flood is over
        reporter.record(Sample("/r1/camera", b"x", pack_meta(frames, 0, 1.0)))
    evicted = frames - MAX_FRAMES  # the last flush took the rest
    assert [r.getMessage() for r in caplog.records] == [
        f"received frames recorded: {MAX_FRAMES} held, the most kept; evicting the oldest "
        "(told once until half of them are gone)",
        f"received frames recorded: room again; {evicted} evicted meanwhile",
    ]
    reporter.close()


def test_the_quickest_frame_is_kept_for_at_most_max_topics() -> None:
    """Any peer publishes: a flood of topics restarts the table instead of growing it."""
    reporter = ReceptionReporter(MemoryTransport(MemoryNetwork(), host="op"))  # not started
    for k in range(MAX_TOPICS + 1):
        reporter.record(Sample(f"/r{k}/camera", b"x", pack_meta(0, 0, 1.0)))
        assert len(reporter._quickest) <= MAX_TOPICS
    assert list(reporter._quickest) == [f"/r{MAX_TOPICS}/camera"]  # the newest, after a restart
    reporter.close()
