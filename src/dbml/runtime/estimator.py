"""The bandwidth estimator as a node part: reception reports in, a budget for the optimizer out.

It listens to ``/dbm/reception`` (what managed subscribers actually receive), maps each
reporter's clock onto its own (the smallest report transit seen, so reporters on other machines
work too), runs :class:`~dbml.estimator.BandwidthEstimator` every ``interval_s`` (and at
once after a report with a frame that queued ``WAKE_QUEUE_S``), and publishes the estimate in
``/dbm/estimated_bandwidth_in_mbit`` with its state in ``/dbm/estimator_state`` (an
:class:`~dbml.protocol.messages.EstimatorState` as JSON: ``dbml monitor`` shows its text, the
testbed reads a cut's decision time from it). The cap is the configured budget,
``/dbm/max_bandwidth_in_mbit`` times ``/dbm/max_bandwidth_utilization``: the estimate never
exceeds it.

Every tick it also sends a small :class:`~dbml.protocol.messages.LinkBeacon` on
``LINK_TOPIC``: whether frames arrive (``up``) or the link is in an outage, and during and just
after one the order in which the channels' held messages go out when it ends (highest priority
first, each after the ones before it had time to cross at the budget). Publishers that heard a
beacon hold their newest message when the beacons stop (a link down both ways) or say outage.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from dbml.core.errors import TransportError
from dbml.core.spec import mbit_to_bytes_per_s
from dbml.estimator import (
    MAX_SAMPLES,
    MAX_STREAMS,
    Arrival,
    BandwidthEstimator,
    Estimate,
    EstimatorSettings,
    Phase,
)
from dbml.protocol import keys, names
from dbml.protocol.messages import (
    HEARD_MAX,
    HEARD_RECENT_MAX,
    RELEASE_MAX_CHANNELS,
    RELEASE_MAX_S,
    EstimatorState,
    Heard,
    LinkBeacon,
    ReceptionReport,
)
from dbml.runtime.params import ParamView
from dbml.runtime.reception import EARLY_FLUSH_QUEUE_S, REPORT_INTERVAL_S
from dbml.runtime.worker import PeriodicWorker
from dbml.transports.base import Role, Sample, Transport
from dbml.transports.overflow import Overflow, ThrottledLog

__all__ = [
    "ESTIMATE_INTERVAL_S",
    "MALFORMED_LOG_S",
    "MAX_REPORTERS",
    "OWED_WINDOW_S",
    "WAKE_GAP_S",
    "WAKE_QUEUE_S",
    "LinkEstimator",
    "release_offsets",
]

log = logging.getLogger("dbml.estimator")

_PUBLISH_CHANGE = 0.01
"""Publish the estimate when it moves by this fraction (or the phase changes)."""
ESTIMATE_INTERVAL_S = 0.1
"""How often the estimator judges the link."""
REPORT_LAG_S = REPORT_INTERVAL_S * 1.5
"""Frames arrive up to one report interval late: the estimator judges the window before."""
WAKE_QUEUE_S = EARLY_FLUSH_QUEUE_S
"""A reported frame that queued this long over its stream's least delay is judged at once,
not at the next tick: on the testbed's drop the cut was decided 65-75 ms after such a frame
arrived (waiting for the report, then for the tick). One frame of another stream ahead of
it explains less (61 ms for 84 KB at 11 Mbit/s), so a steady link does not wake it often."""
WAKE_GAP_S = ESTIMATE_INTERVAL_S / 4
"""Woken ticks are at least this far apart: a congested link's reports from many hosts
run the estimator at most this often."""
RELEASE_ORDER_S = 2.0
"""After an outage, beacons carry the release order this long (publishers may hear late)."""
OWED_WINDOW_S = 1.0
"""A release owes the frames of its channel that land in this window: those that arrived this
long before it and those still in the link (a beacon's ``heard`` says both)."""
MALFORMED_LOG_S = 10.0
"""A malformed reception report is logged at most once this often (with how many since)."""
MAX_REPORTERS = 1024
"""The most reporting hosts whose clock offsets are kept (a fleet has tens). A host name comes
from the network: a report from one more host evicts the one silent the longest, whose offset
is learnt again from its next report, so a flood of made-up names costs at most this much
memory. The table never shrinks otherwise: such a flood is logged once in the node's life."""


@dataclass(slots=True)
class _Arrivals:
    """One channel's arrivals, as a beacon's ``heard`` counts them."""

    newest_s: float
    newest_seq: int
    """The number of the frame reported last (a lower one than before: the publisher restarted)."""
    recent_s: deque[float]
    """When reports of its frames came, on the estimator's clock, newest last (at most
    ``HEARD_RECENT_MAX``, none older than ``OWED_WINDOW_S`` at the last one)."""

    def heard(self, now: float) -> Heard:
        recent = sum(1 for at in self.recent_s if at > now - OWED_WINDOW_S)
        return Heard(self.newest_seq, recent)


def _least(a: Heard, b: Heard) -> Heard:
    """What two hosts heard of one channel, as the one that heard the least."""
    return Heard(min(a.newest_seq, b.newest_seq), max(a.recent_frames, b.recent_frames))


def release_offsets(
    channels: Mapping[str, tuple[float, float]], budget_bytes_per_s: float
) -> dict[str, float]:
    """``{topic: (priority, size_bytes)}`` -> when each held message goes out after an outage.

    Highest priority first (ties: the larger message, whose normalised priority is higher,
    then the topic), each once the messages before it had time to cross at the budget, so the
    release itself never outruns the budget; none later than ``RELEASE_MAX_S`` (the ones that
    would be go together then, each at its own rate from there). At most
    ``RELEASE_MAX_CHANNELS`` are named (the highest priorities): a beacon names no more.
    """
    order = sorted(channels, key=lambda t: (-channels[t][0], -channels[t][1], t))
    del order[RELEASE_MAX_CHANNELS:]
    offsets, at = {}, 0.0
    for topic in order:
        offsets[topic] = min(at, RELEASE_MAX_S)
        at += channels[topic][1] / budget_bytes_per_s if budget_bytes_per_s > 0 else 0.0
    return offsets


class LinkEstimator:
    """Estimate the shared link from reception reports; ``budget_mbit`` feeds the optimizer.

    What the network fills is bounded, and a flood is logged once with a count (an
    ``Overflow`` each, told outside the lock): the reporting hosts (``MAX_REPORTERS``) and
    the channels each one heard (``HEARD_MAX``) here, the streams and frames in
    :class:`~dbml.estimator.BandwidthEstimator`.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        settings: EstimatorSettings | None = None,
        interval_s: float = ESTIMATE_INTERVAL_S,
        report_lag_s: float = REPORT_LAG_S,
        on_change: Callable[[], None] | None = None,
        wall_clock_s: Callable[[], float] = time.time,
    ) -> None:
        self._transport = transport
        self._wall_clock_s = wall_clock_s
        self._settings = settings
        self._report_lag_s = report_lag_s
        self.on_change = on_change
        """Called when the published estimate changes (the optimizer's ``poke``)."""
        self._lock = threading.Lock()
        self._estimator: BandwidthEstimator | None = None
        self._offsets: dict[str, float] = {}
        """Per reporting host, its clock's offset to ours; the longest silent first."""
        self._reporters_full = Overflow("reporting hosts", MAX_REPORTERS, log=log, evicts=True)
        self._malformed = ThrottledLog(MALFORMED_LOG_S, log=log)
        """Malformed reports come from the network, maybe as a flood: one line a while."""
        self._streams_full = Overflow("streams followed", MAX_STREAMS, log=log, evicts=True)
        self._samples_full = Overflow("frames kept", MAX_SAMPLES, log=log)
        self._told = (0, 0)
        """The estimator's ``streams_evicted`` and ``samples_refused`` handed on so far."""
        self._published: tuple[float, str] | None = None
        self._view = ParamView.of(transport.params)
        self._worker = PeriodicWorker(
            self.tick, interval_s=interval_s, name="dbml-estimator", log=log
        )
        # In the data's own class, on purpose: after an outage the "up" beacon then arrives
        # behind the frames still queued for the link, so publishers release after that
        # backlog, not on top of it (as control traffic it overtook the backlog: the release
        # exceeded the budget by 2.2 Mbit/s in 2 of 4 testbed runs, against 0.4-0.7).
        self._beacon = transport.declare_publisher(keys.LINK_TOPIC)
        self._order_until = -math.inf
        self._arrived: dict[tuple[str, str], _Arrivals] = {}
        """Per reporting host and live channel, its newest frames' arrivals, the one heard from
        longest ago first. At most ``HEARD_MAX``: one more evicts the oldest not vouched for
        (``_unvouched``), else the oldest; each tick forgets those no beacon can name any more
        (``_forget_unheard``)."""
        self._unvouched: OrderedDict[tuple[str, str], None] = OrderedDict()
        """Of those, the ones whose host the graph did not show subscribing to the channel when
        first heard (a plain ROS 2 node's, or a forger's), oldest first: evicted first, so a
        flood of reports under made-up hosts never evicts a real subscriber's channel."""
        self._live: frozenset[str] = frozenset()
        """The channels someone publishes, as the graph shows them: a report of any other is
        not an arrival of the link (a made-up channel's frames would hide an outage)."""
        self._listening: frozenset[tuple[str, str]] = frozenset()
        """(host, channel) of every subscription the graph shows."""
        self._arrivals_full = Overflow(
            "(host, channel) pairs heard", HEARD_MAX, log=log, evicts=True
        )
        self._silent_from = math.inf
        """The estimator's time when it last declared an outage: frames after it are back."""
        self._ticked_s = -math.inf
        """Our clock at the last tick: a wake comes at least ``WAKE_GAP_S`` after it."""
        self._cut: tuple[float, float] | None = None
        """The last cut's estimate and its wall-clock decision time: the hold states published
        while the estimate stays there carry that time."""
        self._graph_watch = transport.graph.watch(self._on_graph)
        self._on_graph()
        self._subscription = transport.subscribe(keys.RECEPTION_TOPIC, self._on_report)

    def cap_mbit(self) -> float | None:
        """The configured budget (bandwidth times utilization): the estimate's ceiling."""
        return self._view.dbm().configured_mbit

    def budget_mbit(self) -> float | None:
        """The current estimate, or None before the budget is configured."""
        with self._lock:
            return None if self._estimator is None else self._estimator.estimate_mbit

    def _on_graph(self) -> None:
        """The graph changed: which channels are live, who subscribes to them from where."""
        entries = self._transport.graph.entries()
        live = frozenset(e.topic for e in entries if e.role is Role.PUBLISHER)
        listening = frozenset((e.host, e.topic) for e in entries if e.role is Role.SUBSCRIBER)
        with self._lock:
            self._live, self._listening = live, listening

    def _on_report(self, sample: Sample) -> None:
        try:
            report = ReceptionReport.decode(sample.payload)
        except TransportError as err:
            self._malformed.warning("report", "ignoring a reception report: %s", err)
            return
        now = self._transport.now()
        evicted = refused = displaced = 0
        queued = 0.0
        with self._lock:
            known = self._offsets.pop(report.host, math.inf)
            full = len(self._offsets) >= MAX_REPORTERS  # a new host, with every place taken
            if full:
                del self._offsets[next(iter(self._offsets))]  # the one silent the longest
            # arrival on our clock = arrival on theirs + offset; transit >= 0 bounds the offset
            offset = min(known, now - report.now_s)
            self._offsets[report.host] = offset  # now the most recent
            estimator = self._estimator
            if estimator is not None:
                for frame in report.frames:
                    if frame.topic not in self._live:
                        continue  # no such channel (made up, or gone): not the link's
                    displaced += self._arrival(report.host, frame.topic, frame.seq, now)
                    queued = max(
                        queued,
                        estimator.observe(
                            Arrival(
                                stream=f"{report.host}{frame.topic}",
                                seq=frame.seq,
                                sent_s=frame.sent_ns / 1e9,
                                arrival_s=frame.arrival_s + offset,
                                size_bytes=frame.size_bytes,
                            )
                        ),
                    )
                told = self._told
                self._told = (estimator.streams_evicted, estimator.samples_refused)
                evicted, refused = self._told[0] - told[0], self._told[1] - told[1]
        if queued >= WAKE_QUEUE_S and now - self._ticked_s >= WAKE_GAP_S:
            self._worker.wake()  # a frame queued: judge now, a cut is due sooner than the tick
        if full:
            self._reporters_full.refuse()
        if displaced:
            self._arrivals_full.refuse(displaced)
        if evicted:
            self._streams_full.refuse(evicted)
        if refused:
            self._samples_full.refuse(refused)

    def _arrival(self, host: str, topic: str, seq: int, now: float) -> int:
        """Count a frame of ``topic`` numbered ``seq`` that ``host`` reported ``now``; lock held.

        A host reports its frames in the order they arrived, each channel's in the order they
        were sent: the last one reported is the newest, and a lower number than before means
        the publisher restarted. Returns 1 if it is a new channel of ``host`` while
        ``HEARD_MAX`` channels are, and it evicted the one heard from longest ago), else 0.
        """
        arrived, unvouched, key = self._arrived, self._unvouched, (host, topic)
        evicted = 0
        arrivals = arrived.pop(key, None)
        if arrivals is None:
            if len(arrived) >= HEARD_MAX:
                # the one heard from longest ago, of those no subscription vouches for first
                victim = next(iter(unvouched or arrived))
                del arrived[victim]
                unvouched.pop(victim, None)
                evicted = 1
            arrivals = _Arrivals(now, seq, deque(maxlen=HEARD_RECENT_MAX))
            if key not in self._listening:
                unvouched[key] = None
        arrived[key] = arrivals  # now the one heard last
        if key in unvouched:
            unvouched.move_to_end(key)
        arrivals.newest_s = max(arrivals.newest_s, now)
        arrivals.newest_seq = seq
        recent = arrivals.recent_s
        while recent and recent[0] <= now - OWED_WINDOW_S:
            recent.popleft()
        recent.append(now)
        return evicted

    def tick(self) -> Estimate | None:
        """One estimator update: every ``interval_s``, and soon after a queued frame.

        A report with a frame that queued ``WAKE_QUEUE_S`` wakes the thread at once.
        """
        cap = self.cap_mbit()
        if cap is None:
            return None
        with self._lock:
            self._ticked_s = self._transport.now()
            if self._estimator is None:
                self._estimator = BandwidthEstimator(max_mbit=cap, settings=self._settings)
            # frames arrive up to one report interval late: judge the window that is complete
            estimate = self._estimator.update(
                self._transport.now() - self._report_lag_s, max_mbit=cap
            )
            streams, samples = self._estimator.stream_count, self._estimator.sample_count
        self._streams_full.room(streams)  # an update forgets streams and frames gone quiet
        self._samples_full.room(samples)
        self._publish(estimate)
        self._send_beacon(estimate)
        self._arrivals_full.room(self._forget_unheard(self._transport.now()))
        return estimate

    def _forget_unheard(self, now: float) -> int:
        """Forget the channels no later beacon can name; how many are left.

        A beacon's ``heard`` names a channel heard since the outage began, while the release
        order is in force, and counts its arrivals of the last ``OWED_WINDOW_S``. A channel
        last heard before that window and, unless the order is in force, before the outage
        began, is in no later beacon: the next report of it counts from nothing, as it would.
        """
        forget_to = now - OWED_WINDOW_S
        if now <= self._order_until:  # a later outage tick keeps the order, and its start
            forget_to = min(forget_to, self._silent_from)
        with self._lock:
            arrived = self._arrived
            while arrived:
                first = next(iter(arrived))  # the one heard from longest ago
                if arrived[first].newest_s > forget_to:
                    break
                del arrived[first]
                self._unvouched.pop(first, None)
            return len(arrived)

    def _send_beacon(self, estimate: Estimate) -> None:
        """Tell publishers whether frames arrive (and, around an outage, the release order)."""
        down = estimate.phase is Phase.OUTAGE
        now = self._transport.now()
        heard: dict[str, Heard] | None = None
        if down:
            if now > self._order_until:  # a new outage: frames from now on are the link back
                self._silent_from = now
            self._order_until = now + RELEASE_ORDER_S
        elif now <= self._order_until:
            with self._lock:
                silent = self._silent_from
                heard = {}
                for (_, topic), arrivals in self._arrived.items():
                    if arrivals.newest_s > silent:
                        mine, other = arrivals.heard(now), heard.get(topic)
                        heard[topic] = mine if other is None else _least(mine, other)
        release: dict[str, float] = {}
        if now <= self._order_until:  # only around an outage: it reads every parameter
            channels = {
                topic: (params.priority, params.size_bytes)
                for topic, params in self._view.channels(self._view.topics()).items()
                if params.size_bytes
            }
            release = release_offsets(channels, mbit_to_bytes_per_s(estimate.estimate_mbit))
        self._beacon.put(LinkBeacon(not down, release, now, heard).encode())

    def _publish(self, estimate: Estimate) -> None:
        value, phase = estimate.estimate_mbit, estimate.phase.value
        last = self._published
        if (
            last is not None
            and last[1] == phase
            and abs(value - last[0]) <= _PUBLISH_CHANGE * last[0]
        ):
            return
        self._published = (value, phase)
        params = self._transport.params
        params.set(names.ESTIMATE, round(value, 4))
        decided: float | None = None
        if estimate.phase is Phase.DECREASE:
            decided = self._wall_clock_s()
            self._cut = (value, decided)
        elif estimate.phase is Phase.HOLD and self._cut is not None and self._cut[0] == value:
            # still the cut's estimate: a woken tick may follow the cut within milliseconds,
            # and a reader that polls would see only its hold, not when the cut was decided
            decided = self._cut[1]
        state = EstimatorState.of(estimate, decided_at_s=decided)
        params.set(names.ESTIMATOR_STATE, state.encode())
        if self.on_change is not None:
            self.on_change()

    @property
    def alive(self) -> bool:
        """False once its thread died (the command then exits non-zero)."""
        return self._worker.alive

    def start(self) -> LinkEstimator:
        """Judge the link every interval on a thread of its own."""
        self._worker.start()
        return self

    def close(self) -> None:
        """Stop and withdraw the estimate, so nobody reads a stale one."""
        self._worker.stop()
        self._subscription.close()
        self._graph_watch.close()
        self._beacon.close()
        if self._published is not None:
            self._transport.params.set(names.ESTIMATE, None)
            self._transport.params.set(names.ESTIMATOR_STATE, None)
