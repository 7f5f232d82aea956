"""What a testbed run measured, computed from frames (no namespaces needed)."""

from __future__ import annotations

import random
from dataclasses import replace

import pytest

from dbml.experiment.analysis import (
    WINDOW_S,
    Arrival,
    Outage,
    Tick,
    _worst_windows,
    analyse,
    link_at,
    outages,
    rate_hz,
    settle_s,
)
from dbml.testbed import TestbedError
from dbml.testbed.runner import parse_schedule, parse_uplinks


def test_schedule_parses_and_names_bad_values() -> None:
    assert parse_schedule("0:11,20:5,40:11") == ((0.0, 11.0), (20.0, 5.0), (40.0, 11.0))
    assert link_at(((0.0, 11.0), (20.0, 5.0)), 25.0, 11.0) == 5.0
    # 0 Mbit is an outage: the link is down until the next entry
    assert parse_schedule("0:11,20:0,30:11") == ((0.0, 11.0), (20.0, 0.0), (30.0, 11.0))
    for bad, named in (
        ("0:11,x:5", "'x:5'"),
        ("0:11,20", "'20'"),
        ("0:0", "must be up at 0 s"),
        ("0:11,5:-1", "rate '-1' must be > 0, or 0 for link down"),
        ("0:11,5:nan", "rate 'nan'"),
        ("10:5,5:11", "times must increase"),
        ("-1:5", "time '-1'"),
    ):
        with pytest.raises(TestbedError, match=named):
            parse_schedule(bad)


def test_uplinks_parse_and_name_bad_values() -> None:
    assert parse_uplinks(["R1=4", "r2=2.5"], ["R1", "R2"]) == {"R1": 4.0, "R2": 2.5}
    for bad in ("R3=4", "R1", "R1=fast", "R1=0"):
        with pytest.raises(TestbedError, match=f"--uplink={bad!r}"):
            parse_uplinks([bad], ["R1", "R2"])


def _stream(
    robot: int, *, hz: float, start: float, end: float, delay: float, size: int, skip: int = -1
) -> list[Arrival]:
    frames = []
    seq, t = 0, start
    while t < end:
        if seq != skip:
            frames.append(Arrival(robot, seq, t, t + delay, size, hz))
        seq += 1
        t += 1 / hz
    return frames


def test_steps_measure_rate_latency_losses_and_goodput() -> None:
    t0 = 1000.0
    frames = [
        *_stream(0, hz=10, start=t0, end=t0 + 4, delay=0.05, size=100_000, skip=25),
        *_stream(1, hz=4, start=t0, end=t0 + 4, delay=0.2, size=10_000),
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


def test_a_drop_reports_when_latency_recovered() -> None:
    t0 = 0.0
    # delays grow for 2 s after a drop at 4 s, then are back to normal
    frames = []
    for seq in range(120):
        sent = seq * 0.1
        delay = 0.06 if not 4.0 <= sent < 6.0 else 0.06 + (sent - 4.0) * 0.4
        frames.append(Arrival(0, seq, sent, sent + delay, 50_000, 10.0))
    ticks = [Tick(t / 4, (10.0,), 5.0, 5.0) for t in range(48)]
    result = analyse(
        frames,
        ticks,
        robots=["R1"],
        t0=t0,
        step_s=1.2,
        steps=10,
        link_mbit=11.0,
        schedule=((0.0, 11.0), (4.0, 5.0)),
    )
    (change,) = result.changes
    assert change.to_mbit == 5.0
    assert change.max_latency_p95_ms is not None
    assert change.max_latency_p95_ms > 700
    # the last bad frame arrives at ~6.7 s; the first all-good 1-s window after it ends ~7.7 s
    assert change.recovery_s is not None
    assert 3.0 < change.recovery_s < 4.5


@pytest.mark.parametrize("offset_s", [0.0, 0.1, 0.3, 0.55])
def test_a_slow_stream_is_timed_exactly_in_a_short_step(offset_s: float) -> None:
    # 1.48 Hz (Table 2's slowest) in a 2 s step: one or two frames after the settling time,
    # timed from the frame before the window, so the 5 % check holds whatever the phase
    period = 1 / 1.48
    times = [offset_s + k * period for k in range(20)]
    start = 4.0 + settle_s(2.0)
    assert rate_hz(times, start, 6.0) == pytest.approx(1.48, rel=1e-9)


def test_a_window_without_a_gap_to_time_counts() -> None:
    assert rate_hz([0.5], 0.0, 2.0) == 0.5
    assert rate_hz([], 0.0, 2.0) == 0.0


def test_a_drop_reports_the_first_cut_goodput_after_and_phases() -> None:
    t0 = 0.0
    frames = [
        Arrival(0, seq, seq * 0.1, seq * 0.1 + 0.05, 50_000, 10.0)  # 4 Mbit/s
        for seq in range(100)
    ]
    # the budget is cut 0.6 s after the drop at 4 s as ticks see it; the estimator's own stamp
    # says 0.25 s
    ticks = [Tick(t / 5, (10.0,), 9.0, 9.0) for t in range(23)]
    ticks.append(Tick(4.6, (10.0,), 4.0, 4.0, "decrease: received 4.0 Mbit/s @4.25"))
    ticks.extend(Tick(4.6 + t / 5, (10.0,), 4.0, 4.0, "hold @4.25") for t in range(1, 28))
    result = analyse(
        frames,
        ticks,
        robots=["R1"],
        t0=t0,
        step_s=1.0,
        steps=10,
        link_mbit=11.0,
        schedule=((0.0, 11.0), (4.0, 5.0)),
    )
    (change,) = result.changes
    assert change.first_cut_s == pytest.approx(0.25)
    assert change.goodput_share_after == pytest.approx(4.0 / 5.0, rel=0.05)
    first, second = result.phases
    assert (first.start_s, first.end_s, second.end_s) == (0.0, 4.0, 10.0)
    assert second.utilisation == pytest.approx(4.0 / 5.0, rel=0.05)
    assert second.latency_p95_ms == pytest.approx(50.0)
    assert second.lost == 0


def test_a_cut_without_a_stamp_is_timed_by_the_tick_that_saw_it() -> None:
    frames = [Arrival(0, seq, seq * 0.1, seq * 0.1 + 0.05, 50_000, 10.0) for seq in range(60)]
    ticks = [Tick(t / 5, (10.0,), 9.0 if t / 5 < 4.6 else 4.0, None) for t in range(30)]
    result = analyse(
        frames,
        ticks,
        robots=["R1"],
        t0=0.0,
        step_s=0.6,
        steps=10,
        link_mbit=11.0,
        schedule=((0.0, 11.0), (4.0, 5.0)),
    )
    (change,) = result.changes
    assert change.first_cut_s == pytest.approx(0.6)


def test_a_schedule_starting_below_the_default_link_starts_there() -> None:
    """RFC 8867's 5.1 starts at 4.4 Mbit/s: the first phase is 4.4, not the default 11."""
    from dbml.experiment.analysis import _link_rates

    rates = _link_rates(((0.0, 4.4), (40.0, 11.0), (60.0, 2.6)), 11.0)
    assert rates == [(0.0, 4.4), (40.0, 11.0), (60.0, 2.6)]
    assert _link_rates(((20.0, 5.0),), 11.0) == [(0.0, 11.0), (20.0, 5.0)]


def test_an_outage_reports_the_urgent_first_frame_the_backlog_and_the_worst_window() -> None:
    before = _stream(0, hz=10, start=0.0, end=6.0, delay=0.05, size=84_000)
    # the backlog: three frames sent as the link went down, delivered after it came back
    backlog = [Arrival(0, 60 + k, 6.0 + 0.1 * k, 9.5 + 0.06 * k, 84_000, 10.0) for k in range(3)]
    fresh = [Arrival(0, 70 + k, 9.7 + 0.1 * k, 9.75 + 0.1 * k, 84_000, 10.0) for k in range(20)]
    calm = [Arrival(1, k, 9.2 + 0.5 * k, 9.25 + 0.5 * k, 21_000, 2.0) for k in range(4)]
    ticks = [
        Tick(t_s=t, allocated_hz=(10.0, 2.0), budget_mbit=8.0, estimate_mbit=None)
        for t in (5.0, 9.5, 12.0)
    ]
    (outage,) = outages(
        [*before, *backlog, *fresh, *calm],
        ticks,
        robots=["R1", "R2"],
        t0=0.0,
        schedule=((0.0, 11.0), (6.0, 0.0), (9.0, 11.0)),
        urgent_at=lambda t_s: 0 if t_s >= 9 else 1,
    )
    assert (outage.start_s, outage.end_s, outage.urgent) == (6.0, 9.0, "R1")
    assert outage.first_urgent_s == pytest.approx(0.5)  # a stale frame
    assert outage.first_fresh_urgent_s == pytest.approx(0.75)
    assert outage.stale == 3
    assert outage.lost == 7  # seq 63..69 never came
    assert outage.budget_mbit == 8.0
    # R1's 10 fresh frames a second are 6.72 Mbit/s, R2 adds two 21 KB frames: 7.06
    assert outage.worst_sent_after_mbit == pytest.approx(7.056)
    # the backlog lands in the same second: the wire carried 3 frames more than the release
    assert outage.worst_window_mbit == pytest.approx(7.728)
    assert outage.release_over_budget_mbit == pytest.approx(7.056 - 8.0)


def _steady_outage(budgets: tuple[tuple[float, float], ...]) -> Outage:
    """R1 at 10 Hz of 84 KB (6.72 Mbit/s), the link down 6-9 s; ``budgets``: (t_s, Mbit/s)."""
    before = _stream(0, hz=10, start=0.0, end=6.0, delay=0.05, size=84_000)
    after = _stream(0, hz=10, start=9.0, end=14.0, delay=0.05, size=84_000)
    after = [replace(f, seq=100 + k) for k, f in enumerate(after)]
    ticks = [
        Tick(t_s=t, allocated_hz=(10.0,), budget_mbit=b, estimate_mbit=None) for t, b in budgets
    ]
    (outage,) = outages(
        [*before, *after],
        ticks,
        robots=["R1"],
        t0=0.0,
        schedule=((0.0, 11.0), (6.0, 0.0), (9.0, 11.0)),
        urgent_at=lambda _t: 0,
    )
    return outage


def test_an_outage_s_windows_are_judged_against_the_budget_in_force_then() -> None:
    """A budget cut after the restoration: the larger budget before it hides nothing."""
    outage = _steady_outage(((5.0, 8.0), (9.5, 8.0), (11.0, 4.0)))
    assert outage.budget_mbit == 8.0  # the largest in force, as reported
    # the windows from 11 s on carried 6.72 Mbit/s (10 frames, or 11 on the rounding edge)
    # against a budget of 4; against 8 every window would look within it
    over = outage.release_over_budget_mbit
    assert over is not None
    assert 6.72 - 4.0 - 1e-6 <= over <= 11 * 84_000 * 8e-6 - 4.0 + 1e-6
    assert outage.over_budget_mbit == over


def test_a_window_across_a_raise_is_owed_the_mean_budget_over_it() -> None:
    """The estimator raises the budget 0.5 s after the restoration; a window is owed its mean."""
    outage = _steady_outage(((5.0, 4.0), (9.5, 9.4)))
    over = outage.release_over_budget_mbit
    assert over is not None
    # the first window (9.05-10.05 s) is owed 0.45 s at 4 and 0.55 s at 9.4: 6.97 Mbit/s;
    # judged against 4 alone it would read 2.72 over. One frame of rounding on its edge.
    assert over <= 6.72 - 6.97 + 84_000 * 8e-6 + 1e-6
    assert over >= 6.72 - 6.97 - 1e-6


def test_the_worst_window_is_the_brute_force_one() -> None:
    """The one-pass sliding window finds what summing every window finds."""
    rng = random.Random(7)
    times = sorted(rng.uniform(0.0, 6.0) for _ in range(400))
    sizes = [rng.randrange(1_000, 90_000) for _ in times]
    ticks = [Tick(t_s=0.0, allocated_hz=(), budget_mbit=5.0, estimate_mbit=None)]
    worst, over = _worst_windows(times, sizes, 6.0, ticks)
    brute = max(
        sum(b for t, b in zip(times, sizes, strict=True) if start <= t < start + WINDOW_S)
        for start in times
        if start <= 6.0 - WINDOW_S + 1e-9
    )
    assert worst == pytest.approx(brute * 8e-6)
    assert over == pytest.approx(brute * 8e-6 - 5.0)
