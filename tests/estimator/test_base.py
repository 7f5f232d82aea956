"""What the designs measure alike: the link's rate from packet pairs."""

from __future__ import annotations

import pytest

from dbml.estimator.base import busy_rate_mbit

FRAME_BYTES = 84_000
QUEUED_S = 0.05


def _back_to_back(
    mbit: float, count: int, *, start_s: float = 0.0
) -> list[tuple[float, float, int]]:
    """``count`` frames that queued, arriving one transmission apart on a ``mbit`` link."""
    gap_s = FRAME_BYTES * 8e-6 / mbit
    return [(start_s + i * gap_s, 0.1, FRAME_BYTES) for i in range(count)]


def test_a_pair_across_a_fade_does_not_set_the_rate() -> None:
    """The first frame after a 300-ms fade arrives late; the ones behind it at the link's rate."""
    before = _back_to_back(12.0, 2)
    after = _back_to_back(12.0, 4, start_s=before[-1][0] + 0.3)
    assert busy_rate_mbit(before + after, QUEUED_S) == pytest.approx(12.0)


def test_too_few_pairs_say_nothing_when_more_are_asked() -> None:
    frames = _back_to_back(5.0, 3)
    assert busy_rate_mbit(frames, QUEUED_S, least=3) is None
    assert busy_rate_mbit(frames, QUEUED_S, least=2) == pytest.approx(5.0)


def test_frames_that_did_not_queue_are_not_pairs() -> None:
    idle = [(t, 0.0, size) for t, _, size in _back_to_back(5.0, 6)]
    assert busy_rate_mbit(idle, QUEUED_S) is None


HELD = [
    (8.227, 0.129, FRAME_BYTES),
    (8.686, 0.521, FRAME_BYTES),
    (8.693, 0.461, FRAME_BYTES),
    (8.693, 0.393, FRAME_BYTES),
    (8.796, 0.429, FRAME_BYTES),
    (8.940, 0.499, FRAME_BYTES),
]
"""R1's frames (arrival, queueing, size) after 11 -> 5 Mbit/s in a testbed run that failed.

The second waited for a retransmission; the two behind it had crossed meanwhile and came out
with it, and the one after them had partly crossed. Their pairs read 1.5, 96, unbounded, 6.5
and 4.7 Mbit/s: the cut read the link at 6.5 (0.95 of it went back to the 5-Mbit/s link).
"""


def test_frames_that_come_out_together_read_with_the_stall_before_them() -> None:
    alone = busy_rate_mbit(HELD, QUEUED_S)  # each pair alone
    assert alone is not None
    assert alone > 6.0
    payload_mbit = 5.0 * 0.957  # what the link carried as payload, measured in test_netns
    rate = busy_rate_mbit(HELD, QUEUED_S, fastest_mbit=12.65)
    assert rate == pytest.approx(payload_mbit, rel=0.03)
    # Before the frame after them had arrived whole: the stall, the burst and that frame are
    # one reading, not a second one as fast as the burst left it.
    rate = busy_rate_mbit(HELD[:5], QUEUED_S, fastest_mbit=12.65)
    assert rate == pytest.approx(payload_mbit, rel=0.03)


def test_a_link_faster_than_the_budget_is_read_as_it_is() -> None:
    """A radio at 14 Mbit/s under a 10-Mbit/s budget: its pairs are no burst."""
    frames = _back_to_back(14.0, 6)
    assert busy_rate_mbit(frames, QUEUED_S, fastest_mbit=12.5) == pytest.approx(14.0)


def test_empty_frames_arriving_together_read_nothing() -> None:
    """A report's sizes may be 0 (any peer sends them): such a burst is no reading, no error."""
    frames = [(1.0, 0.5, 0), (1.0, 0.5, 0), (1.0, 0.5, 0)]
    assert busy_rate_mbit(frames, QUEUED_S, fastest_mbit=12.5) is None
