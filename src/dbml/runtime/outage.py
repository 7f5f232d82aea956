"""The outage gate: what a managed publisher sends while the link is down, and how it resumes.

Once it has heard the estimator's beacon (``LINK_TOPIC``), a publisher holds only its newest
message, sending nothing on ``[topic]/optimized``, while the beacons stop (a link down both
ways) or say outage. Meanwhile the channels of the beacon's release order take turns, one
``PROBE_INTERVAL_S`` each, to probe with their newest message (so an idle or departed channel
cannot keep the link from being found), each through its rate limiter at most at its own rate.
When the link is back it sends the newest message at its place in the release order (on the
next beacon or ``publish``, whichever comes first) and goes on at its rate, with at most one
message's credit: the outage's time is not banked into a burst. What it sent after the last
beacon it heard (before it knew, probes, the fail-safe's) sat in the dead link's buffer: such
a channel releases only once the estimator says its frames arrive again (``HEARD_WAIT_S``), so
fresh frames do not queue behind that backlog, and the release owes what of it lands in the
release's window (``OWED_WINDOW_S``): the frames the estimator heard in the last second and
those sent after the newest it heard. What a session the outage closed dropped is not owed.

The hold can only be safer than the fail-safe, never worse: it lasts at most ``HOLD_MAX_S``,
after which the channel runs at its minimum (as without an allocation) until a beacon says the
link is back, so a dead estimator or a lost beacon cannot silence it for good. A channel still
waiting for its first allocation sends nothing during or after a hold, and nothing in a beacon
can raise a rate: probes and releases spend the same credit as every other message.

``OutageGate`` is that state machine alone: every call takes ``now`` and the facts it needs
(the rate in force, whether a first allocation is awaited, how many messages were sent), it
holds no rate limiter, starts no thread and sends nothing. It says what to do: go on as if no
outage happened (``Admission.OPEN``), hold, send a probe, release with what is owed
(``Release``); and it caps the rate the channel's limiter runs at (``cap_hz``: the probe rate
for a probe, the minimum once a hold outlasted its bound). The publisher serialises calls
under its lock, applies the cap and the releases to its limiter, and puts what goes outside
the lock.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

from dbml.protocol.messages import Heard, LinkBeacon
from dbml.runtime.estimator import OWED_WINDOW_S

__all__ = [
    "BEACON_WINDOW",
    "HEARD_WAIT_S",
    "HOLD_MAX_S",
    "LINK_SILENCE_S",
    "OWED_WINDOW_S",
    "PROBE_INTERVAL_S",
    "PROBE_RATE_HZ",
    "STALE_RESET_S",
    "Admission",
    "OutageGate",
    "Release",
]

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
HOLD_MAX_S = 5.0
"""The longest a hold lasts (seconds): then the channel runs at its fail-safe minimum until a
beacon says the link is back. A hold is a refinement of the fail-safe, never a stop."""
BEACON_WINDOW = 50
"""Beacons (5 s of them) whose quickest transit is the yardstick of a stale or early one. The
minimum ages, so neither clock drift nor one odd stamp sets it for good; silence does not age
it, so the backlog buffered through an outage is still judged against the time before it."""


class Admission(enum.Enum):
    """What the gate says of a message offered outside the steady state (else a ``Release``)."""

    OPEN = "open"
    """No hold: the allocation's and the fail-safe's rules decide."""
    PROBE = "probe"
    """This channel's turn to probe: the message goes if the limiter, capped at
    ``cap_hz(now, probe=True)``, has a frame (then say so: ``probed``); else it is held as the
    newest."""
    HOLD = "hold"
    """Held (the newest is kept for the release) or, awaiting a first allocation, dropped."""
    EXPIRED = "expired"
    """The hold just outlasted ``HOLD_MAX_S``: from now on the fail-safe minimum (say so once)."""
    OUTLASTED = "outlasted"
    """The hold outlasted ``HOLD_MAX_S`` before: the fail-safe minimum."""


@dataclass(frozen=True, slots=True)
class Release:
    """The hold is over: restart the limiter with ``owed_frames`` owed, then send ``message``.

    The limiter keeps at most one frame of what it earned (the outage's time is not banked
    into a burst), less ``owed_frames``: what went into the dead link and lands in the
    release's window. ``message`` (None: nothing to send) goes if a frame is left.
    """

    owed_frames: float
    message: bytes | None


class OutageGate:
    """One channel's hold, probe and release around a link outage (see the module docstring).

    Probes and the release spend the same credit as every other message: the publisher runs the
    channel's limiter at the rate in force capped by ``cap_hz``, and restarts it on a
    ``Release``. ``min_rate_hz`` is the channel's declared minimum, the most it sends once a
    hold outlasted ``HOLD_MAX_S``. ``sent_seq`` arguments are the number of messages sent on
    ``[topic]/optimized`` so far; what was sent after the last beacon that said the link was up
    may sit in a dead link's buffer.
    """

    def __init__(self, topic: str, *, min_rate_hz: float) -> None:
        self.topic = topic
        self.min_rate_hz = min_rate_hz
        self.link_deadline = math.inf
        """Hold after this: beacon silence or an outage (inf: no beacon heard yet)."""
        self._hold_from: float | None = None
        """When the outage a beacon reported began (None: none reported)."""
        self.held: bytes | None = None
        """The newest message, kept for the release."""
        self._release_at: float | None = None
        self._back_at: float | None = None
        """When a beacon first said the link is back in the hold in force."""
        self._heard: Heard | None = None
        """What the estimator last said arrived of this channel since the outage began."""
        self._probe_turn: tuple[int, int] | None = None
        """(this channel's place, how many) in the last outage beacon's release order."""
        self._probe_at = -math.inf
        self._confirmed_seq = 0
        """The last message sent before a beacon said the link was up: later ones may sit in a
        dead link's buffer."""
        self._transits: deque[float] = deque(maxlen=BEACON_WINDOW)
        """Recent beacons' transit plus the clock offset: the yardstick of a stale one."""
        self._odd_since: float | None = None
        self._expiry_noted = False

    def hold_start(self, now: float) -> float | None:
        """When the hold in force began (None: the link is up, or no beacon was ever heard)."""
        if self._hold_from is not None:
            return self._hold_from
        return self.link_deadline if now > self.link_deadline else None

    def holding(self, now: float) -> bool:
        """Whether ``[topic]/optimized`` is held (down, not yet released, within ``HOLD_MAX_S``)."""
        start = self.hold_start(now)
        return start is not None and now - start <= HOLD_MAX_S

    def cap_hz(self, now: float, *, probe: bool = False) -> float:
        """The most the channel's limiter runs at now, whatever the rate in force.

        ``PROBE_RATE_HZ`` for a ``probe``; the channel's minimum once a hold outlasted
        ``HOLD_MAX_S``, as in the fail-safe, until a beacon says the link is back; else no cap.
        """
        if probe:
            return PROBE_RATE_HZ
        start = self.hold_start(now)
        return self.min_rate_hz if start is not None and now - start > HOLD_MAX_S else math.inf

    def in_line(self, now: float, sent_s: float) -> bool:
        """Whether a beacon stamped ``sent_s`` speaks of now.

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

    def on_beacon(
        self, now: float, beacon: LinkBeacon, *, rate_hz: float, waiting: bool, sent_seq: int
    ) -> Release | None:
        """Take in a beacon that is in line (``in_line``): a release after an outage, if now.

        ``rate_hz`` is the rate in force and ``waiting`` whether a first allocation is still
        awaited. Keeps holding off, holds, or releases; the release sends the held message.
        """
        start = self.hold_start(now)
        if not beacon.up:
            # Repeated outage beacons do not extend the hold: it began once.
            self._hold_from = now if start is None else start
            self.link_deadline, self._release_at, self._back_at = -math.inf, None, None
            self._heard = None
            self._probe_turn = _turn(beacon.release_s, self.topic)
            return None
        if start is None:
            self.link_deadline = now + LINK_SILENCE_S
            self._confirmed_seq = sent_seq
            return None
        # Back: go at our place in the release order, once our backlog is through.
        if self._back_at is None:
            self._back_at = now
        if beacon.heard is not None and self.topic in beacon.heard:
            self._heard = beacon.heard[self.topic]
        if self._release_at is None and self._clear(now, beacon.heard, sent_seq):
            self._release_at = now + beacon.release_s.get(self.topic, 0.0)
        if self._release_at is None or now < self._release_at:
            return None
        # A slow source may not publish again soon: its held message goes now, unless the
        # channel still waits for a first allocation.
        return self._release(now, rate_hz, sent_seq, None if waiting else self.held)

    def admit(
        self, now: float, payload: bytes, *, rate_hz: float, waiting: bool, sent_seq: int
    ) -> Admission | Release:
        """What to do with ``payload``, offered outside the steady state.

        Not held: ``OPEN``, the first-allocation and fail-safe rules decide. Held: ``PROBE`` at
        our turn, a ``Release`` of ``payload`` at our place, else keep the newest message
        (``HOLD``); past ``HOLD_MAX_S``, the fail-safe minimum (``EXPIRED`` once, then
        ``OUTLASTED``).
        """
        start = self.hold_start(now)
        if start is None:
            return Admission.OPEN
        if now - start > HOLD_MAX_S:
            self.held = None
            expired, self._expiry_noted = not self._expiry_noted, True
            return Admission.EXPIRED if expired else Admission.OUTLASTED
        if waiting:
            self.held = None  # never allocated: nothing of it may cross, now or at the release
            return Admission.HOLD
        if self._release_at is not None:
            if now >= self._release_at:  # this newer message replaces the held one
                return self._release(now, rate_hz, sent_seq, payload)
        elif now >= self._probe_at and self._my_turn(now, start):
            self.held = payload  # until the probe goes (``probed``)
            return Admission.PROBE
        self.held = payload
        return Admission.HOLD

    def probed(self, now: float) -> None:
        """The probe ``admit`` offered went: the next one at the next turn, nothing held."""
        self._probe_at, self.held = now + PROBE_INTERVAL_S, None

    def _release(self, now: float, rate_hz: float, sent_seq: int, message: bytes | None) -> Release:
        """Leave the hold, sending ``message``; what was sent since the last beacon is owed.

        As far as it lands in the release's window (``OWED_WINDOW_S``, see ``_owed``): never
        more than one window of the rate in force.
        """
        owed = min(self._owed(sent_seq), rate_hz * OWED_WINDOW_S)
        self._hold_from, self._release_at, self._probe_turn, self.held = None, None, None, None
        self._back_at, self._heard = None, None
        self.link_deadline = now + LINK_SILENCE_S
        self._expiry_noted = False
        self._confirmed_seq = sent_seq
        return Release(owed_frames=owed, message=message)

    def _owed(self, sent_seq: int) -> float:
        """The frames sent since the last beacon that said the link was up that a release owes.

        Without word from the estimator, all of them. With it, only those that land in the
        release's window: the ones it heard in the last ``OWED_WINDOW_S`` and the ones sent
        after the newest it heard (still in the link). The rest arrived earlier, or were
        dropped with a session the outage closed: owing them would silence the channel for up
        to a second, long enough for the estimator to read a second outage. Never more than
        all of them; a forged count can at most owe nothing, as after an outage in which
        nothing went into the dead link. A newest number above ours was counted before this
        publisher (re)started: no word.
        """
        sent = sent_seq - self._confirmed_seq
        heard = self._heard
        if heard is None or heard.newest_seq > sent_seq:  # a count of another run of ours
            return float(sent)
        in_link = max(0, sent_seq - heard.newest_seq)
        return float(min(sent, heard.recent_frames + in_link))

    def _clear(self, now: float, heard: Mapping[str, Heard] | None, sent_seq: int) -> bool:
        """Whether nothing we sent is still stuck in the link (see ``HEARD_WAIT_S``)."""
        if sent_seq == self._confirmed_seq or heard is None or self.topic in heard:
            return True
        return self._back_at is not None and now - self._back_at >= HEARD_WAIT_S

    def _my_turn(self, now: float, start: float) -> bool:
        """Whether this channel probes in the current ``PROBE_INTERVAL_S`` of the hold."""
        if self._probe_turn is None:
            return False  # no release order heard: the hold's bound is the way out
        place, count = self._probe_turn
        return int((now - start) / PROBE_INTERVAL_S) % count == place


def _turn(release_s: Mapping[str, float], topic: str) -> tuple[int, int] | None:
    """``topic``'s place in a release order and its length (None: not in it)."""
    if topic not in release_s:
        return None
    order = sorted(release_s, key=lambda t: (release_s[t], t))
    return order.index(topic), len(order)
