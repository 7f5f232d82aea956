"""A run step by step: rate, latency, losses and goodput per robot."""

from __future__ import annotations

import pytest

from dbml.experiment.analysis import Tick, Window, analyse
from tests.experiment.analysis.frames import stream


def test_steps_measure_rate_latency_losses_and_goodput() -> None:
    t0 = 1000.0
    frames = [
        *stream(0, hz=10, start=t0, end=t0 + 4, delay=0.05, size=100_000, skip=25),
        *stream(1, hz=4, start=t0, end=t0 + 4, delay=0.2, size=10_000),
    ]
    ticks = [Tick(t0 + 0.5, (10.0, 4.0), 9.0, None)]
    result = analyse(frames, ticks, robots=["R1", "R2"], t0=t0, step_s=2.0, steps=2, link_mbit=11.0)
    first, second = result.steps
    r1, r2 = first.robots
    assert r1.delivered_hz == pytest.approx(10.0, rel=1e-6)
    assert r2.delivered_hz == pytest.approx(4.0, rel=1e-6)
    assert r1.latency_p50_ms == pytest.approx(50.0)
    assert r2.latency_p95_ms == pytest.approx(200.0)
    assert r1.lost == 0
    assert second.robots[0].lost == 1  # frame 25, sent at 2.5 s
    # goodput over the measured part of the step: 10 x 100 kB + 4 x 10 kB per second
    assert first.goodput_mbit == pytest.approx((10 * 100_000 + 4 * 10_000) * 8e-6, rel=0.1)
    assert first.budget_mbit == 9.0
    assert first.link_mbit == 11.0


def test_a_rate_is_judged_against_the_allocations_in_force_over_its_window() -> None:
    """Moved from 10 to 16 Hz halfway through the window: 13 Hz delivered is what was allowed.

    Judged against the last allocation alone, R1 would be 19 % short; R2, which stayed at 10 Hz
    through the same change, is short of the 13 Hz it was allowed on average.
    """
    t0 = 1000.0
    frames = [
        *stream(0, hz=10, start=t0, end=t0 + 2, delay=0.01, size=1_000),
        *stream(0, hz=16, start=t0 + 2, end=t0 + 3, delay=0.01, size=1_000),
        *stream(1, hz=10, start=t0, end=t0 + 3, delay=0.01, size=1_000),
    ]
    ticks = [Tick(t0 + 0.5, (10.0, 10.0), 9.0, None), Tick(t0 + 2.0, (16.0, 16.0), 9.0, None)]
    result = analyse(frames, ticks, robots=["R1", "R2"], t0=t0, step_s=3.0, steps=1, link_mbit=11.0)
    (step,) = result.steps
    moved, stayed = step.robots
    assert moved.allocated_hz == 16.0  # the allocation at the window's end, as reported
    assert moved.allocated_mean_hz == pytest.approx(13.0)  # the window is [t0 + 1, t0 + 3)
    assert abs(moved.delivered_hz - 16.0) > 0.05 * 16.0
    assert moved.within_rate()
    assert stayed.delivered_hz == pytest.approx(10.0, rel=1e-6)
    assert not stayed.within_rate()


@pytest.mark.parametrize(
    ("delivered_hz", "followed"),
    [(15.51, True), (14.0, True), (16.5, True), (13.3, False), (17.2, False)],
)
def test_a_rate_that_moved_and_came_back_is_followed_between_its_mean_and_last(
    delivered_hz: float, followed: bool
) -> None:
    """The photo demo's R2 in a CI run: last 16 Hz, 14.36 Hz on the ticks' mean, 15.51 delivered.

    The ticks sample the allocation every 0.2 s and the publisher follows a reaction later, so
    anything between the two is followed; 5 % beyond either is not.
    """
    window = Window(
        "R2",
        allocated_hz=16.0,
        delivered_hz=delivered_hz,
        latency_p50_ms=None,
        latency_p95_ms=None,
        lost=0,
        goodput_mbit=0.0,
        allocated_mean_hz=14.357,
    )
    assert window.followed_rate() is followed
    assert not Window("R2", 16.0, 15.51, None, None, 0, 0.0, allocated_mean_hz=14.357).within_rate()
