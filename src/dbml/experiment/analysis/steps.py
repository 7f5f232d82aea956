"""A run step by step and as a rolling time series, with what followed each link change."""

from __future__ import annotations

import bisect
import itertools
from collections.abc import Sequence
from dataclasses import replace

from dbml.experiment.analysis.link import link_changes, link_phases
from dbml.experiment.analysis.records import Analysis, Arrival, SeriesPoint, StepResult, Tick
from dbml.experiment.analysis.thresholds import WINDOW_S, WINDOW_STEP_S
from dbml.experiment.analysis.windows import EDGE_S, RobotFrames, link_at, link_mean, settle_s

__all__ = ["analyse"]


def analyse(
    frames: Sequence[Arrival],
    ticks: Sequence[Tick],
    *,
    robots: Sequence[str],
    t0: float,
    step_s: float,
    steps: int,
    link_mbit: float,
    schedule: Sequence[tuple[float, float]] = (),
    link_events: bool = True,
) -> Analysis:
    """Steps, time series and the recovery after every link change.

    ``link_events=False``: no change or phase of the schedule is judged on its own (a recorded
    trace changes every 200 ms); a step carries the rate's mean over it, the series the rate in
    force.
    """
    streams = [RobotFrames(name, i, frames) for i, name in enumerate(robots)]
    ordered = sorted(ticks, key=lambda t: t.t_s)
    tick_times = [t.t_s for t in ordered]

    def seen(at: float) -> Tick | None:
        index = bisect.bisect_right(tick_times, at)
        return ordered[index - 1] if index else None

    def allocated(stream: RobotFrames, at: float) -> float | None:
        tick = seen(at)
        value = tick.allocated_hz[stream.index] if tick is not None else None
        return stream.applied_hz(at) if value is None else value  # unmanaged: what it applied

    def allocated_mean(stream: RobotFrames, start: float, end: float) -> float | None:
        """The allocations in force over ``[start, end)``, weighted by how long each was."""
        inside = tick_times[
            bisect.bisect_right(tick_times, start) : bisect.bisect_left(tick_times, end)
        ]
        cuts = [start, *inside, end]
        total = 0.0
        for a, b in itertools.pairwise(cuts):
            value = allocated(stream, a)
            if value is None:
                return None
            total += value * (b - a)
        return total / (end - start)

    step_rows = []
    for k in range(steps):
        start, end = t0 + k * step_s, t0 + (k + 1) * step_s
        tick = seen(end)
        rows = []
        for stream in streams:
            measured = start + settle_s(step_s)
            window = replace(
                stream.window(measured, end, allocated(stream, end), lost_from=start),
                allocated_mean_hz=allocated_mean(stream, measured, end),
            )
            variant = tick.variants[stream.index] if tick is not None and tick.variants else None
            encoding = None
            if tick is not None and stream.index < len(tick.encodings):
                encoding = tick.encodings[stream.index]
            rows.append(replace(window, variant=variant, encoding=encoding))
        step_rows.append(
            StepResult(
                step=k + 1,
                robots=tuple(rows),
                budget_mbit=None if tick is None else tick.budget_mbit,
                estimate_mbit=None if tick is None else tick.estimate_mbit,
                link_mbit=link_at(schedule, end - t0 - EDGE_S, link_mbit)
                if link_events
                else link_mean(schedule, start - t0, end - t0, link_mbit),
            )
        )

    series = []
    t = t0 + WINDOW_S
    while t <= t0 + steps * step_s + EDGE_S:
        tick = seen(t)
        state = None if tick is None else tick.estimator
        series.append(
            SeriesPoint(
                t_s=t - t0,
                robots=tuple(
                    s.window(t - WINDOW_S, t, allocated(s, t), lost_from=t - WINDOW_S)
                    for s in streams
                ),
                budget_mbit=None if tick is None else tick.budget_mbit,
                estimator=None if state is None else state.text,
                link_mbit=link_at(schedule, t - t0, link_mbit),
            )
        )
        t += WINDOW_STEP_S
    if not link_events:
        return Analysis(tuple(step_rows), tuple(series), (), ())
    changes = link_changes(
        series, ordered, streams, schedule, t0=t0, end_s=steps * step_s, link_mbit=link_mbit
    )
    phases = link_phases(streams, schedule, t0=t0, end_s=steps * step_s, link_mbit=link_mbit)
    return Analysis(tuple(step_rows), tuple(series), changes, phases)
