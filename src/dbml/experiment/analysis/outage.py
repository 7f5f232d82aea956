"""What the restoration after each outage did: the urgent channel first, the budget kept."""

from __future__ import annotations

import bisect
import itertools
from collections.abc import Callable, Sequence

from dbml.core.spec import bytes_per_s_to_mbit
from dbml.experiment.analysis.records import Arrival, Outage, Tick
from dbml.experiment.analysis.thresholds import OUTAGE_AFTER_S, WINDOW_S
from dbml.experiment.analysis.windows import EDGE_S, RobotFrames

__all__ = ["outages", "worst_windows"]


def _budget_at(ticks: Sequence[Tick], t_s: float) -> float | None:
    """The budget in force at ``t_s``: the last one seen at or before it, else the first after.

    ``ticks`` are sorted by time and all carry a budget.
    """
    k = bisect.bisect_right([t.t_s for t in ticks], t_s)
    if k > 0:
        return ticks[k - 1].budget_mbit
    return ticks[0].budget_mbit if ticks else None


def _budget_over(ticks: Sequence[Tick], start: float, end: float) -> float | None:
    """The mean budget in force over ``[start, end)``, weighted by time.

    Rates follow the budget as it moves (a rate earns credit over time), so a window is owed
    the budget's integral: judged against its start alone, a window while the estimator raises
    the budget would count the raise as excess, and one while it cuts would hide the cut.
    ``ticks`` are sorted by time and all carry a budget.
    """
    budget = _budget_at(ticks, start)
    if budget is None:
        return None
    weighted, at = 0.0, start
    for tick in ticks:
        if at < tick.t_s < end:
            weighted += budget * (tick.t_s - at)
            budget, at = tick.budget_mbit, tick.t_s
            assert budget is not None  # the caller keeps only ticks with a budget
    weighted += budget * (end - at)
    return weighted / (end - start)


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
