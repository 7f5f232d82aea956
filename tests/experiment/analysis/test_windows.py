"""One robot over one window: a delivered rate timed exactly, and the link's rates in force."""

from __future__ import annotations

import pytest

from dbml.experiment.analysis import rate_hz, settle_s
from dbml.experiment.analysis.windows import link_rates


@pytest.mark.parametrize("offset_s", [0.0, 0.1, 0.3, 0.55])
def test_a_slow_stream_is_timed_exactly_in_a_short_step(offset_s: float) -> None:
    # 1.48 Hz (Table 2's slowest) in a 2 s step: one or two frames after the settling time,
    # timed from the frame before the window, so the 5 % check holds whatever the phase
    period = 1 / 1.48
    times = [offset_s + k * period for k in range(20)]
    start = 4.0 + settle_s(2.0)
    assert rate_hz(times, start, 6.0) == pytest.approx(1.48, rel=1e-9)


def test_a_stream_delayed_now_and_then_by_another_is_timed_at_its_rate() -> None:
    # 16 Hz whose every third frame waits 62 ms behind another robot's 84 KB frame, in a 1.33 s
    # window that ends just after a delayed one (its first-to-last span reads 15.3 Hz)
    times = [k / 16 + (0.075 if k % 3 == 0 else 0.013) for k in range(64)]
    start, end = 2.05 + settle_s(2.0), 4.05
    assert rate_hz(times, start, end) == pytest.approx(16.0, rel=0.01)


def test_a_window_without_a_gap_to_time_counts() -> None:
    assert rate_hz([0.5], 0.0, 2.0) == 0.5
    assert rate_hz([], 0.0, 2.0) == 0.0


def test_a_schedule_starting_below_the_default_link_starts_there() -> None:
    """RFC 8867's 5.1 starts at 4.4 Mbit/s: the first phase is 4.4, not the default 11."""
    rates = link_rates(((0.0, 4.4), (40.0, 11.0), (60.0, 2.6)), 11.0)
    assert rates == [(0.0, 4.4), (40.0, 11.0), (60.0, 2.6)]
    assert link_rates(((20.0, 5.0),), 11.0) == [(0.0, 11.0), (20.0, 5.0)]
