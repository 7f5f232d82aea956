"""What an experiment measured: per step and robot, over time, and after each link change.

Pure: it takes the frames the operator received and the parameters it saw (``Arrival`` and
``Tick``), and computes per window the allocated and delivered rate, one-way latency
percentiles, losses (sequence gaps) and goodput; per step (after ``settle_s``), as a rolling
time series, and the recovery after each change of the link's rate. The thresholds that judge
a run are named here, once.
"""

from __future__ import annotations

import bisect
import itertools
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from dbml.core.spec import bytes_per_s_to_mbit

__all__ = [
    "BUDGET_BACK_FRACTION",
    "BUDGET_BACK_S",
    "CUT_STAMP",
    "FIRST_CUT_S",
    "GOODPUT_AFTER_FRACTION",
    "GOODPUT_AFTER_S",
    "GOODPUT_FRACTION",
    "LIVE_FRAMES",
    "LIVE_WINDOW_S",
    "MAX_P95_MS",
    "OUTAGE_AFTER_S",
    "PEAK_P95_AFTER_DROP_MS",
    "RATE_TOLERANCE",
    "RATE_TOLERANCE_HZ",
    "RECOVERED_P95_MS",
    "RECOVERY_S",
    "WINDOW_S",
    "WINDOW_STEP_S",
    "Analysis",
    "Arrival",
    "LinkChange",
    "LinkPhase",
    "Outage",
    "SeriesPoint",
    "StepResult",
    "StreamLatency",
    "Tick",
    "Window",
    "analyse",
    "latest",
    "link_at",
    "outages",
    "rate_hz",
    "settle_s",
    "stream_latency",
]

RATE_TOLERANCE = 0.05
"""A delivered rate within 5 % of the allocation is the allocation (the paper's claim)."""
RATE_TOLERANCE_HZ = 0.3
"""The demo's floor on the tolerance: a few-Hz stream in a short step has few frames to time."""
MAX_P95_MS = 200.0
"""A steady link keeps every robot's one-way p95 latency under this (teleoperation's limit)."""
RECOVERED_P95_MS = 250.0
"""After a drop, a window whose p95 is under this (and loses nothing) counts as recovered."""
RECOVERY_S = 3.0
"""After a drop, latency and losses are back within this (the estimator's promise)."""
GOODPUT_FRACTION = 0.9
"""On a steady link with no capped uplink, dbml's goodput is at least this share of the link."""
BUDGET_BACK_FRACTION = 0.9
"""After a rise, the budget counts as back once it reaches this share of the new link."""
BUDGET_BACK_S = 10.0
"""After a rise, the estimated budget is back within this."""
FIRST_CUT_S = 0.3
"""After a drop, the estimator cuts the budget within this (GCC: about a round trip + 100 ms)."""
PEAK_P95_AFTER_DROP_MS = 250.0
"""After a drop, no window's p95 latency reaches this."""
GOODPUT_AFTER_FRACTION = 0.85
"""From ``GOODPUT_AFTER_S`` after a drop, goodput is at least this share of the new rate."""
GOODPUT_AFTER_S = 3.0
"""After a change, goodput is judged from this long on: the estimator has settled by then."""
CUT_STAMP = re.compile(r"@(\d+(?:\.\d+)?)$")
"""The estimator's state ends with ``@<wall-clock s>`` of its decision: the time of a cut to
the millisecond, where the operator's ticks see it only to ``TICK_S``."""
WINDOW_S = 1.0
"""Rolling windows of the time series and the recovery measurement."""
WINDOW_STEP_S = 0.25
"""One point of the time series every this many seconds."""
LIVE_WINDOW_S = 2.0
"""A live view's readings cover this long: smoother than one second, still current."""
LIVE_FRAMES = 400
"""A live view reads at most this many of the newest frames (all of ``LIVE_WINDOW_S``)."""
OUTAGE_AFTER_S = 5.0
"""After an outage, every 1-s window of this long is held against the budget."""
_MS_PER_S = 1000.0
_EDGE_S = 1e-9
_CUT_TOLERANCE = 1e-3
"""A budget below the one before a drop by more than this fraction is a cut (not rounding)."""


@dataclass(frozen=True, slots=True)
class Arrival:
    """One frame as the operator received it (wall-clock times; the hosts share a clock)."""

    robot: int
    seq: int | None
    """The publisher's sequence number (None: no metadata, as over ROS 1)."""
    sent_s: float | None
    arrival_s: float
    size_bytes: int
    rate_hz: float | None
    """The rate the publisher applied when it sent this frame."""


@dataclass(frozen=True, slots=True)
class Tick:
    """The parameters the operator saw at ``t_s`` (wall clock)."""

    t_s: float
    allocated_hz: tuple[float | None, ...]
    budget_mbit: float | None
    estimate_mbit: float | None
    estimator: str | None = None
    """The estimator's state (phase, receive rate, queueing, losses), when one runs."""
    variants: tuple[str, ...] = ()
    """The copy each robot's subscriber takes (``full`` or ``optimized``)."""


@dataclass(frozen=True, slots=True)
class Window:
    """One robot over one window: the measured part of a step, or one point of the series."""

    robot: str
    allocated_hz: float | None
    delivered_hz: float
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    lost: int
    goodput_mbit: float
    variant: str | None = None

    def within_rate(self, *, floor_hz: float = 0.0) -> bool:
        """Delivered within ``RATE_TOLERANCE`` of the allocation (or ``floor_hz``)."""
        if not self.allocated_hz:
            return False
        tolerance = max(RATE_TOLERANCE * self.allocated_hz, floor_hz)
        return abs(self.delivered_hz - self.allocated_hz) <= tolerance


@dataclass(frozen=True, slots=True)
class StepResult:
    """One step: every robot's window and the budget and link at its end."""

    step: int
    robots: tuple[Window, ...]
    budget_mbit: float | None
    estimate_mbit: float | None
    link_mbit: float

    @property
    def goodput_mbit(self) -> float:
        """What all robots delivered."""
        return sum(r.goodput_mbit for r in self.robots)


@dataclass(frozen=True, slots=True)
class SeriesPoint:
    """The ``WINDOW_S`` ending ``t_s`` seconds after step 1 started."""

    t_s: float
    robots: tuple[Window, ...]
    budget_mbit: float | None
    estimator: str | None
    link_mbit: float

    @property
    def goodput_mbit(self) -> float:
        """What all robots delivered."""
        return sum(r.goodput_mbit for r in self.robots)


@dataclass(frozen=True, slots=True)
class LinkChange:
    """A change of the link's rate and how the system followed it."""

    t_s: float
    from_mbit: float
    to_mbit: float
    recovery_s: float | None = None
    """A drop: from when on every window had p95 < ``RECOVERED_P95_MS`` and no loss."""
    max_latency_p95_ms: float | None = None
    lost_after: int = 0
    budget_recovery_s: float | None = None
    """A rise: when the budget reached ``BUDGET_BACK_FRACTION`` of the new rate."""
    first_cut_s: float | None = None
    """A drop: when the budget first fell below the one in force before it (the estimator's
    decision time when its state carries one, else the operator's first tick that saw it)."""
    goodput_share_after: float | None = None
    """Goodput from ``GOODPUT_AFTER_S`` after the change to the next, as a share of the new
    rate (an over-cut shows here)."""

    @property
    def drop(self) -> bool:
        """Whether the link got slower."""
        return self.to_mbit < self.from_mbit


@dataclass(frozen=True, slots=True)
class LinkPhase:
    """Between two changes of the link rate, all robots together: RFC 8867's per-phase figures."""

    start_s: float
    end_s: float
    link_mbit: float
    goodput_mbit: float
    latency_p95_ms: float | None
    lost: int

    @property
    def utilisation(self) -> float:
        """Goodput as a share of the shaped rate (0 while the link is down)."""
        return self.goodput_mbit / self.link_mbit if self.link_mbit > 0 else 0.0


@dataclass(frozen=True, slots=True)
class Analysis:
    """Everything measured in one run."""

    steps: tuple[StepResult, ...] = ()
    series: tuple[SeriesPoint, ...] = ()
    changes: tuple[LinkChange, ...] = ()
    phases: tuple[LinkPhase, ...] = ()


def settle_s(step_s: float) -> float:
    """Time after a step starts before it is measured: the new rates take effect.

    One old period at worst, 1 s at the 1 Hz minimum.
    """
    return min(1.0, step_s / 3)


def link_at(schedule: Sequence[tuple[float, float]], t_s: float, default: float) -> float:
    """The shaped rate in force ``t_s`` seconds after the start."""
    rate = default
    for at, mbit in schedule:
        if at <= t_s:
            rate = mbit
    return rate


def rate_hz(times: Sequence[float], start: float, end: float) -> float:
    """Frames per second in ``[start, end)`` from sorted arrival times.

    From inter-arrival times, counting the gap from the frame before the window: exact even
    when a slow stream (1.48 Hz) has one or two frames in a short window. Without a gap to
    time, the count over the window.
    """
    first, stop = bisect.bisect_left(times, start), bisect.bisect_left(times, end)
    timed_from = max(first, 1)
    if stop > timed_from and times[stop - 1] > times[timed_from - 1]:
        return (stop - timed_from) / (times[stop - 1] - times[timed_from - 1])
    return (stop - first) / (end - start)


def _percentile_ms(latencies: list[float], q: float) -> float | None:
    return None if not latencies else float(np.percentile(latencies, q)) * _MS_PER_S


def _losses(frames: Sequence[Arrival]) -> list[tuple[float, int]]:
    """(arrival time, frames missing before this one) for every sequence gap of one robot."""
    last: int | None = None
    gaps = []
    for frame in frames:
        if frame.seq is None:
            continue
        if last is not None and frame.seq > last + 1:
            gaps.append((frame.arrival_s, frame.seq - last - 1))
        if last is None or frame.seq > last:
            last = frame.seq
    return gaps


class _Robot:
    """One robot's frames, sorted by arrival, with what every window needs."""

    def __init__(self, name: str, index: int, frames: Sequence[Arrival]) -> None:
        self.name, self.index = name, index
        self.frames = sorted((f for f in frames if f.robot == index), key=lambda f: f.arrival_s)
        self.times = [f.arrival_s for f in self.frames]
        self.gaps = _losses(self.frames)

    def window(
        self, start: float, end: float, allocated_hz: float | None, *, lost_from: float
    ) -> Window:
        inside = self.frames[
            bisect.bisect_left(self.times, start) : bisect.bisect_left(self.times, end)
        ]
        latencies = [f.arrival_s - f.sent_s for f in inside if f.sent_s is not None]
        delivered = rate_hz(self.times, start, end)
        mean_size = sum(f.size_bytes for f in inside) / len(inside) if inside else 0.0
        return Window(
            robot=self.name,
            allocated_hz=allocated_hz,
            delivered_hz=delivered,
            latency_p50_ms=_percentile_ms(latencies, 50),
            latency_p95_ms=_percentile_ms(latencies, 95),
            lost=sum(n for at, n in self.gaps if lost_from <= at < end),
            goodput_mbit=bytes_per_s_to_mbit(delivered * mean_size),
        )

    def applied_hz(self, at: float) -> float | None:
        """The rate the publisher applied, from the last frame that arrived by ``at``."""
        applied = [f.rate_hz for f in self.frames[: bisect.bisect_right(self.times, at)]]
        return next((r for r in reversed(applied) if r is not None), None)


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
) -> Analysis:
    """Steps, time series and the recovery after every link change."""
    streams = [_Robot(name, i, frames) for i, name in enumerate(robots)]
    ordered = sorted(ticks, key=lambda t: t.t_s)
    tick_times = [t.t_s for t in ordered]

    def seen(at: float) -> Tick | None:
        index = bisect.bisect_right(tick_times, at)
        return ordered[index - 1] if index else None

    def allocated(stream: _Robot, at: float) -> float | None:
        tick = seen(at)
        value = tick.allocated_hz[stream.index] if tick is not None else None
        return stream.applied_hz(at) if value is None else value  # unmanaged: what it applied

    step_rows = []
    for k in range(steps):
        start, end = t0 + k * step_s, t0 + (k + 1) * step_s
        tick = seen(end)
        rows = []
        for stream in streams:
            window = stream.window(
                start + settle_s(step_s), end, allocated(stream, end), lost_from=start
            )
            variant = tick.variants[stream.index] if tick is not None and tick.variants else None
            rows.append(replace(window, variant=variant))
        step_rows.append(
            StepResult(
                step=k + 1,
                robots=tuple(rows),
                budget_mbit=None if tick is None else tick.budget_mbit,
                estimate_mbit=None if tick is None else tick.estimate_mbit,
                link_mbit=link_at(schedule, end - t0 - _EDGE_S, link_mbit),
            )
        )

    series = []
    t = t0 + WINDOW_S
    while t <= t0 + steps * step_s + _EDGE_S:
        tick = seen(t)
        series.append(
            SeriesPoint(
                t_s=t - t0,
                robots=tuple(
                    s.window(t - WINDOW_S, t, allocated(s, t), lost_from=t - WINDOW_S)
                    for s in streams
                ),
                budget_mbit=None if tick is None else tick.budget_mbit,
                estimator=None if tick is None else tick.estimator,
                link_mbit=link_at(schedule, t - t0, link_mbit),
            )
        )
        t += WINDOW_STEP_S
    changes = _changes(
        series, ordered, streams, schedule, t0=t0, end_s=steps * step_s, link_mbit=link_mbit
    )
    phases = _phases(streams, schedule, t0=t0, end_s=steps * step_s, link_mbit=link_mbit)
    return Analysis(tuple(step_rows), tuple(series), changes, phases)


def _link_rates(
    schedule: Sequence[tuple[float, float]], link_mbit: float
) -> list[tuple[float, float]]:
    """Each rate of the link from when it starts: the schedule's own at 0 s, else the default."""
    return [(0.0, link_at(schedule, 0.0, link_mbit)), *[(t, r) for t, r in schedule if t > 0]]


def _phases(
    streams: Sequence[_Robot],
    schedule: Sequence[tuple[float, float]],
    *,
    t0: float,
    end_s: float,
    link_mbit: float,
) -> tuple[LinkPhase, ...]:
    """Goodput, p95 latency and losses of every phase of the link schedule."""
    rates = _link_rates(schedule, link_mbit)
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
                _percentile_ms(latencies, 95),
                sum(n for s in streams for t, n in s.gaps if start <= t < end),
            )
        )
    return tuple(phases)


def _cut_time(tick: Tick) -> float:
    """When the estimate a tick saw was decided: the estimator's stamp, else the tick."""
    match = CUT_STAMP.search(tick.estimator or "")
    return float(match.group(1)) if match else tick.t_s


def _goodput_share(series: Sequence[SeriesPoint], start_s: float, end_s: float) -> float | None:
    """Mean goodput of the windows inside ``[start_s, end_s]`` over the link rate."""
    inside = [
        p
        for p in series
        if p.t_s - WINDOW_S >= start_s - _EDGE_S and p.t_s <= end_s and p.link_mbit > 0
    ]
    if not inside:
        return None
    return sum(p.goodput_mbit / p.link_mbit for p in inside) / len(inside)


def _changes(
    series: Sequence[SeriesPoint],
    ticks: Sequence[Tick],
    streams: Sequence[_Robot],
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
    rates = _link_rates(schedule, link_mbit)
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
                max(_cut_time(t), t0 + at) - t0 - at
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


def latest(
    arrivals: Sequence[Arrival], ticks: Sequence[Tick], *, robots: Sequence[str]
) -> tuple[Window, ...]:
    """Every robot over the ``LIVE_WINDOW_S`` before the newest tick: a live view's reading."""
    if not ticks:
        return ()
    now, tick = ticks[-1].t_s, ticks[-1]
    recent = arrivals[-LIVE_FRAMES:]
    return tuple(
        _Robot(name, i, recent).window(
            now - LIVE_WINDOW_S, now, tick.allocated_hz[i], lost_from=now - LIVE_WINDOW_S
        )
        for i, name in enumerate(robots)
    )


@dataclass(frozen=True, slots=True)
class StreamLatency:
    """One stream's one-way latency over a whole run (the urgent stream beside the cameras)."""

    name: str
    received: int
    lost: int
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    latency_max_ms: float | None


def stream_latency(frames: Sequence[Arrival], index: int, *, name: str) -> StreamLatency:
    """Latency percentiles and losses of the frames reported as robot ``index``, all of them."""
    stream = _Robot(name, index, frames)
    latencies = [f.arrival_s - f.sent_s for f in stream.frames if f.sent_s is not None]
    return StreamLatency(
        name=name,
        received=len(stream.frames),
        lost=sum(n for _, n in stream.gaps),
        latency_p50_ms=_percentile_ms(latencies, 50),
        latency_p95_ms=_percentile_ms(latencies, 95),
        latency_max_ms=max(latencies) * _MS_PER_S if latencies else None,
    )


@dataclass(frozen=True, slots=True)
class Outage:
    """A link outage (0 Mbit in the schedule) and the restoration after it."""

    start_s: float
    end_s: float
    """When the link came back (seconds after step 1 started)."""
    urgent: str
    """The most urgent channel's robot when the link came back."""
    first_urgent_s: float | None
    """From the restoration to the urgent channel's first frame, stale or not."""
    first_fresh_urgent_s: float | None
    """...to its first frame sent after the restoration (not the backlog of the outage)."""
    stale: int
    """Frames sent before the restoration that arrived after it: the outage's backlog."""
    lost: int
    """Frames lost (sequence gaps) from the outage's start to ``OUTAGE_AFTER_S`` after it."""
    worst_window_mbit: float | None
    """The most any 1-s window carried in the ``OUTAGE_AFTER_S`` after the restoration: the
    wire, with the backlog sent before the link went down."""
    worst_sent_after_mbit: float | None
    """The same of frames sent after the restoration only: what the release sent."""
    budget_mbit: float | None
    """The largest budget in force in that time (None: nothing allocated, unmanaged)."""
    over_budget_mbit: float | None = None
    """How far the wire's worst window went over the budget in force over that window
    (negative: under it). Each window is judged against its own budget, the time-weighted mean
    of the budgets in force across it: a budget cut after the restoration must not be hidden
    by the larger one before it, nor a raise counted as excess."""
    release_over_budget_mbit: float | None = None
    """The same of what was sent after the restoration only: what the release sent."""


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


def _worst_windows(
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
        if start > end - WINDOW_S + _EDGE_S:
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
    streams = [_Robot(name, i, frames) for i, name in enumerate(robots)]
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
        wire, wire_over = _worst_windows(
            [t for t, _, _ in inside], [b for _, b, _ in inside], until, known
        )
        sent, sent_over = _worst_windows(
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
