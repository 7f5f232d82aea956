"""The measurements more than one design takes (``dbml.estimator.base``)."""

from __future__ import annotations

import pytest

from dbml.estimator.base import busy_rate_mbit, pair_rate_mbit

FRAME_BYTES = 21_000
LINK_MBIT = 10.5
SERVICE_S = FRAME_BYTES * 8e-6 / LINK_MBIT
QUEUED_S = 0.02


def _back_to_back(
    count: int, *, fade_s: float = 0.0, at: int = -1
) -> list[tuple[float, float, int]]:
    """Frames that each waited (queueing 50 ms) and left one service apart; a fade before ``at``."""
    t, out = 0.0, []
    for i in range(count):
        t += SERVICE_S + (fade_s if i == at else 0.0)
        out.append((t, 0.05, FRAME_BYTES))
    return out


def test_the_pair_rate_is_the_links() -> None:
    assert pair_rate_mbit(_back_to_back(10), QUEUED_S) == pytest.approx(LINK_MBIT)


def test_a_pair_across_a_fade_does_not_make_the_pair_rate() -> None:
    frames = _back_to_back(10, fade_s=0.3, at=5)
    assert pair_rate_mbit(frames, QUEUED_S) == pytest.approx(LINK_MBIT)
    # the bytes over the time, as the reference: the fade's gap pulls it to a third
    busy = busy_rate_mbit(frames, QUEUED_S)
    assert busy is not None
    assert busy < 0.5 * LINK_MBIT


def test_frames_that_did_not_wait_are_no_pairs() -> None:
    idle = [(t, 0.0, size) for t, _, size in _back_to_back(10)]
    assert pair_rate_mbit(idle, QUEUED_S) is None
    assert pair_rate_mbit([], QUEUED_S) is None
