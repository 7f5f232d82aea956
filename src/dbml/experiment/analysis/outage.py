"""What the restoration after each outage did.

The urgent channel first, the budget kept, and every robot behind the link back at its
allocation.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Callable, Mapping, Sequence

from dbml.core.spec import bytes_per_s_to_mbit
from dbml.experiment.analysis.records import Arrival, Outage, Recovery, Tick
from dbml.experiment.analysis.thresholds import (
    APPLIED_LAG_S,
    OUTAGE_AFTER_S,
    OUTAGE_RECOVERY_S,
    RATE_TOLERANCE,
    RECOVERED_FLOOR_HZ,
    STUCK_WINDOW_S,
    WINDOW_S,
    WINDOW_STEP_S,
)
from dbml.experiment.analysis.windows import EDGE_S, RobotFrames

__all__ = ["LINK_SCOPE", "down_intervals", "outages", "recoveries", "worst_windows"]

LINK_SCOPE = "link"
"""The scope of an outage of the shared link: every robot is behind it."""


def _held(
    points: Sequence[tuple[float, float]], start: float, end: float
) -> tuple[float, list[float]] | None:
    """Over ``[start, end)``: a value's mean weighted by time, and every value in force.

    ``points`` are (time, value) sorted by time, each value held until the next point; before
    the first point, the first holds. None: no points. Rates follow a budget or an allocation
    as it moves (a rate earns credit over time), so a window is owed the integral: judged
    against its start alone, a window while the estimator raises the budget would count the
    raise as excess, and one while it cuts would hide the cut.
    """
    if not points:
        return None
    k = bisect.bisect_right([t for t, _ in points], start)
    value = points[k - 1][1] if k > 0 else points[0][1]
    in_force, weighted, at = [value], 0.0, start
    for t, after in points[k:]:
        if t >= end:
            break
        weighted += value * (t - at)
        value, at = after, t
        in_force.append(value)
    weighted += value * (end - at)
    return weighted / (end - start), in_force


def _budget_over(ticks: Sequence[Tick], start: float, end: float) -> float | None:
    """The mean budget in force over ``[start, end)`` (``ticks`` sorted by time)."""
    held = _held([(t.t_s, t.budget_mbit) for t in ticks if t.budget_mbit is not None], start, end)
    return None if held is None else held[0]


def worst_windows(
    times: Sequence[float], sizes: Sequence[int], end: float, ticks: Sequence[Tick]
) -> tuple[float | None, float | None]:
    """The worst ``WINDOW_S`` windows: most carried (Mbit/s), most over its budget.

    Windows start at a frame before ``end - WINDOW_S``; each is judged against the mean budget
    in force over it. One pass: prefix sums of the sizes, each window's end found by an index
    that only moves forward.
    """
    worst: float | None = None
    over: float | None = None
    prefix = [0, *itertools.accumulate(sizes)]
    stop = 0
    for k, start in enumerate(times):
        if start > end - WINDOW_S + EDGE_S:
            break
        stop = max(stop, k)
        while stop < len(times) and times[stop] < start + WINDOW_S:
            stop += 1
        carried = bytes_per_s_to_mbit((prefix[stop] - prefix[k]) / WINDOW_S)
        worst = carried if worst is None else max(worst, carried)
        budget = _budget_over(ticks, start, start + WINDOW_S)
        if budget is not None:
            over = carried - budget if over is None else max(over, carried - budget)
    return worst, over


def outages(
    frames: Sequence[Arrival],
    ticks: Sequence[Tick],
    *,
    robots: Sequence[str],
    t0: float,
    schedule: Sequence[tuple[float, float]],
    urgent_at: Callable[[float], int],
) -> tuple[Outage, ...]:
    """Every outage of ``schedule`` (a rate of 0) and what the restoration after it did.

    ``urgent_at(t_s)`` is the robot whose channel has the highest priority ``t_s`` after the
    start: the one that should be heard first when the link is back.
    """
    streams = [RobotFrames(name, i, frames) for i, name in enumerate(robots)]
    found = []
    for k, (at, mbit) in enumerate(schedule):
        if mbit != 0 or k + 1 >= len(schedule):
            continue
        back = schedule[k + 1][0]
        start, restored, until = t0 + at, t0 + back, t0 + back + OUTAGE_AFTER_S
        urgent = streams[urgent_at(back)]
        after = [f for f in urgent.frames if f.arrival_s >= restored]
        fresh = [f for f in after if f.sent_s is not None and f.sent_s >= restored]
        inside = sorted(
            (f.arrival_s, f.size_bytes, f.sent_s is not None and f.sent_s >= restored)
            for s in streams
            for f in s.frames
            if restored <= f.arrival_s < until
        )
        fresh_inside = [(t, b) for t, b, after_it in inside if after_it]
        budgets = [
            t.budget_mbit for t in ticks if restored <= t.t_s <= until and t.budget_mbit is not None
        ]
        known = sorted(
            (t for t in ticks if t.budget_mbit is not None and t.t_s <= until),
            key=lambda t: t.t_s,
        )
        wire, wire_over = worst_windows(
            [t for t, _, _ in inside], [b for _, b, _ in inside], until, known
        )
        sent, sent_over = worst_windows(
            [t for t, _ in fresh_inside], [b for _, b in fresh_inside], until, known
        )
        found.append(
            Outage(
                start_s=at,
                end_s=back,
                urgent=urgent.name,
                first_urgent_s=after[0].arrival_s - restored if after else None,
                first_fresh_urgent_s=fresh[0].arrival_s - restored if fresh else None,
                stale=sum(
                    1
                    for s in streams
                    for f in s.frames
                    if f.arrival_s >= restored and f.sent_s is not None and f.sent_s < restored
                ),
                lost=sum(n for s in streams for t, n in s.gaps if start < t <= until),
                worst_window_mbit=wire,
                worst_sent_after_mbit=sent,
                budget_mbit=max(budgets, default=None),
                over_budget_mbit=wire_over,
                release_over_budget_mbit=sent_over,
            )
        )
    return tuple(found)


def down_intervals(schedule: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """``schedule``'s outages as (down, back) seconds; one still down at the end is left out."""
    return [
        (at, schedule[k + 1][0])
        for k, (at, mbit) in enumerate(schedule)
        if mbit == 0 and k + 1 < len(schedule)
    ]


def recoveries(
    frames: Sequence[Arrival],
    ticks: Sequence[Tick],
    *,
    robots: Sequence[str],
    t0: float,
    end_s: float,
    schedule: Sequence[tuple[float, float]],
    robot_schedules: Mapping[str, Sequence[tuple[float, float]]],
) -> tuple[Recovery, ...]:
    """Per outage and robot behind it: when it delivered its allocation again, or stuck.

    ``schedule`` is the shared link's (every robot is behind it), ``robot_schedules`` each
    robot's own radio; times are seconds after ``t0``, the run ends at ``end_s``. A 1-s window
    delivers the allocation when its frames sent after the return are within
    ``RATE_TOLERANCE`` or ``RECOVERED_FLOOR_HZ`` of the allocation's mean over it (counted: the
    silence before does not weigh on it; the mean: an allocation that moves within the window,
    at a step or as the estimator moves the budget, is followed, not met at once) and its last
    frame says the publisher runs at an allocation in force within ``APPLIED_LAG_S`` of its
    sending (a fail-safe minimum near a low allocation is not one). Windows start every
    ``WINDOW_STEP_S`` from the return; the first that delivers counts. ``stuck``: none
    delivers in the ``STUCK_WINDOW_S`` before the robot's next outage or the run's end. An
    outage back too late to judge is left out.
    """
    streams = [RobotFrames(name, i, frames) for i, name in enumerate(robots)]
    ordered = sorted(ticks, key=lambda t: t.t_s)
    allocations = [
        [(t.t_s, t.allocated_hz[k] or 0.0) for t in ordered] for k in range(len(robots))
    ]  # no allocation: 0 Hz, which no window delivers

    def delivers(k: int, start: float, back: float) -> bool:
        held = _held(allocations[k], t0 + start, t0 + start + WINDOW_S)
        if held is None or min(held[1]) <= 0:  # not allocated for part of it
            return False
        hz = held[0]
        stream = streams[k]
        inside = stream.frames[
            bisect.bisect_left(stream.times, t0 + start) : bisect.bisect_left(
                stream.times, t0 + start + WINDOW_S
            )
        ]
        fresh = [f for f in inside if f.sent_s is None or f.sent_s >= t0 + back]
        tolerance = max(RATE_TOLERANCE * hz, RECOVERED_FLOOR_HZ)
        if not fresh or abs(len(fresh) / WINDOW_S - hz) > tolerance:
            return False
        last = fresh[-1]
        if last.rate_hz is None:
            return True
        sent = last.arrival_s if last.sent_s is None else last.sent_s
        near = _held(allocations[k], sent - APPLIED_LAG_S, sent + APPLIED_LAG_S)
        assert near is not None  # the window's own allocations are there
        return any(abs(last.rate_hz - h) <= RATE_TOLERANCE * h for h in near[1])

    def starts(first: float, last: float) -> list[float]:
        n = max(0, math.floor((last - first) / WINDOW_STEP_S + EDGE_S) + 1)
        return [first + i * WINDOW_STEP_S for i in range(n)]

    outages_of = {
        robot: sorted(down_intervals(schedule) + down_intervals(robot_schedules.get(robot, ())))
        for robot in robots
    }
    scoped = [(LINK_SCOPE, list(robots), schedule)]
    scoped += [(robot, [robot], own) for robot, own in sorted(robot_schedules.items())]
    found = []
    for scope, behind, own in scoped:
        for down, back in down_intervals(own):
            if back > end_s - WINDOW_S - OUTAGE_RECOVERY_S:
                continue  # too late in the run to see it come back
            for robot in behind:
                k = robots.index(robot)
                until = min(
                    (d for d, _ in outages_of[robot] if d > down), default=end_s
                )  # its next outage, or the end
                last_start = until - WINDOW_S
                at = next((t for t in starts(back, last_start) if delivers(k, t, back)), None)
                tail = starts(max(back, last_start - STUCK_WINDOW_S), last_start)
                stuck = not any(delivers(k, t, back) for t in tail)
                recovery = None if at is None else at - back
                found.append(Recovery(robot, scope, down, back, recovery, stuck))
    return tuple(found)
