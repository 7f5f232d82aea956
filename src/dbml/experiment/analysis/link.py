"""How a run followed each change of the link's rate: per-phase figures, cut and recovery."""

from __future__ import annotations

from collections.abc import Sequence

from dbml.core.spec import bytes_per_s_to_mbit
from dbml.experiment.analysis.records import LinkChange, LinkPhase, SeriesPoint, Tick
from dbml.experiment.analysis.thresholds import (
    BUDGET_BACK_FRACTION,
    GOODPUT_AFTER_S,
    RECOVERED_P95_MS,
    WINDOW_S,
)
from dbml.experiment.analysis.windows import EDGE_S, RobotFrames, link_rates, percentile_ms

__all__ = ["cut_time", "link_changes", "link_phases"]

_CUT_TOLERANCE = 1e-3
"""A budget below the one before a drop by more than this fraction is a cut (not rounding)."""


def link_phases(
    streams: Sequence[RobotFrames],
    schedule: Sequence[tuple[float, float]],
    *,
    t0: float,
    end_s: float,
    link_mbit: float,
) -> tuple[LinkPhase, ...]:
    """Goodput, p95 latency and losses of every phase of the link schedule."""
    rates = link_rates(schedule, link_mbit)
    phases = []
    for k, (at, mbit) in enumerate(rates):
        until = min(rates[k + 1][0], end_s) if k + 1 < len(rates) else end_s
        if until <= at:
            break
        start, end = t0 + at, t0 + until
        inside = [f for s in streams for f in s.frames if start <= f.arrival_s < end]
        latencies = [f.arrival_s - f.sent_s for f in inside if f.sent_s is not None]
        phases.append(
            LinkPhase(
                at,
                until,
                mbit,
                bytes_per_s_to_mbit(sum(f.size_bytes for f in inside) / (until - at)),
                percentile_ms(latencies, 95),
                sum(n for s in streams for t, n in s.gaps if start <= t < end),
            )
        )
    return tuple(phases)


def cut_time(tick: Tick) -> float:
    """When the estimate a tick saw was decided: the estimator's decision time, else the tick."""
    state = tick.estimator
    if state is None or state.decided_at_s is None:
        return tick.t_s
    return state.decided_at_s


def _goodput_share(series: Sequence[SeriesPoint], start_s: float, end_s: float) -> float | None:
    """Mean goodput of the windows inside ``[start_s, end_s]`` over the link rate."""
    inside = [
        p
        for p in series
        if p.t_s - WINDOW_S >= start_s - EDGE_S and p.t_s <= end_s and p.link_mbit > 0
    ]
    if not inside:
        return None
    return sum(p.goodput_mbit / p.link_mbit for p in inside) / len(inside)


def link_changes(
    series: Sequence[SeriesPoint],
    ticks: Sequence[Tick],
    streams: Sequence[RobotFrames],
    schedule: Sequence[tuple[float, float]],
    *,
    t0: float,
    end_s: float,
    link_mbit: float,
) -> tuple[LinkChange, ...]:
    """How the run followed each change of the link rate.

    After a drop: when latency and losses recovered; after a rise: when the budget grew back.
    """
    changes = []
    rates = link_rates(schedule, link_mbit)
    for k in range(1, len(rates)):
        at, mbit = rates[k]
        before = rates[k - 1][1]
        until = rates[k + 1][0] if k + 1 < len(rates) else end_s
        if at >= end_s:
            break
        share = _goodput_share(series, at + GOODPUT_AFTER_S, until)
        if mbit >= before:
            reached = next(
                (
                    t.t_s - t0 - at
                    for t in ticks
                    if at <= t.t_s - t0 <= until
                    and t.budget_mbit is not None
                    and t.budget_mbit >= BUDGET_BACK_FRACTION * mbit
                ),
                None,
            )
            changes.append(
                LinkChange(at, before, mbit, budget_recovery_s=reached, goodput_share_after=share)
            )
            continue
        prior = [t.budget_mbit for t in ticks if t.t_s - t0 <= at and t.budget_mbit is not None]
        cut = next(
            (
                max(cut_time(t), t0 + at) - t0 - at
                for t in ticks
                if at < t.t_s - t0 <= until
                and prior
                and t.budget_mbit is not None
                and t.budget_mbit < prior[-1] * (1 - _CUT_TOLERANCE)
            ),
            None,
        )
        # windows that start after the change: from which one on are all of them good?
        after = [p for p in series if p.t_s - WINDOW_S >= at and p.t_s <= until]
        recovered: float | None = None
        for point in reversed(after):
            good = all(
                (r.latency_p95_ms is None or r.latency_p95_ms < RECOVERED_P95_MS) and r.lost == 0
                for r in point.robots
            )
            if not good:
                break
            recovered = point.t_s - at
        p95 = [r.latency_p95_ms for p in after for r in p.robots if r.latency_p95_ms is not None]
        lost = sum(n for s in streams for t, n in s.gaps if t0 + at < t <= t0 + until)
        changes.append(
            LinkChange(
                at,
                before,
                mbit,
                recovery_s=recovered,
                max_latency_p95_ms=max(p95, default=None),
                lost_after=lost,
                first_cut_s=cut,
                goodput_share_after=share,
            )
        )
    return tuple(changes)
