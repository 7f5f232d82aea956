"""The ``delivery-rate`` design (after BBR): the budget cruises at the link's rate and probes.

The budget cruises at the link's rate (the packet-pair rate measured at the last cut, raised by
probes the link carried); every ``cruise_s`` a round asks ``probe_gain`` more, each one carried
triples the next step, one that queues is drained for a round. A queue beyond one frame of
another stream, growing or standing, means the link is full: the budget drops below the link's
rate until what is queued has drained (down to ``drain_gain``), then cruises at that rate. The
queue is measured over each stream's least delay since the last cut: a slower link makes every
frame's own transmission longer, which is not a queue.

It reads, per stream that speaks for the link, its frames (their delays since the last cut,
their sizes) and their slope, the packet pairs and the delivery rate of the last rounds, and
the frames lost.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from dbml.estimator.base import (
    Arrival,
    Decision,
    Phase,
    Sample,
    SharedSettings,
    View,
    busy_rate_mbit,
    check_positive,
    check_shares,
    receive_rate_mbit,
)

__all__ = ["DeliveryRateDetector", "DeliveryRateSettings"]

_PROBE_GROWTH = 3.0
"""A probe the link carried makes the next one's step this much larger."""
_CUT_RATE_FLOOR = 0.5
"""A cut's link rate is at least this share of the last second's rate."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DeliveryRateSettings:
    """The ``delivery-rate`` design's gains and rounds; the defaults were tuned on the testbed."""

    probe_gain: float = 1.1
    """The budget in a probe round, as a share of the filtered rate."""
    startup_gain: float = 2.0
    """Each probe the link carried triples the next one's step, to this."""
    drain_gain: float = 0.5
    """The deepest cut, as a share of the link's rate, to drain a queue."""
    cruise_gain: float = 1.0
    """Between probes, the budget as a share of the filtered rate."""
    bw_window_s: float = 2.5
    """The delivery rate is the maximum over this much time."""
    round_s: float = 1.0
    """One round: a budget change acted on (``response_s``) and measured."""
    cruise_s: float = 2.0
    """Time at the filtered rate between probes."""
    queue_target_s: float = 0.05
    """Queueing beyond one other stream's frame above this means the link is full: the filter
    restarts from what was delivered, the budget drains the queue."""
    overuse_trend: float = 0.05
    """Seconds of queueing gained per second: a queue growing faster is growing."""
    drain_s: float = 1.0
    """A cut drains what is queued within this long (down to ``drain_gain``)."""

    def __post_init__(self) -> None:
        check_positive(
            "estimator",
            self,
            (
                "probe_gain",
                "startup_gain",
                "cruise_gain",
                "bw_window_s",
                "round_s",
                "cruise_s",
                "queue_target_s",
                "drain_s",
            ),
        )
        check_shares("estimator", self, ("drain_gain",))

    def detector(self, shared: SharedSettings) -> DeliveryRateDetector:
        """A fresh ``delivery-rate`` detector."""
        return DeliveryRateDetector(self, shared)


@dataclass(frozen=True, slots=True)
class _Queue:
    """One stream's queueing over its least delay since the last cut."""

    latest_s: float
    pair_s: float
    """The lesser of its last two frames': one frame's wait behind a burst is not a queue."""
    least_s: float
    """The least in the window: a standing queue."""
    trend: float
    size_bytes: int
    """Its largest frame in the window."""


class DeliveryRateDetector:
    """BBR's max-filtered delivery rate and probe cycle, bounded by a standing queue."""

    def __init__(self, settings: DeliveryRateSettings, shared: SharedSettings) -> None:
        self.settings = settings
        self._shared = shared
        self._frozen_until = -math.inf
        self._capacity_mbit: float | None = None
        self._bw: deque[tuple[float, float]] = deque()
        """(time, delivery rate in Mbit/s): the maximum over ``bw_window_s`` is the rate."""
        self._gain = 1.0
        self._round_until = -math.inf
        self._cruise_until = -math.inf
        self._probe_base_mbit = 0.0
        self._base_from = -math.inf
        """The last cut: queueing is over each stream's least delay since (the link's rate,
        and so each frame's own transmission time, may have changed)."""

    def observe(self, arrival: Arrival) -> None:
        """Nothing: it reads the streams' frames from the view."""

    def forget(self, stream: str | None) -> None:
        """Nothing: it keeps nothing per stream."""

    def decide(self, view: View) -> Decision:
        """Budget = gain x the most delivered lately; a queue beyond one frame resets it.

        The delivery rate (what arrived over ``round_s`` less the reaction) is max-filtered
        over ``bw_window_s`` while the budget cruises or probes (a drain's arrivals are the
        backlog, in bursts). Between probes the budget cruises at ``cruise_gain`` of the
        link's rate; every ``cruise_s`` a round asks ``probe_gain`` more, and if the link
        carried it (delivered more, queued nothing) the next round's step is three times
        larger, up to ``startup_gain`` (BBR's probing up); a probe whose large frames start to
        queue ends at once and a round at ``2 - probe_gain`` drains what it queued. A queue
        beyond what one frame of another stream explains, standing or growing, means the link
        is full: its rate is the packet-pair rate (at least half the last second's), and the
        budget drains what is queued (down to ``drain_gain`` of it), then cruises.
        """
        s, shared = self.settings, self._shared
        now = view.now_s
        estimate = view.estimate_mbit
        if view.settling:
            return Decision(Phase.HOLD, estimate)
        bw = self._bw
        while bw and bw[0][0] < now - s.bw_window_s:
            bw.popleft()
        used = view.received >= shared.probe_fraction * estimate
        reference = max(view.received, self._capacity_mbit or 0.0)
        short = [_short_queue(j.samples, j.window, self._base_from, j.slope) for j in view.judged]
        # a stream of small frames waits behind the large ones: only two in a row count
        largest = max((q.size_bytes for q in short), default=0)
        excess = [
            (
                (q.latest_s if 2 * q.size_bytes >= largest else q.pair_s) - wait,
                q.least_s - wait,
                q.trend,
            )
            for k, q in enumerate(short)
            for wait in (_other_frame_s(k, short, reference),)
        ]
        full = view.lost > 0 or any(
            least > s.queue_target_s or (latest > s.queue_target_s and slope > s.overuse_trend)
            for latest, least, slope in excess
        )
        if full and now >= self._frozen_until:
            busy = busy_rate_mbit(view.pairs(shared.window_s), s.queue_target_s / 2)
            # a burst of frames read together is not the link's rate: what arrived over the
            # last second bounds it from below. Only what arrived by ``now``: a node judges a
            # little in the past, and the frames reported since would count over a second that
            # ends before them (judged at once on a fresh report, the floor read 10.25 Mbit/s
            # of an 11-Mbit/s link just cut to 5, and the budget cruised over the new link)
            floor = receive_rate_mbit(
                [r for r in view.recent if r[0] <= now], now, shared.rate_window_s
            )
            rate = max(busy or 0.0, _CUT_RATE_FLOOR * floor) or view.cut_rate
            if rate > 0:
                # the queue grows by the overload until the cut acts: what the senders were
                # told over what the link delivers (the trend, from a few frames, lags it)
                overload = max([estimate / rate - 1.0, *(sl for *_, sl in excess)])
                latest = max((q for q, *_ in excess), default=0.0)
                backlog = max(0.0, latest + max(0.0, overload) * shared.response_s)
                share = max(s.drain_gain, 1.0 - backlog / s.drain_s)
                estimate = min(estimate, share * rate)
                drain_s = backlog / (1.0 - share) if share < 1 else 0.0
                self._frozen_until = now + shared.response_s + drain_s
                self._capacity_mbit = min(rate, self._capacity_mbit or rate)
                if busy is not None and busy > (self._capacity_mbit or 0.0):
                    self._capacity_mbit = busy
                bw.clear()
                self._gain = 0.0  # draining: cruise once it is done
                self._round_until = self._frozen_until
                self._base_from = now
            return Decision(Phase.DECREASE, estimate)
        delivered = receive_rate_mbit(
            view.recent, now, max(shared.window_s, s.round_s - shared.response_s)
        )
        if self._gain >= 1 and delivered > 0 and used and not full:
            bw.append((now, delivered))
        # a probe's queue shows first in the streams of large frames (a small frame's delay
        # is mostly the wait behind a large one): growing at all there ends the probe
        quiet = not any(
            q.latest_s > s.queue_target_s / 2 and q.trend > s.overuse_trend
            for q in short
            if 2 * q.size_bytes >= largest
        )
        if self._gain > 1 and not quiet:
            # the probe queues: the link has no more room; drain what it queued for a round
            self._gain = max(s.drain_gain, 2.0 - s.probe_gain)
            estimate = self._gain * self._probe_base_mbit
            self._round_until = self._frozen_until = now + s.round_s
            return Decision(Phase.HOLD, estimate)
        if now < self._round_until:
            return Decision(Phase.INCREASE if self._gain > 1 else Phase.HOLD, estimate)
        best = max((rate for _, rate in bw), default=0.0)
        capacity = self._capacity_mbit or best
        if self._gain > 1:
            # a probe round ended without a queue: did the link carry it (more arrived)? Then
            # ask more (start-up); else cruise at what the link is known to carry
            if best >= (1.0 + (self._gain - 1.0) / 2) * self._probe_base_mbit:
                self._capacity_mbit = capacity = max(capacity, min(best, estimate))
                if estimate < view.max_mbit:
                    # each probe carried triples the next one's step (BBR's probing up)
                    self._probe_base_mbit = estimate
                    self._gain = min(s.startup_gain, 1.0 + _PROBE_GROWTH * (self._gain - 1.0))
                    estimate *= self._gain
                    self._round_until = now + s.round_s
                    return Decision(Phase.INCREASE, estimate)
            self._gain = 0.0
        if self._gain == 1.0:
            if now >= self._cruise_until and used and estimate < view.max_mbit:
                self._probe_base_mbit = estimate
                self._gain = s.probe_gain
                estimate = self._gain * self._probe_base_mbit
                self._round_until = now + s.round_s
                return Decision(Phase.INCREASE, estimate)
            # cruising: the rate follows the link
            return Decision(Phase.INCREASE if used else Phase.HOLD, estimate)
        # after a drain: cruise at the link's rate
        self._gain = 1.0
        self._cruise_until = now + s.cruise_s
        if capacity > 0:
            estimate = s.cruise_gain * capacity
        return Decision(Phase.HOLD, estimate)


def _short_queue(
    samples: deque[Sample], mine: list[Sample], since_s: float, slope: float
) -> _Queue:
    """A stream's queueing over its least delay since ``since_s`` (the last cut).

    A frame's delay holds its own transmission, which grows when the link slows: a base from
    before the cut would read that as a standing queue for as long as it remembers the faster
    link. After the cut the queue drains, so the least delay since is the new link's.
    """
    recent = [d for t, d, _ in samples if t > since_s] or [samples[-1][1]]
    base = min(recent)
    latest = max(0.0, samples[-1][1] - base)
    pair = max(0.0, min(d for _, d, _ in list(samples)[-2:]) - base)
    offset = min(d for _, d, _ in samples) - base  # the queued values are over the long base
    least = max(0.0, min(q for _, q, _ in mine) + offset)
    return _Queue(latest, pair, least, slope, max(size for *_, size in mine))


def _other_frame_s(index: int, streams: list[_Queue], rate_mbit: float) -> float:
    """How long a frame may wait behind one frame of another stream: not a standing queue."""
    largest = max((q.size_bytes for k, q in enumerate(streams) if k != index), default=0)
    return largest * 8e-6 / rate_mbit if rate_mbit > 0 else 0.0
