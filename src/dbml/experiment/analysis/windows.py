"""One robot's frames over a window: delivered rate, latency percentiles, losses, goodput."""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

from dbml.core.spec import bytes_per_s_to_mbit
from dbml.experiment.analysis.records import Arrival, StreamLatency, Tick, Window
from dbml.experiment.analysis.thresholds import LIVE_FRAMES, LIVE_WINDOW_S

__all__ = [
    "EDGE_S",
    "MS_PER_S",
    "RobotFrames",
    "latest",
    "link_at",
    "link_rates",
    "percentile_ms",
    "rate_hz",
    "settle_s",
    "stream_latency",
]

MS_PER_S = 1000.0
EDGE_S = 1e-9
"""A time this close to a window's edge counts as on it (float sums of steps)."""
_FITTED_FRAMES = 3
"""From this many frames on, a window's rate is a fitted slope, not the span of two."""


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


def link_mean(
    schedule: Sequence[tuple[float, float]], start_s: float, end_s: float, default: float
) -> float:
    """The shaped rate's mean over ``[start_s, end_s)`` (a recorded trace's, over a step)."""
    if end_s <= start_s:
        return link_at(schedule, start_s, default)
    rates = link_rates(schedule, default)
    total = 0.0
    for (at, mbit), (until, _) in zip(rates, [*rates[1:], (math.inf, 0.0)], strict=True):
        lo, hi = max(at, start_s), min(until, end_s)
        if hi > lo:
            total += mbit * (hi - lo)
    return total / (end_s - start_s)


def link_rates(
    schedule: Sequence[tuple[float, float]], link_mbit: float
) -> list[tuple[float, float]]:
    """Each rate of the link from when it starts: the schedule's own at 0 s, else the default."""
    return [(0.0, link_at(schedule, 0.0, link_mbit)), *[(t, r) for t, r in schedule if t > 0]]


def rate_hz(times: Sequence[float], start: float, end: float) -> float:
    """Frames per second in ``[start, end)`` from sorted arrival times.

    Timed, not counted, from the frame before the window on: exact even when a slow stream
    (1.48 Hz) has one or two frames in a short window. With three frames or more, the rate is
    the least-squares slope of their arrival times, so a frame that waited behind another
    stream's (an 84 KB frame holds a shared 11 Mbit/s link for 61 ms) moves it little: timed
    from the first frame to the last alone, a 16 Hz stream whose latency varies between 13 and
    78 ms read 15.6 to 16.2 Hz in a 1.3 s window. Without a gap to time, the count over the
    window.
    """
    first, stop = bisect.bisect_left(times, start), bisect.bisect_left(times, end)
    timed = times[max(first, 1) - 1 : stop]
    if len(timed) >= _FITTED_FRAMES:
        slope = float(np.polyfit(np.arange(len(timed)), timed, 1)[0])
        if slope > 0:
            return 1.0 / slope
    if len(timed) > 1 and timed[-1] > timed[0]:
        return (len(timed) - 1) / (timed[-1] - timed[0])
    return (stop - first) / (end - start)


def percentile_ms(latencies: list[float], q: float) -> float | None:
    """The ``q``-th percentile of latencies in seconds, in milliseconds (None if none)."""
    return None if not latencies else float(np.percentile(latencies, q)) * MS_PER_S


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


class RobotFrames:
    """One robot's frames, sorted by arrival, with what every window needs."""

    def __init__(self, name: str, index: int, frames: Sequence[Arrival]) -> None:
        self.name, self.index = name, index
        self.frames = sorted((f for f in frames if f.robot == index), key=lambda f: f.arrival_s)
        self.times = [f.arrival_s for f in self.frames]
        self.gaps = _losses(self.frames)

    def window(
        self, start: float, end: float, allocated_hz: float | None, *, lost_from: float
    ) -> Window:
        """``[start, end)`` as a ``Window``; losses counted from ``lost_from``."""
        inside = self.frames[
            bisect.bisect_left(self.times, start) : bisect.bisect_left(self.times, end)
        ]
        latencies = [f.arrival_s - f.sent_s for f in inside if f.sent_s is not None]
        delivered = rate_hz(self.times, start, end)
        mean_size = sum(f.size_bytes for f in inside) / len(inside) if inside else 0.0
        scores = [f.ssim for f in inside if f.ssim is not None]
        return Window(
            robot=self.name,
            allocated_hz=allocated_hz,
            delivered_hz=delivered,
            latency_p50_ms=percentile_ms(latencies, 50),
            latency_p95_ms=percentile_ms(latencies, 95),
            lost=sum(n for at, n in self.gaps if lost_from <= at < end),
            goodput_mbit=bytes_per_s_to_mbit(delivered * mean_size),
            ssim=sum(scores) / len(scores) if scores else None,
        )

    def applied_hz(self, at: float) -> float | None:
        """The rate the publisher applied, from the last frame that arrived by ``at``."""
        applied = [f.rate_hz for f in self.frames[: bisect.bisect_right(self.times, at)]]
        return next((r for r in reversed(applied) if r is not None), None)


def latest(
    arrivals: Sequence[Arrival], ticks: Sequence[Tick], *, robots: Sequence[str]
) -> tuple[Window, ...]:
    """Every robot over the ``LIVE_WINDOW_S`` before the newest tick: a live view's reading."""
    if not ticks:
        return ()
    now, tick = ticks[-1].t_s, ticks[-1]
    recent = arrivals[-LIVE_FRAMES:]
    return tuple(
        RobotFrames(name, i, recent).window(
            now - LIVE_WINDOW_S, now, tick.allocated_hz[i], lost_from=now - LIVE_WINDOW_S
        )
        for i, name in enumerate(robots)
    )


def stream_latency(frames: Sequence[Arrival], index: int, *, name: str) -> StreamLatency:
    """Latency percentiles and losses of the frames reported as robot ``index``, all of them."""
    stream = RobotFrames(name, index, frames)
    latencies = [f.arrival_s - f.sent_s for f in stream.frames if f.sent_s is not None]
    return StreamLatency(
        name=name,
        received=len(stream.frames),
        lost=sum(n for _, n in stream.gaps),
        latency_p50_ms=percentile_ms(latencies, 50),
        latency_p95_ms=percentile_ms(latencies, 95),
        latency_max_ms=max(latencies) * MS_PER_S if latencies else None,
    )
