"""What a testbed run measured: per step and robot, and how fast the system followed the link.

Pure: it takes the frames the operator received (robot, sequence number, send time, arrival
time, size, the rate the publisher applied) and the parameters it saw, and computes delivered
rates, one-way latency percentiles, losses (sequence gaps) and goodput, per step, plus the
recovery times after each change of the link's rate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dbml.testbed.netns import TestbedError

__all__ = [
    "Frame",
    "Tick",
    "analyse",
    "link_at",
    "parse_schedule",
    "parse_uplinks",
    "settle_s",
]

WINDOW_S = 1.0
"""Rolling windows for the time series and the recovery targets."""
WINDOW_STEP_S = 0.25


@dataclass(frozen=True, slots=True)
class Frame:
    robot: int
    seq: int
    sent_s: float
    arrival_s: float
    size_bytes: int
    rate_hz: float
    """The rate the publisher applied when it sent this frame."""


@dataclass(frozen=True, slots=True)
class Tick:
    """The parameters the operator saw at ``t_s``."""

    t_s: float
    allocated_hz: tuple[float | None, ...]
    budget_mbit: float | None
    estimate_mbit: float | None
    estimator: str | None = None
    """The estimator's state (phase, receive rate, queueing, losses), when one runs."""


def parse_schedule(text: str) -> tuple[tuple[float, float], ...]:
    """``"0:11,20:5,40:11"`` -> ((0, 11), (20, 5), (40, 11)): seconds -> Mbit/s, increasing."""
    entries: list[tuple[float, float]] = []
    for part in text.split(","):
        at, sep, rate = part.strip().partition(":")
        try:
            if not sep:
                raise ValueError(part)
            t_s, mbit = float(at), float(rate)
        except ValueError:
            raise TestbedError(
                f"--link-schedule={text!r}: {part.strip()!r} must be SECONDS:MBIT"
            ) from None
        if not (math.isfinite(t_s) and t_s >= 0):
            raise TestbedError(f"--link-schedule={text!r}: time {at!r} must be >= 0")
        if not (math.isfinite(mbit) and mbit > 0):
            raise TestbedError(f"--link-schedule={text!r}: rate {rate!r} must be > 0")
        if entries and t_s <= entries[-1][0]:
            raise TestbedError(f"--link-schedule={text!r}: times must increase ({at!r})")
        entries.append((t_s, mbit))
    return tuple(entries)


def parse_uplinks(items: Sequence[str], robots: Sequence[str]) -> dict[str, float]:
    """``["R1=4"]`` -> {"R1": 4.0}; the robot must exist and the rate be > 0."""
    uplinks: dict[str, float] = {}
    for item in items:
        robot, sep, rate = item.partition("=")
        robot = robot.strip().upper()
        if not sep or robot not in robots:
            raise TestbedError(f"--uplink={item!r} must be ROBOT=MBIT with ROBOT in {robots}")
        try:
            mbit = float(rate)
        except ValueError:
            raise TestbedError(f"--uplink={item!r}: rate {rate!r} is not a number") from None
        if not (math.isfinite(mbit) and mbit > 0):
            raise TestbedError(f"--uplink={item!r}: rate {rate!r} must be > 0")
        uplinks[robot] = mbit
    return uplinks


def link_at(schedule: Sequence[tuple[float, float]], t_s: float, default: float) -> float:
    """The shaped rate in force at ``t_s`` seconds after the start."""
    rate = default
    for at, mbit in schedule:
        if at <= t_s:
            rate = mbit
    return rate


def settle_s(step_s: float) -> float:
    """Time after a step starts before it is measured: the new rates take effect."""
    return min(1.0, step_s / 3)


def _rate_hz(inside: Sequence[Frame], span_s: float) -> float:
    """Frames per second: from inter-arrival times when there are a few (exact even for short
    windows), else the count over the window."""
    if len(inside) >= 3:
        first, last = inside[0].arrival_s, inside[-1].arrival_s
        if last > first:
            return (len(inside) - 1) / (last - first)
    return len(inside) / span_s


def _goodput_mbit(inside: Sequence[Frame], rate_hz: float) -> float:
    """Payload Mbit/s: the delivered rate times the mean frame size (no window-edge effect)."""
    return rate_hz * sum(f.size_bytes for f in inside) / len(inside) * 8e-6 if inside else 0.0


def _percentile_ms(latencies: list[float], q: float) -> float | None:
    return None if not latencies else float(np.percentile(latencies, q)) * 1000


def _losses(frames: Sequence[Frame]) -> list[tuple[float, int]]:
    """(arrival time, frames missing before this one) for every sequence gap."""
    last: dict[int, int] = {}
    gaps = []
    for frame in sorted(frames, key=lambda f: f.arrival_s):
        previous = last.get(frame.robot)
        if previous is not None and frame.seq > previous + 1:
            gaps.append((frame.arrival_s, frame.seq - previous - 1))
        if previous is None or frame.seq > previous:
            last[frame.robot] = frame.seq
    return gaps


def analyse(
    frames: Sequence[Frame],
    ticks: Sequence[Tick],
    *,
    robots: Sequence[str],
    t0: float,
    step_s: float,
    steps: int,
    link_mbit: float,
    schedule: Sequence[tuple[float, float]] = (),
) -> dict[str, Any]:
    """Steps, time series and the recovery after every link change, as plain data."""
    ordered = sorted(frames, key=lambda f: f.arrival_s)
    by_robot = [[f for f in ordered if f.robot == i] for i in range(len(robots))]
    gaps = [_losses(mine) for mine in by_robot]

    def allocated(robot: int, at: float) -> float | None:
        seen = [t.allocated_hz[robot] for t in ticks if t.t_s <= at]
        value = seen[-1] if seen else None
        if value is None:  # unmanaged: the rate the publisher applied
            sent = [f.rate_hz for f in by_robot[robot] if f.sent_s <= at]
            value = sent[-1] if sent else None
        return value

    def budget(at: float) -> tuple[float | None, float | None]:
        seen = [t for t in ticks if t.t_s <= at]
        return (seen[-1].budget_mbit, seen[-1].estimate_mbit) if seen else (None, None)

    step_rows = []
    for k in range(steps):
        start, end = t0 + k * step_s, t0 + (k + 1) * step_s
        measured_from = start + settle_s(step_s)
        span = end - measured_from
        rows: list[dict[str, Any]] = []
        for i, robot in enumerate(robots):
            inside = [f for f in by_robot[i] if measured_from <= f.arrival_s < end]
            latencies = [f.arrival_s - f.sent_s for f in inside]
            delivered = _rate_hz(inside, span)
            rows.append(
                {
                    "robot": robot,
                    "allocated_hz": allocated(i, end),
                    "delivered_hz": delivered,
                    "latency_p50_ms": _percentile_ms(latencies, 50),
                    "latency_p95_ms": _percentile_ms(latencies, 95),
                    "lost": sum(n for t, n in gaps[i] if start <= t < end),
                    "goodput_mbit": _goodput_mbit(inside, delivered),
                }
            )
        used, estimate = budget(end)
        step_rows.append(
            {
                "step": k + 1,
                "robots": rows,
                "goodput_mbit": sum(r["goodput_mbit"] for r in rows),
                "budget_mbit": used,
                "estimate_mbit": estimate,
                "link_mbit": link_at(schedule, end - t0 - 1e-9, link_mbit),
            }
        )

    series = _series(by_robot, gaps, ticks, t0=t0, end=t0 + steps * step_s, robots=robots)
    for point in series:
        point["link_mbit"] = link_at(schedule, point["t"], link_mbit)
    changes = _changes(
        series, ticks, gaps, schedule, t0=t0, end_s=steps * step_s, link_mbit=link_mbit
    )
    return {"steps": step_rows, "series": series, "changes": changes}


def _series(
    by_robot: list[list[Frame]],
    gaps: list[list[tuple[float, int]]],
    ticks: Sequence[Tick],
    *,
    t0: float,
    end: float,
    robots: Sequence[str],
) -> list[dict[str, Any]]:
    """Rolling 1-s windows every 0.25 s: delivered rate, p95 latency, losses, budget."""
    points = []
    t = t0 + WINDOW_S
    while t <= end + 1e-9:
        seen = [tick for tick in ticks if tick.t_s <= t]
        robots_now: list[dict[str, Any]] = []
        for i, robot in enumerate(robots):
            inside = [f for f in by_robot[i] if t - WINDOW_S <= f.arrival_s < t]
            latencies = [f.arrival_s - f.sent_s for f in inside]
            robots_now.append(
                {
                    "robot": robot,
                    "allocated_hz": seen[-1].allocated_hz[i] if seen else None,
                    "delivered_hz": len(inside) / WINDOW_S,
                    "latency_p95_ms": _percentile_ms(latencies, 95),
                    "lost": sum(n for at, n in gaps[i] if t - WINDOW_S <= at < t),
                    "goodput_mbit": sum(f.size_bytes for f in inside) * 8e-6 / WINDOW_S,
                }
            )
        points.append(
            {
                "t": t - t0,
                "robots": robots_now,
                "budget_mbit": seen[-1].budget_mbit if seen else None,
                "estimator": seen[-1].estimator if seen else None,
                "goodput_mbit": sum(r["goodput_mbit"] for r in robots_now),
            }
        )
        t += WINDOW_STEP_S
    return points


def _changes(
    series: list[dict[str, Any]],
    ticks: Sequence[Tick],
    gaps: list[list[tuple[float, int]]],
    schedule: Sequence[tuple[float, float]],
    *,
    t0: float,
    end_s: float,
    link_mbit: float,
) -> list[dict[str, Any]]:
    """For each change of the link rate: when latency and losses recovered (a drop) or when
    the budget grew back to 90 % of the link (a rise)."""
    changes = []
    rates = [(0.0, link_mbit), *[(at, mbit) for at, mbit in schedule if at > 0]]
    for k in range(1, len(rates)):
        at, mbit = rates[k]
        before = rates[k - 1][1]
        until = rates[k + 1][0] if k + 1 < len(rates) else end_s
        if at >= end_s:
            break
        change: dict[str, Any] = {"t_s": at, "from_mbit": before, "to_mbit": mbit}
        if mbit < before:
            # windows that start after the change: from which one on are all of them good?
            after = [p for p in series if p["t"] - WINDOW_S >= at and p["t"] <= until]
            recovered: float | None = None
            for point in reversed(after):
                good = all(
                    (r["latency_p95_ms"] is None or r["latency_p95_ms"] < 250) and r["lost"] == 0
                    for r in point["robots"]
                )
                if not good:
                    break
                recovered = point["t"] - at
            change["recovery_s"] = recovered
            change["max_latency_p95_ms"] = max(
                (
                    r["latency_p95_ms"]
                    for p in series
                    if at <= p["t"] - WINDOW_S and p["t"] <= until
                    for r in p["robots"]
                    if r["latency_p95_ms"] is not None
                ),
                default=None,
            )
            change["lost_after"] = sum(
                n for mine in gaps for t, n in mine if t0 + at < t <= t0 + until
            )
        else:
            reached = next(
                (
                    t.t_s - t0 - at
                    for t in ticks
                    if at <= t.t_s - t0 <= until
                    and t.budget_mbit is not None
                    and t.budget_mbit >= 0.9 * mbit
                ),
                None,
            )
            change["budget_recovery_s"] = reached
        changes.append(change)
    return changes
