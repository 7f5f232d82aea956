"""The managed publisher (the paper's DBMPublisher).

Every message goes to ``[topic]`` for local consumers (only when someone subscribes there) and,
throttled to the allocated rate, to ``[topic]/optimized`` for remote ones. The allocated rate is
pushed by the optimizer through ``[topic]/dbm/frequency/current_value``; the publisher applies it,
acknowledges it in ``[topic]/dbm/frequency/applied_value`` and never polls. A new channel sends
nothing on ``[topic]/optimized`` until its first allocation, which comes once the optimizer knows
its size and has made room for it (bytes nobody allocated would break the budget on the wire);
if none comes within ``failsafe_periods`` periods it runs at its minimum. Hearing neither an
allocation nor the optimizer's heartbeat (``/dbm/round``) for ``failsafe_periods`` optimisation
periods sends it back to its minimum (fail-safe), and the next one takes over again. Once it has
heard the estimator's beacon (``LINK_TOPIC``) it holds ``[topic]/optimized`` through a link
outage and releases it in the beacon's order when the link is back (``dbml.runtime.outage``).
A ``std_msgs/Float64`` on ``[topic]/dbm/priority`` sets the channel's priority, over every
transport (``dbml.runtime.priority.PriorityTopic``): a bridge's channel too.

The publisher composes four small state machines, each with the clock passed in and tested on
its own: ``FailSafe`` (the allocation in force and its deadline), ``OutageGate`` (hold, probe
and release), ``QosSwitch`` (the transport class of ``[topic]/optimized``) and ``SizeTracker``
(the size the optimizer is told). It wires them to the transport: it hears its own channel's
parameters and dbml's global ones only (``ParamView.watch_channel``, ``watch_dbm``), changes
their state under one lock, and makes every middleware call and every log outside it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable

from dbml.core.errors import TransportError
from dbml.core.spec import MAX_RATE_HZ, ChannelSpec, check_number
from dbml.protocol import keys, names
from dbml.protocol.ladders import Encoding, parse_rung_label
from dbml.protocol.messages import LinkBeacon
from dbml.protocol.metadata import pack_meta
from dbml.runtime.failsafe import FAILSAFE_PERIODS, FailSafe
from dbml.runtime.outage import (
    BEACON_WINDOW,
    HEARD_WAIT_S,
    HOLD_MAX_S,
    LINK_SILENCE_S,
    OWED_WINDOW_S,
    PROBE_INTERVAL_S,
    Admission,
    OutageGate,
    Release,
)
from dbml.runtime.params import ParamView
from dbml.runtime.priority import PriorityTopic
from dbml.runtime.qos import QosSwitch, TransportQos, channel_qos
from dbml.runtime.rate import Rate, RateLimiter
from dbml.runtime.size import SIZE_CHANGE, SizeTracker
from dbml.transports.base import (
    Handle,
    ParamValue,
    Publisher,
    Role,
    Sample,
    Transport,
    TransportPriority,
    Variant,
)

__all__ = [
    "BEACON_WINDOW",
    "FAILSAFE_PERIODS",
    "HEARD_WAIT_S",
    "HOLD_MAX_S",
    "LINK_SILENCE_S",
    "OWED_WINDOW_S",
    "PROBE_INTERVAL_S",
    "SENT_CHANGE",
    "SENT_SPAN_PERIODS",
    "SENT_STALL_INTERVALS",
    "SENT_TIMES_KEPT",
    "SIZE_CHANGE",
    "ManagedPublisher",
    "silent_too_long",
    "worth_saying",
]

log = logging.getLogger("dbml.publisher")

_UNSTEADY = (0.0, -math.inf)
"""``ManagedPublisher._steady`` without an allocation: every ``publish`` takes the long way."""
SENT_CHANGE = 0.1
"""A sent rate this far (relative) from the one last said is said again: a steady channel
writes nothing, a driver that stops is said at the next heartbeat."""
SENT_STALL_INTERVALS = 2.0
"""A source silent this many of its mean intervals at a heartbeat is said to send nothing."""
SENT_TIMES_KEPT = 64
"""The sent rate is timed over at most this many of the latest messages (a 1-s span at 64 Hz):
a rate over whole intervals between messages needs their times, not only their count."""
SENT_SPAN_PERIODS = 0.9
"""The sent rate is measured over at least this much of the optimizer's period."""


def silent_too_long(silent_s: float, rate_hz: float, *, limit_hz: float) -> bool:
    """Whether a source silent for ``silent_s`` has stopped.

    Silent ``SENT_STALL_INTERVALS`` of its intervals at the slower of its rate and the limit's:
    a decrease is not a stop.
    """
    slowest = min(rate_hz, limit_hz)
    return slowest > 0 and silent_s > SENT_STALL_INTERVALS / slowest


def _span_s(period_s: float, limit_hz: float) -> float:
    """The shortest span a sent rate is measured over.

    ``SENT_SPAN_PERIODS`` of the optimizer's period, and ``SENT_STALL_INTERVALS`` of the limit's
    intervals: at 0.6 Hz, one frame in a 1-s span reads 1 Hz, and none reads a stop.
    """
    if limit_hz <= 0:
        return SENT_SPAN_PERIODS * period_s
    return max(SENT_SPAN_PERIODS * period_s, SENT_STALL_INTERVALS / limit_hz)


def worth_saying(said_hz: float | None, sent_hz: float) -> bool:
    """Whether ``sent_hz`` differs enough from what was last said (``SENT_CHANGE``, or a stop)."""
    if said_hz is None or (said_hz == 0) != (sent_hz == 0):
        return True
    return abs(sent_hz - said_hz) > SENT_CHANGE * max(said_hz, sent_hz)


class ManagedPublisher:
    """Publish on ``topic`` at the rate the optimizer allocates, within its declared bounds.

    ``publish(payload)`` drops what exceeds the rate; ``rate.sleep()`` paces a sensor loop so it
    does not even capture what would be dropped. Call ``publish`` from one thread; allocations
    arrive on the transport's thread. The rate in force is derived in one place,
    ``FailSafe.rate_hz`` (``current_rate_hz()``; the loop's pace and each message's stamped
    rate): the last allocation while it is fresh, else the minimum (before the first
    allocation, and in fail-safe once ``failsafe_periods`` periods pass without one). The rate
    ``[topic]/optimized``'s limiter runs at is that rate capped by the outage gate
    (``OutageGate.cap_hz``: the probe rate for a probe, the minimum once a hold outlasted its
    bound), derived in ``_limit_hz`` alone and applied in ``_apply_locked`` alone, from the
    instant of each event that may change it and before the limiter is asked outside the
    steady state; the steady path asks it only while that rate is the allocation. A pushed
    rate above the declared maximum is clamped to it, and a size written by anyone else is
    overwritten by the real one: the publisher is the authority on its own bounds and size.
    ``republish_full=False`` (a bridge, whose ``[topic]`` has its own publisher) sends only
    ``[topic]/optimized``.
    """

    def __init__(
        self,
        transport: Transport,
        topic: str,
        *,
        min_rate_hz: float,
        max_rate_hz: float,
        priority: float | None = None,
        failsafe_periods: float = FAILSAFE_PERIODS,
        wall_clock_ns: Callable[[], int] = time.time_ns,
        republish_full: bool = True,
        transport_priority: TransportPriority | None = None,
        map_transport_priority: bool = True,
        variant: Variant = Variant.OPTIMIZED,
        encoding: Encoding | None = None,
    ) -> None:
        names.check_channel(topic)
        # Validates the bounds with the same rules and messages as the allocation core.
        ChannelSpec(topic, min_rate_hz, max_rate_hz, 1.0, 0.0 if priority is None else priority)
        check_number(failsafe_periods, field="failsafe_periods", minimum=0, exclusive_minimum=True)
        if not variant.managed:
            raise ValueError(f"variant={variant.value!r}: the managed copy is not the full one")
        self.topic = topic
        self._variant = variant
        self._rung: tuple[Encoding, int | None] | None = (
            None if encoding is None else (encoding, None)
        )
        """The rung in force (a camera's) and the bytes its frame was counted at: the
        optimizer's last push, else the default (counted at nothing)."""
        self.min_rate_hz = float(min_rate_hz)
        self.max_rate_hz = float(max_rate_hz)
        self._transport = transport
        self._now = transport.now
        self._wall_clock_ns = wall_clock_ns
        self._lock = threading.Lock()
        """Guards the allocation, the gate, the limiter and ``[topic]/optimized``'s numbering."""
        self._full_seq = 0
        self._optimized_seq = 0
        self._view = ParamView.of(transport.params)
        self._allocation = FailSafe(
            min_rate_hz=self.min_rate_hz,
            max_rate_hz=self.max_rate_hz,
            now=transport.now(),
            failsafe_periods=failsafe_periods,
            period_s=self._view.dbm().period_s,
        )
        self._gate = OutageGate(topic, min_rate_hz=self.min_rate_hz)
        self._limiter = RateLimiter(self._limit_hz(transport.now()))
        self._sizes = SizeTracker()
        self._steady = _UNSTEADY
        """(rate, until): while the clock is not past ``until`` an allocation of ``rate`` is
        fresh and the link up, and ``publish`` asks nothing else (set under the lock)."""
        self._closed = False
        self._beacon_warned = False
        self._sent_mark: tuple[float, int] | None = None
        """(time, messages sent) at the last heartbeat: the sent rate is measured between two."""
        self._sent_times: deque[float] = deque(maxlen=SENT_TIMES_KEPT)
        """When the latest messages went on ``[topic]/optimized``."""
        self._sent_said: float | None = None
        self._sent_s = -math.inf
        """When the last message went on ``[topic]/optimized``."""
        # The loop keeps its own phase across rate changes: one push reaches every publisher at
        # once, and loops that all restarted from it would send their frames together.
        self.rate = Rate(self.current_rate_hz, clock=transport.now, keep_phase=True)
        # [topic]/optimized is what crosses the network: it travels in the channel's class.
        self._explicit_priority = transport_priority
        self._map_qos = transport.has_priorities and (
            map_transport_priority or transport_priority is not None
        )
        self._qos_stale = False
        """Set when the priority or size changed: the next ``publish`` looks at the class."""
        self._watches: list[Handle] = [
            self._view.watch_channel(topic, self._on_channel_param),
            self._view.watch_dbm(self._on_dbm_param),
        ]
        params = transport.params
        params.set(names.min_rate(topic), self.min_rate_hz)
        params.set(names.max_rate(topic), self.max_rate_hz)
        if priority is not None:  # otherwise keep what was set (the optimizer reads none as 0)
            params.set(names.priority(topic), float(priority))
        # A bridge announces the channel as its publisher but leaves [topic] to the original one.
        self._full: Publisher | None = None
        if republish_full:
            self._full = transport.declare_publisher(topic, Variant.FULL)
        self._qos_stale = False  # our own priority write: the class below already has it
        self._switch = QosSwitch(self._declare_optimized, self._wanted_qos())
        self._announcement = transport.graph.announce(Role.PUBLISHER, topic, Variant.FULL)
        self._link_watch = transport.subscribe(keys.LINK_TOPIC, self._on_link)
        # A Float64 on [topic]/dbm/priority sets the priority, whoever publishes it.
        self._priority_topic = PriorityTopic(transport, topic)

    # -- allocation and fail-safe -------------------------------------------------------------

    def _on_channel_param(self, field: str, value: ParamValue) -> None:
        """A valid value of one of our channel's parameters (on the store's thread)."""
        if field == names.CURRENT_FIELD:
            if isinstance(value, float):
                self._on_allocation(value)
            return
        if field == names.ENCODING_FIELD:
            if isinstance(value, str) and self._rung is not None:
                self._on_encoding(value)
            return
        if field == names.SIZE_FIELD:
            real = self._sizes.dispute(value)
            if real is not None:
                # Someone else's size for our channel: the next publish re-asserts the real one
                # (on the publishing thread, never a blocking write on this callback thread).
                log.warning(
                    "%s: %s=%r is not the real size %d",
                    self.topic,
                    names.size(self.topic),
                    value,
                    real,
                )
        elif field != names.PRIORITY_FIELD:
            return
        if self._map_qos:  # often the middleware's callback thread: the publisher re-declares
            self._qos_stale = True

    def _on_allocation(self, value: float) -> None:
        """Apply a pushed rate and acknowledge it.

        Every push is acknowledged, also one that changes nothing: the optimizer pushes again
        what was not acknowledged (a push or its acknowledgement lost to a route not yet up).
        """
        allocation = self._allocation
        with self._lock:
            recovered = allocation.lapse_noted
            now = self._now()
            rate = allocation.allocate(value, now)
            self._apply_locked(now)
        if recovered:
            self._log_recovery(rate)
        # A non-blocking write: this may be the middleware's callback thread.
        self._transport.params.set(names.applied(self.topic), rate)

    def _on_encoding(self, label: str) -> None:
        """Apply a pushed rung (the view checked it) and acknowledge it, as a rate is."""
        self._rung = parse_rung_label(label)  # one reference swapped: read without a lock
        self._transport.params.set(names.encoding_applied(self.topic), label)

    @property
    def encoding(self) -> Encoding | None:
        """The rung in force, ``(scale, jpeg_quality)``: a camera's (None for other channels)."""
        rung = self._rung
        return None if rung is None else rung[0]

    @property
    def rung(self) -> tuple[Encoding, int | None] | None:
        """The rung in force and the bytes the allocation counted a frame of it at (one read)."""
        return self._rung

    def _on_dbm_param(self, name: str, value: ParamValue) -> None:
        """A new optimisation period, or the optimizer's heartbeat."""
        if name == names.PERIOD and isinstance(value, float):
            with self._lock:
                self._allocation.set_period(value)
                self._apply_locked(self._now())
        elif name == names.ROUND:
            # The optimizer's heartbeat: an unchanged allocation is not pushed again, and stands.
            allocation = self._allocation
            with self._lock:
                recovered = allocation.lapse_noted
                now = self._now()
                rate = allocation.heartbeat(now)
                self._apply_locked(now)
            if recovered and rate is not None:
                self._log_recovery(rate)
            self._say_sent(now)

    def _say_sent(self, now: float) -> None:
        """At a heartbeat: the rate sent, written if it moved by ``SENT_CHANGE`` or stopped.

        Measured over at least ``SENT_SPAN_PERIODS`` of the optimizer's period (a change of
        parameters brings extra rounds, milliseconds apart) and two of the limit's intervals.
        A source silent for more than ``SENT_STALL_INTERVALS`` of its intervals
        (``silent_too_long``) has stopped: 0 at once, at any heartbeat.
        """
        with self._lock:
            sent, last_s = self._optimized_seq, self._sent_s
            times = tuple(self._sent_times)
            period_s = self._allocation.period_s
            limit_hz = self._limiter.rate_hz

        def stalled(rate_hz: float) -> bool:
            return silent_too_long(now - last_s, rate_hz, limit_hz=limit_hz)

        said = self._sent_said
        mark = self._sent_mark
        if said is not None and said > 0 and stalled(said):
            rate = 0.0  # (said at once, unless ``say_if_stopped`` said it already)
        elif mark is None or now - mark[0] < _span_s(period_s, limit_hz):
            if mark is None:
                self._sent_mark = (now, sent)
            return
        else:
            frames = sent - mark[1]
            if frames == 0 and said is not None and said > 0:
                # Silent, but not too long for the rate it said (above): a slow rate between two
                # frames (a cut to 0.6 Hz leaves 1-s spans empty), not a stop. The span goes on.
                return
            within = [t for t in times if t > mark[0]]
            if len(within) > 1 and within[-1] > within[0]:
                # Timed from its first frame in the span to its last, whole intervals only:
                # where the heartbeat falls between two frames does not count (4 Hz over a 1-s
                # span is 3, 4 or 5 frames by phase alone, and a steady fleet would rewrite its
                # rates every period). It is the rate while it ran.
                rate = alive_hz = (len(within) - 1) / (within[-1] - within[0])
            else:
                rate = alive_hz = frames / (now - mark[0])
            rate = min(rate, MAX_RATE_HZ)
            if rate > 0 and stalled(alive_hz):
                rate = 0.0
        self._sent_mark = (now, sent)
        with self._lock:  # ``say_if_stopped`` may have said 0 meanwhile
            say = worth_saying(self._sent_said, rate)
            if say:
                self._sent_said = rate
        if say:
            self._transport.params.set(names.sent(self.topic), rate)  # non-blocking

    def say_if_stopped(self) -> None:
        """Say at once that nothing is sent, if the source has stopped (no heartbeat waited for).

        For a caller that sees its source idle (the bridge, waiting for a message): a source
        that said a rate and has been silent too long for it (``silent_too_long``) has
        stopped. Cheap when it has not; said once.
        """
        now = self._now()
        with self._lock:  # the heartbeat's thread says too: one decides at a time
            said = self._sent_said
            if said is None or said <= 0:
                return
            if not silent_too_long(now - self._sent_s, said, limit_hz=self._limiter.rate_hz):
                return
            self._sent_said = 0.0
        self._transport.params.set(names.sent(self.topic), 0.0)  # non-blocking

    def _log_recovery(self, rate: float) -> None:
        log.warning("%s: allocation heard again; running at %.3f Hz", self.topic, rate)

    def _limit_hz(self, now: float, *, probe: bool = False) -> float:
        """The rate the limiter runs at: the one derivation (lock held, or no thread yet).

        The rate in force (``FailSafe.rate_hz``: the fresh allocation, else the minimum, while
        awaiting a first allocation and in fail-safe alike) capped by the outage gate
        (``OutageGate.cap_hz``: ``PROBE_RATE_HZ`` for a ``probe``, the only message a hold lets
        through; the minimum once a hold outlasted ``HOLD_MAX_S``; else no cap). A released
        channel runs at the rate in force again.
        """
        return min(self._allocation.rate_hz(now), self._gate.cap_hz(now, probe=probe))

    def _apply_locked(
        self, now: float, release: Release | None = None, *, probe: bool = False
    ) -> None:
        """Run the limiter at ``_limit_hz(now)`` and derive ``_steady``; lock held.

        The one place the limiter's rate changes: after each event that may change the limit
        (an allocation, a heartbeat, a new period, a known size, a beacon) and before the
        limiter is asked outside the steady state. The rate applies from ``now``, so credit is
        the integral of the rates in force (a change seen late, at a look, earns at the lower
        of the two since the last look). A ``release`` restarts the limiter: at most one frame
        kept, less what it owes.
        """
        limit_hz = self._limit_hz(now, probe=probe)
        if release is None:
            self._limiter.set_rate(limit_hz, now)
        else:
            self._limiter.restart(limit_hz, now, owed_frames=release.owed_frames)
        # While the allocation is fresh and the link up the limit is the allocation: ``publish``
        # asks nothing else until the first of the two deadlines.
        fresh = self._allocation.in_force()
        if fresh is None:
            self._steady = _UNSTEADY
        else:
            rate, until = fresh
            self._steady = (rate, min(until, self._gate.link_deadline))

    def current_rate_hz(self) -> float:
        """The rate in force: the allocation while it is fresh, else the minimum."""
        return self._rate_in_force(self._now())

    def _rate_in_force(self, now: float) -> float:
        """``FailSafe.rate_hz``, and the first time a fail-safe is found, say so."""
        allocation = self._allocation
        with self._lock:
            rate = allocation.rate_hz(now)
            silent_s = allocation.note_lapse(now)
            waited_s = allocation.note_long_wait(now)
        if waited_s is not None:
            log.warning(
                "%s: no first allocation after %.1f s while the optimizer's rounds arrive; "
                "sending nothing on the optimized topic until it admits the channel",
                self.topic,
                waited_s,
            )
        if silent_s is not None:
            log.warning(
                "%s: no allocation heard for %.1f s (%g periods); fail-safe: minimum %.3f Hz",
                self.topic,
                silent_s,
                allocation.failsafe_periods,
                self.min_rate_hz,
            )
        return rate

    def wait_s(self) -> float:
        """Seconds until the limiter lets a message go at the rate it runs at (0: now).

        What a caller whose message was refused waits before offering it again (the bridge);
        a message refused for another reason (held through an outage, no first allocation
        yet) finds 0 here.
        """
        now = self._now()
        with self._lock:
            return self._limiter.wait_s(now)

    @property
    def failsafe(self) -> bool:
        """Whether no allocation was heard for ``failsafe_periods`` periods."""
        return self._allocation.lapsed(self._now())

    # -- link outage --------------------------------------------------------------------------

    @property
    def holding(self) -> bool:
        """Whether ``[topic]/optimized`` is held (down, not yet released, within ``HOLD_MAX_S``)."""
        now = self._now()
        with self._lock:
            return self._gate.holding(now)

    def _warn_beacon(self, err: TransportError) -> None:
        """Report a malformed beacon once per channel (they come every tick), then quietly."""
        if self._beacon_warned:
            log.debug("%s: %s", self.topic, err)
            return
        self._beacon_warned = True
        log.warning("%s: %s (ignored; further ones are logged at debug level)", self.topic, err)

    def _on_link(self, sample: Sample) -> None:
        """The estimator's beacon: keep holding off, hold, or release after an outage."""
        try:
            beacon = LinkBeacon.decode(sample.payload)
        except TransportError as err:
            self._warn_beacon(err)
            return
        now = self._now()
        allocation = self._allocation
        with self._lock:
            if self._closed or not self._gate.in_line(now, beacon.sent_s):
                return
            rate = allocation.rate_hz(now)
            release = self._gate.on_beacon(
                now,
                beacon,
                rate_hz=rate,
                waiting=allocation.waiting(now),
                sent_seq=self._optimized_seq,
            )
            self._apply_locked(now, release)
            held = None if release is None else release.message
            if held is None or not self._limiter.allow(now):
                return
            seq = self._number_locked(now)
        # A slow source may not publish again soon: the held message goes now, outside the lock.
        self._switch.publisher.put(held, attachment=pack_meta(seq, self._wall_clock_ns(), rate))

    def _admit_locked(self, now: float, rate: float, payload: bytes) -> tuple[bool, bool]:
        """Whether ``payload`` goes without a fresh allocation or a link known up; lock held.

        The gate says what to do, the limiter (at ``_limit_hz``) whether a frame is left. A
        new channel waits for its first allocation (bounded by the fail-safe deadline), its
        credit spent meanwhile, so the first allocation does not open with a burst. The second
        value says a hold just outlasted ``HOLD_MAX_S``.
        """
        waiting = self._allocation.waiting(now)
        verdict = self._gate.admit(
            now, payload, rate_hz=rate, waiting=waiting, sent_seq=self._optimized_seq
        )
        if isinstance(verdict, Release):  # this newer message is the one released
            self._apply_locked(now, verdict)
            return self._limiter.allow(now), False
        if verdict is Admission.HOLD:
            return False, False
        probe = verdict is Admission.PROBE
        self._apply_locked(now, probe=probe)
        allowed = self._limiter.allow(now)
        if probe:
            if allowed:
                self._gate.probed(now)
            return allowed, False
        # Open, or past the hold's bound: the allocation's and the fail-safe's rules.
        return allowed and not waiting, verdict is Admission.EXPIRED

    def _number_locked(self, now: float) -> int:
        """The sequence number of a message on ``[topic]/optimized`` that goes at ``now``."""
        self._optimized_seq += 1
        self._sent_s = now
        self._sent_times.append(now)
        return self._optimized_seq

    # -- transport class ----------------------------------------------------------------------

    @property
    def optimized_publisher(self) -> Publisher:
        """The transport's publisher of ``[topic]/optimized`` in force (for its own statistics)."""
        return self._switch.publisher

    @property
    def transport_qos(self) -> TransportQos | None:
        """The class ``[topic]/optimized`` travels in now (None: the middleware's default)."""
        return self._switch.qos

    def _wanted_qos(self) -> TransportQos | None:
        """The class the channel's priority and size call for (``dbml.runtime.qos``)."""
        if not self._map_qos:
            return None
        channel = self._view.channel(self.topic)
        size = int(channel.size_bytes) if channel.size_bytes else None
        return channel_qos(channel.priority, size, self._explicit_priority)

    def _declare_optimized(self, qos: TransportQos | None) -> Publisher:
        if qos is None:
            return self._transport.declare_publisher(self.topic, self._variant)
        return self._transport.declare_publisher(
            self.topic, self._variant, priority=qos.priority, express=qos.express
        )

    def update_transport_class(self) -> bool:
        """Re-declare ``[topic]/optimized`` if its priority or size now call for another class.

        A zenoh publisher's class is fixed at declaration, so a change of class (rare: a
        priority event, the first message's size) declares a new publisher and swaps it in
        (``QosSwitch``): no lock is held across the middleware call, a racing change of class
        wins over an older one, and the old publisher is undeclared at the next change (or
        ``close``). Sequence numbers belong to this object, so the numbering goes on across the
        swap. True if the class changed.
        """
        self._qos_stale = False
        wanted = self._wanted_qos()
        swapped = self._switch.switch(wanted)
        if swapped:
            log.info("%s: transport class now %s", self.topic, wanted)
        return swapped

    # -- publishing ---------------------------------------------------------------------------

    def _track_size(self, size: int) -> None:
        """Tell the optimizer a new size; the wait for a first allocation counts from here."""
        if not self._sizes.observe(size):
            return
        self._transport.params.set(names.size(self.topic), size)
        with self._lock:
            now = self._now()
            self._allocation.size_known(now)
            self._apply_locked(now)

    def publish(
        self,
        payload: bytes | Callable[[], bytes],
        *,
        encode: Callable[[], bytes] | None = None,
        size_bytes: int | None = None,
        admit: Callable[[bytes, float], bool] | None = None,
    ) -> bool:
        """Send ``payload``; True if it went to ``[topic]/optimized`` (within the rate).

        Each variant numbers its own messages, so a receiver's sequence gaps are losses, never
        the throttling. A camera gives ``encode``: what its managed copy carries instead of
        ``payload`` (the frame at the rung in force), called only for a frame that goes; and
        ``size_bytes``, the size the optimizer is told (its frame at the default rung); its
        ``payload`` may be a callable, then called only when ``[topic]`` has a subscriber.
        ``admit``, asked of a managed copy the limiter let through at the allocated rate (given
        with it), may still refuse it (a camera's frame over the bytes it was counted at); the
        limiter's frame is spent all the same.
        """
        managed: bytes | None = None
        """What the managed copy carries: ``payload``, or ``encode()`` once it is needed."""
        if encode is None:
            if callable(payload):
                raise ValueError("a payload made on demand needs encode and size_bytes")
            managed = payload
        if size_bytes is None and managed is None:
            raise ValueError("a payload made on demand needs encode and size_bytes")
        now = self._now()
        rate, until = self._steady
        steady = now <= until  # the common case: the limiter runs at the allocation already
        if not steady:
            rate = self._rate_in_force(now)  # before a new size moves the deadline
        size = size_bytes if size_bytes is not None else len(managed or b"")
        if size != self._sizes.known_bytes:
            self._track_size(size)
        if self._qos_stale:
            self.update_transport_class()
        full = self._full
        if full is not None and full.has_subscribers:
            self._full_seq += 1
            whole = payload() if callable(payload) else payload
            full.put(whole, attachment=pack_meta(self._full_seq, self._wall_clock_ns(), rate))
        if not steady and managed is None and encode is not None:
            # The outage gate may hold this message and release it later: the managed copy's
            # own bytes, made outside the lock (off the common path: steady publishes skip it).
            managed = encode()
        expired = False
        if steady and admit is not None:
            # A frame the limiter lets go is made, then admitted by its bytes, then numbered:
            # one refused after it was made leaves no gap in the sequence.
            with self._lock:
                allowed = self._limiter.allow(now)
            if not allowed:
                return False
            if managed is None:
                assert encode is not None
                managed = encode()
            if not admit(managed, rate):
                return False
            with self._lock:
                seq = self._number_locked(now)
            self._switch.publisher.put(
                managed, attachment=pack_meta(seq, self._wall_clock_ns(), rate)
            )
            return True
        with self._lock:
            if steady:
                allowed = self._limiter.allow(now)
            else:
                assert managed is not None
                allowed, expired = self._admit_locked(now, rate, managed)
            if allowed:  # numbered under the lock: a release may put from the beacon's thread
                seq = self._number_locked(now)
        if expired:
            log.warning(
                "%s: held for %.1f s without word of the link; fail-safe: minimum %.3f Hz",
                self.topic,
                HOLD_MAX_S,
                self.min_rate_hz,
            )
        if not allowed:
            return False
        if managed is None:
            assert encode is not None
            managed = encode()
        self._switch.publisher.put(managed, attachment=pack_meta(seq, self._wall_clock_ns(), rate))
        return True

    def close(self) -> None:
        """Withdraw from the graph and undeclare both publishers.

        The beacon's subscription goes first: a release it would trigger puts on the
        publishers undeclared below.
        """
        self._link_watch.close()
        self._priority_topic.close()
        with self._lock:
            self._closed = True
        self._announcement.close()
        for watch in self._watches:
            watch.close()
        self._watches.clear()
        if self._full is not None:
            self._full.close()
        self._switch.close()
