"""A bottleneck link in simulation: FIFO, one frame at a time, capacity changing over time.

Closed loop (open without an estimator): senders share ``utilization * estimate`` by bytes
(80/20, or ``shares`` at each time; each capped at its maximum rate), the estimate reaches them
``reaction_s`` late, the estimator sees each frame once it has arrived (``report_lag_s`` later,
as the node judges the window its reports completed). ``jitter_s`` adds a delay per frame after
the bottleneck (a stream's frames stay in order), as the testbed's traces measured
(bench/estimator_replay.py). Pure arithmetic, so the loop is exact and repeatable.
"""

from __future__ import annotations

import bisect
import heapq
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from dbml.estimator.base import Arrival, Estimate
from dbml.estimator.shared import BandwidthEstimator

__all__ = [
    "CAP_MBIT",
    "FRAMES",
    "WIRE_EFFICIENCY",
    "Trace",
    "drop_and_rise",
    "simulate",
    "transmission_over",
]

FRAMES = (("r1", 84_000, 16.0, 0.8), ("r2", 21_000, 16.0, 0.2))
"""The paper's two cameras: stream, bytes per frame, maximum Hz, share of the budget."""
WIRE_EFFICIENCY = 0.957
"""Payload Mbit/s per shaped Mbit/s, measured with raw TCP on the testbed's link."""
CAP_MBIT = 11.0 * 0.92
"""The testbed's budget on its 11-Mbit/s link: the estimate's cap."""


_DROP_S, _RISE_S = 20.0, 40.0
_NEVER_S = 3600.0
"""A transmission on a link that never comes back ends this long after it started."""
_FULL_MBIT, _DROPPED_MBIT = 11.0, 5.0
_P95 = 0.95


def drop_and_rise(t: float) -> float:
    """The testbed's drop: 11 Mbit/s, 5 from 20 s, 11 again from 40 s."""
    return _FULL_MBIT if t < _DROP_S or t >= _RISE_S else _DROPPED_MBIT


def transmission_over(
    schedule: Sequence[tuple[float, float]], *, wire_efficiency: float = WIRE_EFFICIENCY
) -> Callable[[float, float], float]:
    """``simulate``'s ``transmit_until`` for a link of ``(from s, Mbit/s)`` steps.

    A frame's transmission is the capacity integrated over its time on the wire, so a fade (a
    step near 0) holds the frame in flight until the link comes back.
    """
    times = [at for at, _ in schedule]
    rates = [mbit * wire_efficiency for _, mbit in schedule]

    def finish_s(start_s: float, megabits: float) -> float:
        i = max(bisect.bisect_right(times, start_s) - 1, 0)
        t, left = start_s, megabits
        while True:
            end = times[i + 1] if i + 1 < len(times) else float("inf")
            rate = rates[i]
            if rate > 0 and t + left / rate <= end:
                return t + left / rate
            if end == float("inf"):
                return t + (left / rate if rate > 0 else _NEVER_S)
            left -= rate * (end - t)
            t, i = end, i + 1

    return finish_s


@dataclass
class Trace:
    """What a simulation saw: each update's estimate, each frame's delay, what was offered."""

    estimates: list[Estimate] = field(default_factory=list)
    delays: list[tuple[float, float, str]] = field(default_factory=list)
    """(arrival s, one-way delay s, stream) of every frame."""
    sent_mbit: list[tuple[float, float]] = field(default_factory=list)
    """(time s, Mbit/s the senders offered) at each tick."""

    def estimate_at(self, t_s: float) -> float:
        """The estimate in force at ``t_s``."""
        return next(e.estimate_mbit for e in reversed(self.estimates) if e.t_s <= t_s)

    def p95_delay(self, start_s: float, end_s: float) -> float:
        """The 95th percentile of the delays of the frames that arrived in ``[start_s, end_s)``."""
        delays = sorted(d for t, d, _ in self.delays if start_s <= t < end_s)
        return delays[int(_P95 * (len(delays) - 1))]

    def max_delay(self, start_s: float, end_s: float, stream: str | None = None) -> float:
        """The longest delay of the frames (of ``stream``) that arrived in ``[start_s, end_s)``."""
        return max(d for t, d, s in self.delays if start_s <= t < end_s and stream in (None, s))


def simulate(
    estimator: BandwidthEstimator | None,
    link_mbit: Callable[[float], float],
    *,
    duration_s: float,
    constant_mbit: float = 0.0,
    utilization: float = 1.0,
    tick_s: float = 0.1,
    reaction_s: float = 0.15,
    clock_offsets_s: dict[str, float] | None = None,
    propagation_s: float = 0.001,
    wire_efficiency: float = WIRE_EFFICIENCY,
    jitter_s: Callable[[str, int], float] | None = None,
    report_lag_s: float = 0.0,
    shares: Callable[[float], Mapping[str, float]] | None = None,
    transmit_until: Callable[[float, float], float] | None = None,
) -> Trace:
    """``FRAMES``' senders over a link of ``link_mbit(t)`` for ``duration_s``, and what arrived.

    ``estimator`` (None: a constant budget of ``constant_mbit``) is told each frame as it
    arrives (``report_lag_s`` late) and updated every ``tick_s``; its estimate reaches the
    senders ``reaction_s`` later. ``clock_offsets_s`` shifts a stream's send times (the
    sender's clock); ``jitter_s(stream, seq)`` delays a frame after the bottleneck.
    ``transmit_until(start_s, megabits)``: when a frame's transmission started at ``start_s``
    ends (a recorded link's capacity integrated over it); else at ``link_mbit(start)``.
    """
    offsets = clock_offsets_s or {}
    last_arrival = dict.fromkeys((name for name, *_ in FRAMES), 0.0)
    trace = Trace()
    start = constant_mbit if estimator is None else estimator.estimate_mbit
    budgets: list[tuple[float, float]] = [(0.0, start)]  # (effective from, Mbit/s)
    next_send = {name: 0.0 for name, *_ in FRAMES}
    seqs = dict.fromkeys(next_send, 0)
    link_free_s = 0.0
    pending: list[tuple[float, int, Arrival]] = []
    order = 0

    def rate_hz(name: str, size: int, max_hz: float, share: float, t: float) -> float:
        budget = next(b for at, b in reversed(budgets) if at <= t)
        if shares is not None:
            share = shares(t).get(name, share)
        return max(1.0, min(max_hz, utilization * budget * share / (size * 8e-6)))

    t = 0.0
    while t < duration_s:
        tick_end = t + tick_s
        # senders: every frame sent before the end of this tick enters the FIFO in send order
        while True:
            name, size, max_hz, share = min(FRAMES, key=lambda f: next_send[f[0]])
            sent = next_send[name]
            if sent >= tick_end:
                break
            start = max(sent + propagation_s, link_free_s)
            if transmit_until is not None:
                link_free_s = transmit_until(start, size * 8e-6)
            else:
                link_free_s = start + size * 8e-6 / (link_mbit(start) * wire_efficiency)
            extra = 0.0 if jitter_s is None else jitter_s(name, seqs[name])
            arrived_s = max(link_free_s + extra, last_arrival[name])
            last_arrival[name] = arrived_s
            arrival = Arrival(name, seqs[name], sent + offsets.get(name, 0.0), arrived_s, size)
            heapq.heappush(pending, (arrived_s, order, arrival))
            order += 1
            seqs[name] += 1
            trace.delays.append((arrived_s, arrived_s - sent, name))
            next_send[name] = sent + 1.0 / rate_hz(name, size, max_hz, share, sent)
        judged_s = tick_end - report_lag_s
        while pending and pending[0][0] <= judged_s:
            arrived = heapq.heappop(pending)[2]
            if estimator is not None:
                estimator.observe(arrived)
        if estimator is not None:
            estimate = estimator.update(judged_s)
            trace.estimates.append(estimate)
            budgets.append((tick_end + reaction_s, estimate.estimate_mbit))
        offered = sum(
            rate_hz(n, size, hz, share, tick_end) * size * 8e-6 for n, size, hz, share in FRAMES
        )
        trace.sent_mbit.append((tick_end, offered))
        t = tick_end
    return trace
