"""The managed publisher (the paper's DBMPublisher).

Every message goes to ``[topic]`` for local consumers (only when someone subscribes there) and,
throttled to the allocated rate, to ``[topic]/optimized`` for remote ones. The allocated rate is
pushed by the optimizer through ``[topic]/dbm/frequency/current_value``; the publisher applies it,
acknowledges it in ``[topic]/dbm/frequency/applied_value`` and never polls. A new channel sends
nothing on ``[topic]/optimized`` until its first allocation, which comes once the optimizer knows
its size and has made room for it (bytes nobody allocated would break the budget on the wire);
if none comes within ``failsafe_periods`` periods it runs at its minimum. Hearing neither an
allocation nor the optimizer's heartbeat (``/dbm/round``) for ``failsafe_periods`` optimisation
periods sends it back to its minimum (fail-safe), and the next one takes over again.

Link outage: once it has heard the estimator's beacon (``/dbm/link``), a publisher holds only
its newest message, sending nothing on ``[topic]/optimized``, while the beacons stop (a link
down both ways) or say outage. Meanwhile the channels of the beacon's release order take turns,
one ``PROBE_INTERVAL_S`` each, to probe with their newest message (so an idle or departed
channel cannot keep the link from being found), each through its rate limiter at most at its
own rate. When the link is back it sends the newest message at its place in the release order
(on the next beacon or ``publish``, whichever comes first) and goes on at its rate, with at most
one message's credit: the outage's time is not banked into a burst. What it sent after the last
beacon it heard (before it knew, probes, the fail-safe's) sat in the dead link's buffer: such
a channel releases only once the estimator says its frames arrive again (``HEARD_WAIT_S``), so
fresh frames do not queue behind that backlog, and the release owes it (up to
``OWED_WINDOW_S`` of its rate).

The hold can only be safer than the fail-safe, never worse: it lasts at most ``HOLD_MAX_S``,
after which the channel runs at its minimum (as without an allocation) until a beacon says the
link is back, so a dead estimator or a lost beacon cannot silence it for good. A channel still
waiting for its first allocation sends nothing during or after a hold, and nothing in a beacon
can raise a rate: probes and releases spend the same credit as every other message.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping

from dbml.core.errors import TransportError
from dbml.core.spec import ChannelSpec, check_number
from dbml.runtime import names
from dbml.runtime.estimator import LINK_TOPIC, LinkBeacon
from dbml.runtime.metadata import pack_meta
from dbml.runtime.params import ParamView
from dbml.runtime.qos import TransportQos, explicit_qos, map_priority
from dbml.runtime.rate import Rate, RateLimiter
from dbml.transports.base import (
    Closer,
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
    "SIZE_CHANGE",
    "ManagedPublisher",
]

log = logging.getLogger("dbml.publisher")

SIZE_CHANGE = 0.10
"""Relative change of message size that is worth telling the optimizer about."""
FAILSAFE_PERIODS = 3.0
"""Optimisation periods without an allocation before a publisher falls back to its minimum."""
LINK_SILENCE_S = 0.3
"""No estimator beacon (sent every 0.1 s) for this long: the link is down, hold."""
STALE_RESET_S = 1.0
"""Beacons that all look stale for this long mean a new clock offset, not a buffered backlog."""
PROBE_INTERVAL_S = 0.5
"""In an outage one channel sends its newest message this often, to find the link back; the
channels of the release order take turns (the others hold until the estimator sees a frame)."""
PROBE_RATE_HZ = 1 / PROBE_INTERVAL_S
"""The most a channel probes at; never above its own rate in force."""
HEARD_WAIT_S = 1.0
"""After an outage, a channel that sent into the dead link waits until the estimator says its
frames arrive again (``LinkBeacon.heard``), at most this long after the link is back."""
OWED_WINDOW_S = 1.0
"""A release owes the frames the channel sent since the last beacon it heard, up to this long
at its rate: TCP still holds them from before the outage and delivers them when the link
returns, so the backlog and the release share one window's budget instead of adding up."""
HOLD_MAX_S = 5.0
"""The longest a hold lasts (seconds): then the channel runs at its fail-safe minimum until a
beacon says the link is back. A hold is a refinement of the fail-safe, never a stop."""
BEACON_WINDOW = 50
"""Beacons (5 s of them) whose quickest transit is the yardstick of a stale or early one. The
minimum ages, so neither clock drift nor one odd stamp sets it for good; silence does not age
it, so the backlog buffered through an outage is still judged against the time before it."""


class ManagedPublisher:
    """Publish on ``topic`` at the rate the optimizer allocates, within its declared bounds.

    ``publish(payload)`` drops what exceeds the rate; ``rate.sleep()`` paces a sensor loop so it
    does not even capture what would be dropped. Call ``publish`` from one thread; allocations
    arrive on the transport's thread. The rate in force is derived in one place,
    ``current_rate_hz()``: the last allocation while it is fresh, else the minimum (before the
    first allocation, and in fail-safe once ``failsafe_periods`` periods pass without one). A
    pushed rate above the declared maximum is clamped to it, and a size written by anyone else is
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
    ) -> None:
        names.check_channel(topic)
        # Validates the bounds with the same rules and messages as the allocation core.
        ChannelSpec(topic, min_rate_hz, max_rate_hz, 1.0, 0.0 if priority is None else priority)
        check_number(failsafe_periods, field="failsafe_periods", minimum=0, exclusive_minimum=True)
        self.topic = topic
        self.min_rate_hz = float(min_rate_hz)
        self.max_rate_hz = float(max_rate_hz)
        self._transport = transport
        self._now = transport.now
        self._failsafe_periods = failsafe_periods
        self._wall_clock_ns = wall_clock_ns
        self._lock = threading.Lock()
        self._full_seq = 0
        self._optimized_seq = 0
        self._confirmed_seq = 0
        """The last message sent before a beacon said the link was up: later ones may sit in a
        dead link's buffer."""
        self._size_bytes = -1
        self._allocated_hz: float | None = None
        self._last_heard = transport.now()
        self._failsafe_noted = False
        self._limiter = RateLimiter(self.min_rate_hz)
        self.rate = Rate(self.current_rate_hz, clock=transport.now)

        params = transport.params
        self._view = ParamView.of(params)
        self._period_s = self._view.dbm().period_s
        # Until then an allocation is expected; after it, fail-safe (also when none ever came).
        self._link_deadline = math.inf
        """Hold ``[topic]/optimized`` after this: beacon silence or an outage (inf: no beacon)."""
        self._hold_from: float | None = None
        """When the outage a beacon reported began (None: none reported)."""
        self._held: bytes | None = None
        self._release_at: float | None = None
        self._back_at: float | None = None
        """When a beacon first said the link is back in the hold in force."""
        self._probe_turn: tuple[int, int] | None = None
        """(this channel's place, how many) in the last outage beacon's release order."""
        self._probe_at = -math.inf
        self._transits: deque[float] = deque(maxlen=BEACON_WINDOW)
        """Recent beacons' transit plus the clock offset: the yardstick of a stale one."""
        self._odd_since: float | None = None
        self._beacon_warned = False
        self._hold_expired_noted = False
        self._closed = False
        self._set_deadline(self._last_heard + failsafe_periods * self._period_s)
        self._view_watch = self._view.watch(self._on_param)
        params.set(names.min_rate(topic), self.min_rate_hz)
        params.set(names.max_rate(topic), self.max_rate_hz)
        if priority is not None:  # otherwise keep what was set (the optimizer reads none as 0)
            params.set(names.priority(topic), float(priority))
        # A bridge announces the channel as its publisher but leaves [topic] to the original one.
        self._full: Publisher | None = None
        if republish_full:
            self._full = transport.declare_publisher(topic, Variant.FULL)
        # [topic]/optimized is what crosses the network: it travels in the channel's class.
        self._explicit_priority = transport_priority
        self._map_qos = transport.has_priorities and (
            map_transport_priority or transport_priority is not None
        )
        self._qos_lock = threading.Lock()
        self._qos = self._qos_target = self._wanted_qos()
        self._qos_generation = 0
        self._qos_stale = False
        """Set when the priority or size changed: the next ``publish`` looks at the class."""
        self._retired: Publisher | None = None
        self._optimized = self._declare_optimized(self._qos)
        self._handles: list[Handle] = [
            transport.graph.announce(Role.PUBLISHER, topic, Variant.FULL),
            self._view.watch(self._on_qos_param),
            Closer(self._close_retired),
        ]
        self._link_watch = transport.subscribe(LINK_TOPIC, self._on_link)

    # -- allocation ---------------------------------------------------------------------------

    def _on_param(self, name: str, value: ParamValue) -> None:
        """A valid period or allocation: apply it (and acknowledge an allocation)."""
        if name == names.PERIOD and isinstance(value, float):
            with self._lock:
                self._period_s = value
                self._set_deadline(self._last_heard + self._failsafe_periods * value)
            return
        if name == names.ROUND:
            # The optimizer's heartbeat: an unchanged allocation is not pushed again, and stands.
            with self._lock:
                if self._allocated_hz is not None:
                    self._heard_locked(self._allocated_hz)
            return
        if name == names.size(self.topic):
            if value != self._size_bytes and self._size_bytes > 0:
                # Someone else's size for our channel: the next publish re-asserts the real one
                # (on the publishing thread, never a blocking write on this callback thread).
                log.warning(
                    "%s: %s=%r is not the real size %d", self.topic, name, value, self._size_bytes
                )
                self._size_bytes = -1
            return
        if name != names.current_value(self.topic) or not isinstance(value, float):
            return
        rate = min(value, self.max_rate_hz)
        with self._lock:
            changed = rate != self._allocated_hz
            self._allocated_hz = rate
            self._heard_locked(rate)
        if changed:  # a non-blocking write: this may be the middleware's callback thread
            self._transport.params.set(names.applied(self.topic), rate)

    def _heard_locked(self, rate: float) -> None:
        """An allocation (or the heartbeat that keeps it) was heard now: it is in force."""
        self._last_heard = now = self._now()
        self._set_deadline(now + self._failsafe_periods * self._period_s)
        if self._failsafe_noted:
            log.warning("%s: allocation heard again; running at %.3f Hz", self.topic, rate)
            self._failsafe_noted = False
        self._limiter.set_rate(rate, now)  # from now, exactly: credit is the rate's integral

    def current_rate_hz(self) -> float:
        """The rate in force: the allocation while it is fresh, else the minimum."""
        return self._rate_at(self._now())

    def _set_deadline(self, failsafe_deadline: float) -> None:
        """``publish``'s one test covers both: a fresh allocation and a link that is up."""
        self._failsafe_deadline = failsafe_deadline
        self._deadline = min(failsafe_deadline, self._link_deadline)

    def _rate_at(self, now: float) -> float:
        if now <= self._failsafe_deadline:
            return self._allocated_hz or self.min_rate_hz
        self._note_failsafe(now)
        return self.min_rate_hz

    def _note_failsafe(self, now: float) -> None:
        """Log once that no allocation is heard (nothing else changes: the rate is derived)."""
        with self._lock:
            if self._failsafe_noted:
                return
            self._failsafe_noted = True
        log.warning(
            "%s: no allocation heard for %.1f s (%g periods); fail-safe: minimum %.3f Hz",
            self.topic,
            now - self._last_heard,
            self._failsafe_periods,
            self.min_rate_hz,
        )

    @property
    def failsafe(self) -> bool:
        """Whether no allocation was heard for ``failsafe_periods`` periods."""
        return self._now() > self._failsafe_deadline

    # -- link outage --------------------------------------------------------------------------

    def _hold_start(self, now: float) -> float | None:
        """When the hold in force began (None: the link is up, or no beacon was ever heard)."""
        if self._hold_from is not None:
            return self._hold_from
        return self._link_deadline if now > self._link_deadline else None

    @property
    def holding(self) -> bool:
        """Whether ``[topic]/optimized`` is held (down, not yet released, within ``HOLD_MAX_S``)."""
        now = self._now()
        start = self._hold_start(now)
        return start is not None and now - start <= HOLD_MAX_S

    def _warn_beacon(self, err: TransportError) -> None:
        """Report a malformed beacon once per channel (they come every tick), then quietly."""
        if self._beacon_warned:
            log.debug("%s: %s", self.topic, err)
            return
        self._beacon_warned = True
        log.warning("%s: %s (ignored; further ones are logged at debug level)", self.topic, err)

    def _in_line_locked(self, now: float, sent_s: float) -> bool:
        """Whether a beacon stamped ``sent_s`` speaks of now; lock held.

        A beacon much later than the recent quickest one sat in a buffer through an outage; one
        much earlier is stamped ahead (a forged or stepped clock): neither tells anything of the
        link now. If they all are out of line for ``STALE_RESET_S``, a clock stepped or the
        path changed: the yardstick starts anew.
        """
        transit = now - sent_s  # plus an unknown constant clock offset
        quickest = min(self._transits, default=transit)
        if abs(transit - quickest) > LINK_SILENCE_S:
            if self._odd_since is None:
                self._odd_since = now
            if now - self._odd_since <= STALE_RESET_S:
                return False
            self._transits.clear()
        self._odd_since = None
        self._transits.append(transit)
        return True

    def _rate_locked(self, now: float) -> float | None:
        """The rate in force without logging (None: waiting for a first allocation); lock held."""
        if now > self._failsafe_deadline:
            return self.min_rate_hz
        return self._allocated_hz

    def _release_locked(self, now: float, rate: float, *, send: bool) -> bool:
        """Leave the hold: True if a message is to ``send`` now and the limiter has a frame.

        The credit left is at most one frame (the message that goes now, or the next one), so
        the outage's time is never banked into a burst; a probe that just went leaves less.
        What was sent since the last beacon is owed (``OWED_WINDOW_S``): it arrives now too.
        """
        self._hold_from, self._release_at, self._probe_turn, self._held = None, None, None, None
        self._back_at = None
        self._link_deadline = now + LINK_SILENCE_S
        self._hold_expired_noted = False
        self._set_deadline(self._failsafe_deadline)
        owed = min(float(self._optimized_seq - self._confirmed_seq), rate * OWED_WINDOW_S)
        self._confirmed_seq = self._optimized_seq
        self._limiter.restart(rate, now, owed_frames=owed)
        return send and self._limiter.allow(now)

    def _on_link(self, sample: Sample) -> None:
        """The estimator's beacon: keep holding off, hold, or release after an outage."""
        try:
            beacon = LinkBeacon.decode(sample.payload)
        except TransportError as err:
            self._warn_beacon(err)
            return
        now = self._now()
        send: tuple[bytes, int, float] | None = None
        with self._lock:
            if self._closed or not self._in_line_locked(now, beacon.sent_s):
                return
            start = self._hold_start(now)
            if not beacon.up:
                # Repeated outage beacons do not extend the hold: it began once.
                self._hold_from = now if start is None else start
                self._link_deadline, self._release_at, self._back_at = -math.inf, None, None
                self._probe_turn = _turn(beacon.release_s, self.topic)
            elif start is None:
                self._link_deadline = now + LINK_SILENCE_S
                self._confirmed_seq = self._optimized_seq
            else:  # back: go at our place in the release order, once our backlog is through
                if self._back_at is None:
                    self._back_at = now
                if self._release_at is None and self._clear_locked(now, beacon.heard):
                    self._release_at = now + beacon.release_s.get(self.topic, 0.0)
                if self._release_at is not None and now >= self._release_at:
                    rate, held = self._rate_locked(now), self._held
                    # A slow source may not publish again soon: its held message goes now,
                    # unless the channel still waits for a first allocation.
                    sending = held is not None and rate is not None
                    went = self._release_locked(now, rate or self.min_rate_hz, send=sending)
                    if went and held is not None and rate is not None:
                        self._optimized_seq += 1
                        send = (held, self._optimized_seq, rate)
            self._set_deadline(self._failsafe_deadline)
        if send is not None:  # the middleware's put, never under the lock
            payload, seq, rate = send
            self._optimized.put(payload, attachment=pack_meta(seq, self._wall_clock_ns(), rate))

    def _clear_locked(self, now: float, heard: frozenset[str] | None) -> bool:
        """Whether nothing we sent is still stuck in the link (see ``HEARD_WAIT_S``); lock held."""
        if self._optimized_seq == self._confirmed_seq or heard is None or self.topic in heard:
            return True
        return self._back_at is not None and now - self._back_at >= HEARD_WAIT_S

    def _gate_locked(self, now: float, rate: float, payload: bytes) -> tuple[bool, bool]:
        """Whether ``payload`` goes without a steady allocation, and whether a hold just expired.

        Not held: the first-allocation and fail-safe rules. Held: probe at our turn, release
        at our place, else keep the newest message; past ``HOLD_MAX_S``, the fail-safe minimum.
        Lock held.
        """
        start = self._hold_start(now)
        if start is None:
            return self._allow_unallocated(rate, now), False
        if now - start > HOLD_MAX_S:
            self._held = None
            expired, self._hold_expired_noted = not self._hold_expired_noted, True
            return self._allow_unallocated(min(rate, self.min_rate_hz), now), expired
        if self._allocated_hz is None and now <= self._failsafe_deadline:
            self._held = None  # never allocated: nothing of it may cross, now or at the release
            return False, False
        if self._release_at is not None:
            if now >= self._release_at:  # this newer message replaces the held one
                return self._release_locked(now, rate, send=True), False
        elif now >= self._probe_at and self._my_turn(now, start):
            probe_hz = min(rate, PROBE_RATE_HZ)
            if probe_hz != self._limiter.rate_hz:
                self._limiter.set_rate(probe_hz, now)
            if self._limiter.allow(now):
                self._probe_at, self._held = now + PROBE_INTERVAL_S, None
                return True, False
        self._held = payload
        return False, False

    def _my_turn(self, now: float, start: float) -> bool:
        """Whether this channel probes in the current ``PROBE_INTERVAL_S`` of the hold."""
        if self._probe_turn is None:
            return False  # no release order heard: the hold's bound is the way out
        place, count = self._probe_turn
        return int((now - start) / PROBE_INTERVAL_S) % count == place

    # -- transport class ----------------------------------------------------------------------

    @property
    def transport_qos(self) -> TransportQos | None:
        """The class ``[topic]/optimized`` travels in now (None: the middleware's default)."""
        with self._qos_lock:
            return self._qos

    def _wanted_qos(self) -> TransportQos | None:
        """The class the channel's priority and size call for (``dbml.runtime.qos``)."""
        if not self._map_qos:
            return None
        channel = self._view.channel(self.topic)
        size = int(channel.size_bytes) if channel.size_bytes else None
        if self._explicit_priority is not None:
            return explicit_qos(self._explicit_priority, size)
        return map_priority(channel.priority or 0.0, size)

    def _declare_optimized(self, qos: TransportQos | None) -> Publisher:
        if qos is None:
            return self._transport.declare_publisher(self.topic, Variant.OPTIMIZED)
        return self._transport.declare_publisher(
            self.topic, Variant.OPTIMIZED, priority=qos.priority, express=qos.express
        )

    def _on_qos_param(self, name: str, _value: ParamValue) -> None:
        # Often on the middleware's callback thread: the publishing thread re-declares.
        if self._map_qos and name in (names.priority(self.topic), names.size(self.topic)):
            self._qos_stale = True

    def update_transport_class(self) -> bool:
        """Re-declare ``[topic]/optimized`` if its priority or size now call for another class.

        A zenoh publisher's class is fixed at declaration, so a change of class (rare: a
        priority event, the first message's size) declares a new publisher and swaps it in. No
        lock is held across the middleware call; a racing change of class wins over an older
        one. The old publisher is undeclared at the next change (or ``close``), not at once: a
        ``publish`` that read it just before the swap may still be putting on it. Sequence
        numbers belong to this object, so the numbering goes on across the swap. True if the
        class changed.
        """
        self._qos_stale = False
        wanted = self._wanted_qos()
        with self._qos_lock:
            if wanted == self._qos_target:  # in force, or being declared
                return False
            self._qos_target = wanted
            self._qos_generation += 1
            if wanted == self._qos:  # back to the class in force: the one in flight is moot
                return False
            generation = self._qos_generation
        fresh = self._declare_optimized(wanted)
        with self._qos_lock:
            swapped = generation == self._qos_generation  # else a newer change wins
            if swapped:
                stale, self._retired = self._retired, self._optimized
                self._optimized, self._qos = fresh, wanted
            else:
                stale = fresh
        if stale is not None:
            stale.close()
        if swapped:
            log.info("%s: transport class now %s", self.topic, wanted)
        return swapped

    def _close_retired(self) -> None:
        with self._qos_lock:
            retired, self._retired = self._retired, None
        if retired is not None:
            retired.close()

    # -- publishing ---------------------------------------------------------------------------

    def _track_size(self, size: int) -> None:
        # The serialised message, as sent; metadata and protocol headers are the overhead that
        # /dbm/max_bandwidth_utilization < 1 reserves room for.
        known = self._size_bytes
        if known < 0 or abs(size - known) > SIZE_CHANGE * known:
            self._size_bytes = size
            self._transport.params.set(names.size(self.topic), size)
            with self._lock:
                if self._allocated_hz is None and not self._failsafe_noted:
                    # The optimizer can only make room once it knows the size: the wait for
                    # the first allocation counts from here, not from the constructor.
                    self._last_heard = now = self._now()
                    self._set_deadline(now + self._failsafe_periods * self._period_s)

    def publish(self, payload: bytes) -> bool:
        """Send ``payload``; True if it went to ``[topic]/optimized`` (within the rate).

        Each variant numbers its own messages, so a receiver's sequence gaps are losses, never
        the throttling.
        """
        now = self._now()
        allocated = self._allocated_hz
        if allocated is not None and now <= self._deadline:
            rate, steady = allocated, True  # the common case: the limiter runs at it already
        else:
            rate, steady = self._rate_at(now), False  # before a new size moves the deadline
        if len(payload) != self._size_bytes:
            self._track_size(len(payload))
        if self._qos_stale:
            self.update_transport_class()
        full = self._full
        if full is not None and full.has_subscribers:
            self._full_seq += 1
            full.put(payload, attachment=pack_meta(self._full_seq, self._wall_clock_ns(), rate))
        expired = False
        with self._lock:
            if steady:
                allowed = self._limiter.allow(now)
            else:
                allowed, expired = self._gate_locked(now, rate, payload)
            if allowed:  # numbered under the lock: a release may put from the beacon's thread
                self._optimized_seq += 1
                seq = self._optimized_seq
        if expired:
            log.warning(
                "%s: held for %.1f s without word of the link; fail-safe: minimum %.3f Hz",
                self.topic,
                HOLD_MAX_S,
                self.min_rate_hz,
            )
        if not allowed:
            return False
        self._optimized.put(payload, attachment=pack_meta(seq, self._wall_clock_ns(), rate))
        return True

    def _allow_unallocated(self, rate: float, now: float) -> bool:
        """Before the first allocation, or without a fresh one (fail-safe); lock held.

        A new channel waits for its first allocation (bounded by the fail-safe deadline). Its
        credit is spent meanwhile, so the first allocation does not open with a burst.
        """
        waiting = self._allocated_hz is None and now <= self._failsafe_deadline
        if rate != self._limiter.rate_hz:  # fail-safe (an allocation applies on arrival)
            self._limiter.set_rate(rate, now)
        return self._limiter.allow(now) and not waiting

    def close(self) -> None:
        """Withdraw from the graph and undeclare both publishers.

        The beacon's subscription goes first: a release it would trigger puts on the
        publishers undeclared below.
        """
        self._link_watch.close()
        with self._lock:
            self._closed = True
        for handle in self._handles:
            handle.close()
        self._handles.clear()
        self._view_watch.close()
        if self._full is not None:
            self._full.close()
        self._optimized.close()


def _turn(release_s: Mapping[str, float], topic: str) -> tuple[int, int] | None:
    """``topic``'s place in a release order and its length (None: not in it)."""
    if topic not in release_s:
        return None
    order = sorted(release_s, key=lambda t: (release_s[t], t))
    return order.index(topic), len(order)
