"""What a perfect bandwidth estimator lets the teleoperation scenario reach on a recorded link.

The oracle knows the link's capacity at every instant. Every ``reallocate_s`` it hands the
optimizer what the link carries of payload at that moment (``WIRE_EFFICIENCY`` of the shaped
rate), capped at the configured budget; the cameras send what the allocation gives them through
one FIFO bottleneck that follows the trace exactly. A benchmark reports each real estimator as a
fraction of this run. Pure arithmetic (no I/O, threads or clocks, every time an argument): a run
is exact and repeatable.

``simulate_fixed_budget`` runs the same on a budget that never moves: the latency each share of
a recorded link costs a sender that does not know its fades in advance.

Below the cap the oracle loads the link at exactly its payload capacity, so a backlog left by
the reallocation lag (a drop between two ticks) drains only once the capacity is back above the
cap: that latency is the price of a perfect estimate, not an estimator's error.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dbml.core.allocation import Strategy
from dbml.core.errors import SpecError
from dbml.core.spec import BYTES_PER_S_PER_MBIT, MAX_PERIOD_S, MIN_PERIOD_S, check_number
from dbml.estimator.simulation import WIRE_EFFICIENCY
from dbml.scenarios.fleet import fleet_allocation, fleet_cameras, fleet_steps
from dbml.scenarios.traces import LinkTrace

__all__ = [
    "DEFAULT_MAX_QUEUE_S",
    "WINDOW_S",
    "OracleRun",
    "OracleWindow",
    "bottleneck_departures",
    "oracle_budget",
    "simulate_fixed_budget",
    "simulate_oracle",
]

DEFAULT_MAX_QUEUE_S = 2.0
"""A frame that would wait longer than this behind the frames ahead of it is lost: the queue
the testbed's links hold is bounded, and an oracle that sizes its budget right never gets near."""
WINDOW_S = 1.0
"""The width of a goodput window."""
_PHASE_SPREAD_S = 1.0 / 16.0
"""Camera ``k`` of ``n`` sends its first frame ``k / n`` of this in: the shortest frame period
(16 Hz), so the cameras' first frames do not all queue behind one another."""
_REALLOCATE_S = 0.1
"""How often the oracle hands the optimizer the capacity (the estimator's update period)."""
_EDGE = 1e-9
"""Slack on ``t / step_s`` so a float sum of ticks on a step's edge counts as in that step."""
_MS_PER_S = 1000.0


@dataclass(frozen=True, slots=True)
class OracleWindow:
    """One ``WINDOW_S`` window from ``t_s``: delivered payload, payload capacity, oracle budget.

    All in Mbit/s; frames count whole in the window they leave the bottleneck in.
    """

    t_s: float
    goodput_mbit: float
    capacity_mbit: float
    budget_mbit: float


@dataclass(frozen=True, slots=True)
class OracleRun:
    """What the oracle reached over ``duration_s``: the reference each estimator is a share of.

    Frames still queued at the end were sent but neither delivered nor lost. Latency
    percentiles are of the delivered frames (None if none was).
    """

    duration_s: float
    frames_sent: int
    frames_delivered: int
    frames_lost: int
    sent_bytes: int
    delivered_bytes: int
    capacity_payload_bytes: float
    """The payload the link could carry over the run."""
    budget_bytes: float
    """The oracle's budget integrated over the run (``oracle_budget`` at every instant)."""
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    latency_p99_ms: float | None
    windows: tuple[OracleWindow, ...]

    @property
    def frames_queued(self) -> int:
        """Frames still in the bottleneck at the end."""
        return self.frames_sent - self.frames_delivered - self.frames_lost

    @property
    def utilisation(self) -> float:
        """Delivered payload over the payload the link could carry (0 if it never could)."""
        if self.capacity_payload_bytes <= 0:
            return 0.0
        return self.delivered_bytes / self.capacity_payload_bytes

    @property
    def budget_share(self) -> float:
        """Delivered payload over the oracle's budget (0 if the budget was always 0)."""
        if self.budget_bytes <= 0:
            return 0.0
        return self.delivered_bytes / self.budget_bytes


class _Rate:
    """A piecewise-constant rate (bytes/s) from 0 s, the last one lasting forever.

    Its integral and the integral's inverse are a bisection each: a run's cost grows with its
    frames, not with the trace's length.
    """

    __slots__ = ("at_s", "cumulative", "rates")

    def __init__(self, at_s: list[float], rates: list[float]) -> None:
        self.at_s = at_s
        self.rates = rates
        self.cumulative = [0.0]
        for k in range(1, len(at_s)):
            self.cumulative.append(self.cumulative[-1] + rates[k - 1] * (at_s[k] - at_s[k - 1]))

    def value(self, t_s: float) -> float:
        """The rate in force at ``t_s``."""
        return self.rates[max(bisect.bisect_right(self.at_s, t_s) - 1, 0)]

    def integral(self, t_s: float) -> float:
        """Bytes from 0 s to ``t_s`` (``t_s >= 0``)."""
        k = max(bisect.bisect_right(self.at_s, t_s) - 1, 0)
        return self.cumulative[k] + self.rates[k] * (t_s - self.at_s[k])

    def reached(self, total: float) -> float:
        """The first time the integral reaches ``total`` (infinity if it never does)."""
        k = bisect.bisect_left(self.cumulative, total)
        if k < len(self.cumulative) and self.cumulative[k] == total:
            return self.at_s[k]
        k -= 1  # total lies inside segment k (or past the last breakpoint)
        if self.rates[k] <= 0:
            return math.inf
        return self.at_s[k] + (total - self.cumulative[k]) / self.rates[k]


def _payload(trace: LinkTrace) -> _Rate:
    """The bottleneck's payload rate in bytes/s."""
    return _Rate(
        [e.at_s for e in trace.entries],
        [e.mbit * WIRE_EFFICIENCY * BYTES_PER_S_PER_MBIT for e in trace.entries],
    )


def _budget(trace: LinkTrace, max_budget_mbit: float) -> _Rate:
    """The oracle's budget in bytes/s."""
    return _Rate(
        [e.at_s for e in trace.entries],
        [
            min(e.mbit * WIRE_EFFICIENCY, max_budget_mbit) * BYTES_PER_S_PER_MBIT
            for e in trace.entries
        ],
    )


def _positive(value: float, field: str) -> float:
    return check_number(value, field=field, owner="oracle", minimum=0, exclusive_minimum=True)


def _max_queue(value: float) -> float:
    return check_number(value, field="max_queue_s", owner="oracle", minimum=0, finite=False)


def oracle_budget(trace: LinkTrace, t_s: float, *, max_budget_mbit: float) -> float:
    """The budget (Mbit/s) a perfect estimator gives at ``t_s``: the payload, at most the cap."""
    cap = _positive(max_budget_mbit, "max_budget_mbit")
    return min(trace.mbit_at(t_s) * WIRE_EFFICIENCY, cap)


def bottleneck_departures(
    trace: LinkTrace,
    frames: Sequence[tuple[float, int]],
    *,
    max_queue_s: float = DEFAULT_MAX_QUEUE_S,
) -> tuple[float | None, ...]:
    """When each frame ``(send_s, size_bytes)``, in send order, leaves the trace's FIFO.

    The link serves ``WIRE_EFFICIENCY`` of the trace's rate, exactly across its changes (a
    stretch at 0 holds the queue). None: lost, the frames ahead would leave more than
    ``max_queue_s`` after it was sent; infinity: it never leaves (the link stays down).
    """
    return _departures(_payload(trace), frames, _max_queue(max_queue_s))


def _departures(
    link: _Rate, frames: Sequence[tuple[float, int]], max_queue_s: float
) -> tuple[float | None, ...]:
    out: list[float | None] = []
    served = 0.0  # bytes the link has served when the last frame admitted leaves
    free_s = -math.inf  # when it leaves
    for send_s, size_bytes in frames:
        if free_s - send_s > max_queue_s:
            out.append(None)
            continue
        served = max(link.integral(send_s), served) + size_bytes
        free_s = link.reached(served)
        out.append(free_s)
    return tuple(out)


def _sends(
    budget: _Rate,
    *,
    robots: int,
    step_s: float,
    duration_s: float,
    reallocate_s: float,
    strategy: Strategy,
) -> list[tuple[float, int]]:
    """Every frame ``(send_s, size_bytes)`` the cameras send over the run, in send order."""
    cameras = fleet_cameras(robots)
    steps = fleet_steps(robots)
    allocations: dict[tuple[int, float], tuple[float, ...]] = {}
    last_s: list[float | None] = [None] * len(cameras)
    sends: list[tuple[float, int, int]] = []  # (send_s, camera, size_bytes)
    for tick in range(math.ceil(duration_s / reallocate_s - _EDGE)):
        start_s = tick * reallocate_s
        end_s = min(start_s + reallocate_s, duration_s)
        step = min(int(start_s / step_s + _EDGE), len(steps) - 1)
        budget_mbit = budget.value(start_s) / BYTES_PER_S_PER_MBIT
        key = (step, budget_mbit)
        if key not in allocations:
            allocations[key] = (
                fleet_allocation(
                    steps[step],
                    cameras,
                    link_mbit=budget_mbit,  # the whole budget is the link, fully usable
                    utilization=1.0,
                    strategy=strategy,
                )
                if budget_mbit > 0
                else (0.0,) * len(cameras)  # the link is down: nothing to send
            )
        for k, (camera, rate_hz) in enumerate(zip(cameras, allocations[key], strict=True)):
            if rate_hz <= 0:
                continue
            period_s = 1.0 / rate_hz
            previous = last_s[k]
            first = k * _PHASE_SPREAD_S / len(cameras) if previous is None else previous + period_s
            t_s = max(first, start_s)
            while t_s < end_s:
                sends.append((t_s, k, camera.size_bytes))
                last_s[k] = t_s
                t_s += period_s
    sends.sort()
    return [(t_s, size) for t_s, _, size in sends]


def _percentile_ms(latencies_s: npt.NDArray[np.float64], q: float) -> float | None:
    return float(np.percentile(latencies_s, q)) * _MS_PER_S if latencies_s.size else None


def simulate_oracle(
    trace: LinkTrace,
    *,
    robots: int = 2,
    step_s: float,
    max_budget_mbit: float,
    strategy: Strategy | str = Strategy.PAPER,
    reallocate_s: float = _REALLOCATE_S,
    max_queue_s: float = DEFAULT_MAX_QUEUE_S,
) -> OracleRun:
    """The teleoperation scenario's ten steps (``step_s`` each) with a perfect estimate.

    Every ``reallocate_s`` the allocation (``strategy``, on the step's events) is recomputed
    for ``oracle_budget`` at that moment; each camera sends its frames one period after the
    last at its current rate; all frames share the trace's bottleneck (``bottleneck_departures``).
    """
    step_s = _positive(step_s, "step_s")
    cap_mbit = _positive(max_budget_mbit, "max_budget_mbit")
    reallocate_s = check_number(
        reallocate_s,
        field="reallocate_s",
        owner="oracle",
        minimum=MIN_PERIOD_S,
        maximum=MAX_PERIOD_S,
    )
    return _simulate(
        trace,
        _budget(trace, cap_mbit),
        robots=robots,
        step_s=step_s,
        strategy=strategy,
        reallocate_s=reallocate_s,
        max_queue_s=max_queue_s,
    )


def simulate_fixed_budget(
    trace: LinkTrace,
    *,
    budget_mbit: float,
    robots: int = 2,
    step_s: float,
    strategy: Strategy | str = Strategy.PAPER,
    max_queue_s: float = DEFAULT_MAX_QUEUE_S,
) -> OracleRun:
    """As ``simulate_oracle``, on a budget that never moves.

    A design that cannot foresee the link sends into a fade what the oracle does not: runs over
    a range of fixed budgets draw what each share of the link costs in latency on that trace.
    """
    step_s = _positive(step_s, "step_s")
    budget_bps = _positive(budget_mbit, "budget_mbit") * BYTES_PER_S_PER_MBIT
    return _simulate(
        trace,
        _Rate([0.0], [budget_bps]),
        robots=robots,
        step_s=step_s,
        strategy=strategy,
        reallocate_s=_REALLOCATE_S,  # the steps' events still move the allocation
        max_queue_s=max_queue_s,
    )


def _simulate(
    trace: LinkTrace,
    budget: _Rate,
    *,
    robots: int,
    step_s: float,
    strategy: Strategy | str,
    reallocate_s: float,
    max_queue_s: float,
) -> OracleRun:
    max_queue_s = _max_queue(max_queue_s)
    try:
        chosen = Strategy(strategy)
    except ValueError:
        names = ", ".join(s.value for s in Strategy)
        raise SpecError(f"oracle: strategy={strategy!r} is not one of: {names}") from None
    duration_s = len(fleet_steps(robots)) * step_s
    link = _payload(trace)
    sends = _sends(
        budget,
        robots=robots,
        step_s=step_s,
        duration_s=duration_s,
        reallocate_s=reallocate_s,
        strategy=chosen,
    )
    departures = _departures(link, sends, max_queue_s)
    send_s = np.array([t for t, _ in sends], dtype=float)
    size_bytes = np.array([size for _, size in sends], dtype=np.int64)
    lost = np.array([d is None for d in departures], dtype=bool)
    leave_s = np.array([math.inf if d is None else d for d in departures], dtype=float)
    delivered = ~lost & (leave_s <= duration_s)

    count = max(math.ceil(duration_s / WINDOW_S - _EDGE), 1)
    bins = np.minimum(np.floor(leave_s[delivered] / WINDOW_S).astype(np.int64), count - 1)
    goodput_bytes = np.bincount(bins, weights=size_bytes[delivered], minlength=count)
    windows = []
    for w in range(count):
        start_s, end_s = w * WINDOW_S, min((w + 1) * WINDOW_S, duration_s)
        width_mbit = (end_s - start_s) * BYTES_PER_S_PER_MBIT
        windows.append(
            OracleWindow(
                t_s=start_s,
                goodput_mbit=float(goodput_bytes[w]) / width_mbit,
                capacity_mbit=(link.integral(end_s) - link.integral(start_s)) / width_mbit,
                budget_mbit=(budget.integral(end_s) - budget.integral(start_s)) / width_mbit,
            )
        )
    latencies_s = leave_s[delivered] - send_s[delivered]
    return OracleRun(
        duration_s=duration_s,
        frames_sent=len(sends),
        frames_delivered=int(delivered.sum()),
        frames_lost=int(lost.sum()),
        sent_bytes=int(size_bytes.sum()),
        delivered_bytes=int(size_bytes[delivered].sum()),
        capacity_payload_bytes=(
            trace.megabits(0.0, duration_s) * WIRE_EFFICIENCY * BYTES_PER_S_PER_MBIT
        ),
        budget_bytes=budget.integral(duration_s),
        latency_p50_ms=_percentile_ms(latencies_s, 50),
        latency_p95_ms=_percentile_ms(latencies_s, 95),
        latency_p99_ms=_percentile_ms(latencies_s, 99),
        windows=tuple(windows),
    )
