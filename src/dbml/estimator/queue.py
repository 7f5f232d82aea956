"""The ``queue`` design (the first one, the default): a standing or rising queue is overuse.

Queueing delay above ``overuse_delay_s`` and rising, or above ``max_queue_delay_s``, or frames
lost (sequence gaps) is overuse; a cut to ``backoff`` of the packet-pair rate minus what drains
the queue within ``drain_s``, then a hold while the queue drains; an increase otherwise, slowly
near the capacity last measured, fast away from it. The default because the other designs'
probing costs frames after a drop on a drop-tail link (docs/estimator.md).

It reads, per stream that speaks for the link, its newest and least queueing and their slope,
the packet pairs of the last ``window_s``, and the frames lost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dbml.estimator.base import (
    Arrival,
    Decision,
    Judged,
    Phase,
    SharedSettings,
    View,
    busy_rate_mbit,
    check_positive,
    check_shares,
)

__all__ = ["QueueDetector", "QueueSettings", "increase"]


@dataclass(frozen=True, slots=True, kw_only=True)
class QueueSettings:
    """The ``queue`` design's thresholds and rates; the defaults were tuned on the testbed."""

    overuse_delay_s: float = 0.04
    """Queueing delay above this, while rising faster than ``overuse_trend``, is overuse."""
    overuse_trend: float = 0.05
    """Seconds of queueing delay gained per second."""
    max_queue_delay_s: float = 0.15
    """Queueing delay above this is overuse unless it is already falling."""
    backoff: float = 0.95
    """A cut is to this share of the packet-pair rate (less what drains the queue)."""
    drain_s: float = 1.0
    """A cut leaves room to drain the queue within this long."""
    slow_increase_per_s: float = 0.05
    fast_increase_per_s: float = 0.25
    near_band: tuple[float, float] = (0.8, 1.1)
    """Around the capacity last measured under overuse (as fractions), increase slowly."""

    def __post_init__(self) -> None:
        check_positive(
            "estimator",
            self,
            (
                "overuse_delay_s",
                "max_queue_delay_s",
                "drain_s",
                "slow_increase_per_s",
                "fast_increase_per_s",
            ),
        )
        check_shares("estimator", self, ("backoff",))

    def detector(self, shared: SharedSettings) -> QueueDetector:
        """A fresh ``queue`` detector."""
        return QueueDetector(self, shared)


class QueueDetector:
    """A standing or rising queue, a cut to the packet-pair rate."""

    def __init__(self, settings: QueueSettings, shared: SharedSettings) -> None:
        self.settings = settings
        self._shared = shared
        self._frozen_until = -math.inf
        """No new cut before this: what was sent before the last one is still arriving."""
        self._capacity_mbit: float | None = None
        """The link's rate measured at the last cut."""

    def observe(self, arrival: Arrival) -> None:
        """Nothing: it reads the streams' delays from the view."""

    def forget(self, stream: str | None) -> None:
        """Nothing: it keeps nothing per stream."""

    def decide(self, view: View) -> Decision:
        """Cut on overuse once a cut could have acted; hold while it drains; increase."""
        s, shared = self.settings, self._shared
        judged = view.judged
        estimate = view.estimate_mbit
        overuse = view.lost > 0 or any(
            (j.latest_s > s.overuse_delay_s and j.slope > s.overuse_trend)
            or (j.least_s > s.max_queue_delay_s and j.slope >= 0)
            for j in judged
        )
        draining = bool(judged) and all(j.slope < -s.overuse_trend for j in judged)
        if view.settling:
            return Decision(Phase.HOLD, estimate)  # the backlog of the outage drains
        if overuse and view.now_s >= self._frozen_until:
            # Frames still queued were sent before this decrease could act: one decrease, then
            # wait until what is sent after it has had time to arrive.
            capacity = (
                busy_rate_mbit(view.pairs(shared.window_s), s.overuse_delay_s / 2) or view.cut_rate
            )
            if capacity > 0:
                # The queue grows no faster than what is offered (the estimate at most) exceeds
                # what the link carries: a burst's slope (frames of two allocations at once, as
                # one replaces the other) does not go on until the cut acts.
                growth = max(0.0, estimate / capacity - 1.0)
                backlog = _backlog_s(judged, shared.response_s, max_slope=growth)
                self._capacity_mbit = capacity
                drain = backlog * capacity / s.drain_s
                target = max(s.backoff * capacity - drain, 0.5 * s.backoff * capacity)
                estimate = min(estimate, target)
                self._frozen_until = view.now_s + backlog + shared.response_s
            return Decision(Phase.DECREASE, estimate)
        if overuse or draining or view.now_s < self._frozen_until:
            return Decision(Phase.HOLD, estimate)  # still draining, or the cut not yet seen
        return increase(
            view,
            self._capacity_mbit,
            probe_fraction=shared.probe_fraction,
            slow_per_s=s.slow_increase_per_s,
            fast_per_s=s.fast_increase_per_s,
            near_band=s.near_band,
        )


def increase(
    view: View,
    capacity_mbit: float | None,
    *,
    probe_fraction: float,
    slow_per_s: float,
    fast_per_s: float,
    near_band: tuple[float, float],
) -> Decision:
    """Up, if the link is used: slowly near ``capacity_mbit`` (the last cut's), fast away."""
    estimate = view.estimate_mbit
    if view.received < probe_fraction * estimate:
        return Decision(Phase.HOLD, estimate)  # not used enough to tell whether more fits
    low, high = near_band
    near = capacity_mbit is not None and (low * capacity_mbit <= estimate <= high * capacity_mbit)
    rate = slow_per_s if near else fast_per_s
    return Decision(Phase.INCREASE, estimate * (1.0 + rate) ** view.dt_s)


def _backlog_s(judged: list[Judged], response_s: float, *, max_slope: float) -> float:
    """The queue by the time a decrease acts.

    It keeps growing until then, at most at ``max_slope`` (seconds of queueing a second).
    """
    return max(
        (
            j.latest_s + min(max(0.0, j.slope), max_slope) * (j.latest_s + response_s)
            for j in judged
        ),
        default=0.0,
    )
