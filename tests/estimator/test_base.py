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
