"""The restoration after an outage: the urgent channel first, every window within its budget."""

from __future__ import annotations

import random
from dataclasses import replace

import pytest

from dbml.experiment.analysis import (
    WINDOW_S,
    WINDOW_STEP_S,
    Arrival,
    Outage,
    Recovery,
    Tick,
    outages,
    recoveries,
)
from dbml.experiment.analysis.outage import LINK_SCOPE, down_intervals, worst_windows
from tests.experiment.analysis.frames import stream


def test_an_outage_reports_the_urgent_first_frame_the_backlog_and_the_worst_window() -> None:
    before = stream(0, hz=10, start=0.0, end=6.0, delay=0.05, size=84_000)
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
    before = stream(0, hz=10, start=0.0, end=6.0, delay=0.05, size=84_000)
    after = stream(0, hz=10, start=9.0, end=14.0, delay=0.05, size=84_000)
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
    worst, over = worst_windows(times, sizes, 6.0, ticks)
    brute = max(
        sum(b for t, b in zip(times, sizes, strict=True) if start <= t < start + WINDOW_S)
        for start in times
        if start <= 6.0 - WINDOW_S + 1e-9
    )
    assert worst == pytest.approx(brute * 8e-6)
    assert over == pytest.approx(brute * 8e-6 - 5.0)


def _recoveries(
    r1_back_s: float | None, r2_back_s: float | None, *, own: bool = False
) -> tuple[Recovery, ...]:
    """R1 (10 Hz) and R2 (4 Hz) over 20 s, the link (or R1's own radio) down 6-9 s.

    Each robot resumes its allocation at its ``*_back_s`` (None: at 1 Hz, its fail-safe, to
    the end); with ``own``, R2 never stops.
    """
    frames = [
        *stream(0, hz=10, start=0.0, end=6.0, delay=0.05, size=84_000),
        *stream(1, hz=4, start=0.0, end=9.0 if own else 6.0, delay=0.05, size=21_000),
    ]
    backs = (r1_back_s, 9.0 if own else r2_back_s)
    for robot, hz, back in ((0, 10, backs[0]), (1, 4, backs[1])):
        frames += stream(
            robot,
            hz=hz if back is not None else 1,
            start=back if back is not None else 9.5,
            end=20.0,
            delay=0.05,
            size=84_000 if robot == 0 else 21_000,
        )
    ticks = [Tick(t_s=0.5, allocated_hz=(10.0, 4.0), budget_mbit=8.0, estimate_mbit=None)]
    schedule = ((0.0, 11.0), (6.0, 0.0), (9.0, 11.0))
    return recoveries(
        frames,
        ticks,
        robots=["R1", "R2"],
        t0=0.0,
        end_s=20.0,
        schedule=() if own else schedule,
        robot_schedules={"R1": schedule} if own else {},
    )


def test_every_robot_behind_the_link_is_timed_from_the_return_to_its_allocation() -> None:
    r1, r2 = _recoveries(10.0, 11.5)
    assert (r1.robot, r1.scope, r1.down_s, r1.back_s) == ("R1", LINK_SCOPE, 6.0, 9.0)
    assert r1.recovery_s == pytest.approx(1.0, abs=WINDOW_STEP_S)
    assert r2.recovery_s == pytest.approx(2.5, abs=WINDOW_STEP_S)
    assert not r1.stuck
    assert not r2.stuck


def test_a_robot_left_at_its_fail_safe_is_stuck_and_never_recovered() -> None:
    r1, r2 = _recoveries(None, 9.0)
    assert r1.recovery_s is None
    assert r1.stuck
    assert not r2.stuck


def test_a_robots_own_outage_times_that_robot_alone() -> None:
    (r1,) = _recoveries(9.5, None, own=True)
    assert (r1.robot, r1.scope) == ("R1", "R1")
    assert r1.recovery_s == pytest.approx(0.5, abs=WINDOW_STEP_S)


def test_down_intervals_leave_out_an_outage_that_never_ends() -> None:
    assert down_intervals(((0.0, 11.0), (5.0, 0.0), (8.0, 4.0), (12.0, 0.0))) == [(5.0, 8.0)]


def _r1_after_6_to_9(frames: list[Arrival], ticks: list[Tick]) -> Recovery:
    """R1's recovery over a 20-s run whose link is down from 6 to 9 s."""
    (r1,) = recoveries(
        frames,
        ticks,
        robots=["R1"],
        t0=0.0,
        end_s=20.0,
        schedule=((0.0, 11.0), (6.0, 0.0), (9.0, 11.0)),
        robot_schedules={},
    )
    return r1


def test_a_fail_safe_minimum_near_a_low_allocation_is_not_a_recovery() -> None:
    """At 1 Hz against 1.48 Hz a 1-s window holds one frame either way: its rate says which."""
    frames = [
        *stream(0, hz=1.48, start=0.0, end=6.0, delay=0.05, size=21_000),
        *stream(0, hz=1.0, start=9.2, end=20.0, delay=0.05, size=21_000),
    ]
    ticks = [Tick(t_s=0.5, allocated_hz=(1.48,), budget_mbit=8.0, estimate_mbit=None)]
    r1 = _r1_after_6_to_9(frames, ticks)
    assert r1.recovery_s is None
    assert r1.stuck


def test_a_later_outage_neither_makes_an_earlier_one_stuck_nor_is_judged_too_late() -> None:
    """R1 back at 9 s, down again from 16 s: the first outage is judged up to the second.

    The second comes back in the run's last seconds: too late to judge, it is left out.
    """
    frames = [
        *stream(0, hz=10, start=0.0, end=6.0, delay=0.05, size=84_000),
        *stream(0, hz=10, start=9.0, end=16.0, delay=0.05, size=84_000),
    ]
    ticks = [Tick(t_s=0.5, allocated_hz=(10.0,), budget_mbit=8.0, estimate_mbit=None)]
    own = ((0.0, 11.0), (6.0, 0.0), (9.0, 11.0), (16.0, 0.0), (19.5, 11.0))
    (r1,) = recoveries(
        frames, ticks, robots=["R1"], t0=0.0, end_s=20.0, schedule=(), robot_schedules={"R1": own}
    )
    assert (r1.down_s, r1.back_s) == (6.0, 9.0)
    assert r1.recovery_s == pytest.approx(0.0, abs=WINDOW_STEP_S)
    assert not r1.stuck
    assert r1.back_within(3.0)


def _following(
    changes: list[tuple[float, float]],
    *,
    start_s: float,
    fail_safe_until_s: float = 0.0,
    silent: tuple[float, float] = (0.0, 0.0),
) -> Recovery:
    """R1 under an allocation that takes each ``(time, Hz)`` of ``changes``; the link down 6-9 s.

    From ``start_s`` it sends at its 1-Hz fail-safe until ``fail_safe_until_s``, then follows
    each change 50 ms later; nothing it sends within ``silent`` crosses the dead link.
    """

    def allocated(t_s: float) -> float:
        return next(hz for at, hz in reversed(changes) if at <= t_s)

    frames, seq, t = [], 0, start_s
    while t < 20.0:
        hz = 1.0 if t < fail_safe_until_s else allocated(t - 0.05)
        if not silent[0] <= t < silent[1]:
            frames.append(Arrival(0, seq, t, t + 0.05, 84_000, hz))
            seq += 1
        t += 1 / hz
    ticks = [
        Tick(t_s=at, allocated_hz=(hz,), budget_mbit=8.0, estimate_mbit=None) for at, hz in changes
    ]
    return _r1_after_6_to_9(frames, ticks)


def test_a_robot_following_a_moving_allocation_is_back_and_not_stuck() -> None:
    """An allocation that moves within a window is followed, not met at once.

    It moves just after the return (a step) and every 0.2 s up to the end (the estimator
    raising the budget by 6 % a tick); the robot follows each change 50 ms later. Judged
    against the allocation at each window's end, the window across the step would not count,
    and the last 2 s, never at an allocation that has already moved on, would be stuck.
    """
    changes = [(0.5, 14.0), (10.0, 11.0), *((14.0 + 0.2 * i, 5.0 * 1.06**i) for i in range(30))]
    r1 = _following(changes, start_s=0.55, silent=(6.0, 9.2))
    assert r1.recovery_s is not None
    assert r1.recovery_s <= 0.5  # the first window from its return at 9.2 s
    assert not r1.stuck


def test_a_fail_safe_minimum_under_a_rising_allocation_is_not_a_recovery() -> None:
    """A robot at its fail-safe minimum while the allocation rises is not back.

    From the return the allocation rises from 1.5 Hz by 6 % every 0.2 s; the robot stays at
    its fail-safe 1 Hz for 3.5 s, then follows. A window's count may be within one frame of
    its mean: the applied rate, against the allocation when each frame was sent, says no.
    """
    changes = [(0.5, 4.0), *((9.0 + 0.2 * i, 1.5 * 1.06**i) for i in range(45))]
    r1 = _following(changes, start_s=9.0, fail_safe_until_s=12.5)
    assert r1.recovery_s is not None
    assert r1.recovery_s >= 3.0  # not before it followed, 3.5 s after the return
    assert not r1.back_within(3.0)
    assert not r1.stuck
