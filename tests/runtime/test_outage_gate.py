"""The outage gate alone: beacons and plain numbers for the clock, then a rate limiter.

What ``test_publisher_outage.py`` shows through a fleet on memory transports is checked here
one rule at a time, with the facts the publisher would pass in (the rate in force, whether a
first allocation is awaited, how many messages went) set by hand: first the gate's word alone
(what it caps, what a release owes), then with a limiter applied as the publisher applies it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Final

import pytest

from dbml.protocol.messages import Heard, LinkBeacon
from dbml.runtime.outage import (
    BEACON_WINDOW,
    HEARD_WAIT_S,
    HOLD_MAX_S,
    LINK_SILENCE_S,
    OWED_WINDOW_S,
    PROBE_INTERVAL_S,
    PROBE_RATE_HZ,
    STALE_RESET_S,
    Admission,
    OutageGate,
    Release,
)
from dbml.runtime.rate import RateLimiter

TOPIC = "/r1/camera"
OTHER = "/r2/camera"
RATE_HZ = 10.0
MIN_RATE_HZ = 1.0
PERIOD_S = 1 / RATE_HZ
START_S = 100.0
SENT: Final = "sent"
"""``Channel.admit``: the gate let the message through and the limiter had a frame for it."""


class Channel:
    """A gate, a rate limiter and the publisher's side of the bargain, on a hand-moved clock.

    As ``ManagedPublisher`` does: the limiter runs at the rate in force capped by the gate
    (``cap_hz``), a release restarts it owing what the gate says, and what the gate lets
    through goes if the limiter has a frame.
    """

    def __init__(self, topic: str = TOPIC, *, rate_hz: float = RATE_HZ) -> None:
        self.now = START_S
        self.rate_hz = rate_hz
        self.waiting = False
        self.sent = 0
        self.limiter = RateLimiter(rate_hz)
        self.gate = OutageGate(topic, min_rate_hz=MIN_RATE_HZ)

    def _limit(self, release: Release | None = None, *, probe: bool = False) -> RateLimiter:
        limit_hz = min(self.rate_hz, self.gate.cap_hz(self.now, probe=probe))
        if release is None:
            self.limiter.set_rate(limit_hz, self.now)
        else:
            self.limiter.restart(limit_hz, self.now, owed_frames=release.owed_frames)
        return self.limiter

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def beacon(
        self,
        up: bool,
        *,
        release_s: Mapping[str, float] | None = None,
        heard: Mapping[str, Heard] | None = None,
    ) -> bytes | None:
        """Hear a beacon stamped now (in line with the others); what it releases, counted."""
        beacon = LinkBeacon(up, dict(release_s or {}), sent_s=self.now, heard=heard)
        assert self.gate.in_line(self.now, beacon.sent_s)
        release = self.gate.on_beacon(
            self.now, beacon, rate_hz=self.rate_hz, waiting=self.waiting, sent_seq=self.sent
        )
        limiter = self._limit(release)
        held = None if release is None else release.message
        went = held is not None and limiter.allow(self.now)
        self.sent += went
        return held if went else None

    def admit(self, payload: bytes = b"frame") -> Admission | str:
        """The gate's word on ``payload``, or ``SENT`` if it went (a probe or the release)."""
        verdict = self.gate.admit(
            self.now, payload, rate_hz=self.rate_hz, waiting=self.waiting, sent_seq=self.sent
        )
        if isinstance(verdict, Release):
            went = self._limit(verdict).allow(self.now)
        elif verdict is Admission.PROBE:
            went = self._limit(probe=True).allow(self.now)
            if went:
                self.gate.probed(self.now)
        else:
            return verdict
        self.sent += went
        return SENT if went else Admission.HOLD

    def steady(self) -> bool:
        """A message at the allocation, as ``publish`` sends it while the link is up."""
        went = self.limiter.allow(self.now)
        self.sent += went
        return went


def silent(channel: Channel) -> Channel:
    """Heard up once, nothing sent since, then the beacons stopped."""
    channel.beacon(up=True)
    channel.advance(LINK_SILENCE_S + 0.01)
    return channel


# -- the gate's word alone, no limiter ---------------------------------------------------------


def hear(
    gate: OutageGate,
    now: float,
    *,
    up: bool,
    release_s: Mapping[str, float] | None = None,
    heard: Mapping[str, Heard] | None = None,
    sent_seq: int = 0,
    waiting: bool = False,
) -> Release | None:
    """``gate`` hears a beacon stamped ``now``, at ``RATE_HZ`` in force."""
    beacon = LinkBeacon(up, dict(release_s or {}), sent_s=now, heard=heard)
    assert gate.in_line(now, beacon.sent_s)
    return gate.on_beacon(now, beacon, rate_hz=RATE_HZ, waiting=waiting, sent_seq=sent_seq)


def offer(gate: OutageGate, now: float, payload: bytes, *, sent_seq: int = 0) -> object:
    return gate.admit(now, payload, rate_hz=RATE_HZ, waiting=False, sent_seq=sent_seq)


def test_the_gate_caps_the_limiter_for_a_probe_and_past_the_holds_bound_only() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    assert gate.cap_hz(now) == math.inf  # no beacon heard: nothing to cap
    assert gate.cap_hz(now, probe=True) == PROBE_RATE_HZ
    hear(gate, now, up=True)
    assert gate.cap_hz(now) == math.inf
    now += LINK_SILENCE_S + 0.01
    assert gate.holding(now)
    assert gate.cap_hz(now) == math.inf  # held: only probes go, each capped
    now += HOLD_MAX_S
    assert not gate.holding(now)
    assert gate.cap_hz(now) == MIN_RATE_HZ  # outlasted: the fail-safe minimum
    assert hear(gate, now, up=True, release_s={TOPIC: 0.0}) == Release(0.0, None)
    assert gate.cap_hz(now) == math.inf  # released: the rate in force again


def test_a_probe_is_offered_at_its_turn_until_it_goes() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    hear(gate, now, up=True)
    hear(gate, now, up=False, release_s={TOPIC: 0.0, OTHER: 0.1})
    assert offer(gate, now, b"a") is Admission.PROBE
    assert offer(gate, now, b"b") is Admission.PROBE  # the limiter refused "a": offered again
    assert gate.held == b"b"  # and kept as the newest until it goes
    gate.probed(now)
    assert gate.held is None
    now += PROBE_INTERVAL_S  # the other channel's turn
    assert offer(gate, now, b"c") is Admission.HOLD
    now += PROBE_INTERVAL_S  # ours again
    assert offer(gate, now, b"d") is Admission.PROBE


def test_a_release_at_a_publish_sends_the_newer_message() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    hear(gate, now, up=True)
    now += LINK_SILENCE_S + 0.01
    assert offer(gate, now, b"held", sent_seq=2) is Admission.HOLD
    assert hear(gate, now, up=True, release_s={TOPIC: 0.25}, sent_seq=2) is None  # not its place
    now += 0.25
    assert offer(gate, now, b"newer", sent_seq=2) == Release(2.0, b"newer")
    assert not gate.holding(now)


def test_a_release_awaiting_a_first_allocation_sends_nothing() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    hear(gate, now, up=True)
    now += LINK_SILENCE_S + 0.01
    assert gate.admit(now, b"x", rate_hz=RATE_HZ, waiting=True, sent_seq=0) is Admission.HOLD
    release = hear(gate, now, up=True, release_s={TOPIC: 0.0}, waiting=True)
    assert release == Release(0.0, None)


@pytest.mark.parametrize(
    ("heard", "owed"),
    [
        (Heard(newest_seq=8, recent_frames=2), 2.0),  # two arrived in the last second
        (Heard(newest_seq=7, recent_frames=2), 3.0),  # and one still in the link
        (None, 8.0),  # no word: all of them
        (Heard(newest_seq=0, recent_frames=1000), 8.0),  # never more than all of them
        (Heard(newest_seq=8, recent_frames=0), 0.0),  # a forged count: at most nothing
        (Heard(newest_seq=10**9, recent_frames=0), 8.0),  # another run's count: no word
    ],
)
def test_a_release_says_what_it_owes(heard: Heard | None, owed: float) -> None:
    """The numbers behind ``_after_a_long_outage``: eight frames went into the dead link."""
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    hear(gate, now, up=True)
    now += LINK_SILENCE_S + 0.01
    offer(gate, now, b"held", sent_seq=8)
    word = None if heard is None else {TOPIC: heard}
    release = hear(gate, now, up=True, release_s={TOPIC: 0.0}, heard=word, sent_seq=8)
    assert release == Release(owed, b"held")


def test_a_release_owes_at_most_one_window_of_the_rate_in_force() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    hear(gate, now, up=True)
    now += LINK_SILENCE_S + 0.01
    beacon = LinkBeacon(True, {TOPIC: 0.0}, sent_s=now)
    assert gate.in_line(now, now)
    release = gate.on_beacon(now, beacon, rate_hz=1.0, waiting=False, sent_seq=100)
    assert release == Release(1.0 * OWED_WINDOW_S, None)


# -- with a limiter, as the publisher applies the gate's word ---------------------------------


def test_without_a_beacon_nothing_is_ever_held() -> None:
    channel = Channel()
    channel.advance(10 * HOLD_MAX_S)
    assert not channel.gate.holding(channel.now)
    assert channel.admit() is Admission.OPEN
    assert channel.gate.link_deadline == float("inf")


def test_beacon_silence_holds_the_newest_message_and_the_next_up_releases_it() -> None:
    channel = silent(Channel())
    assert channel.gate.holding(channel.now)
    assert [channel.admit(f"{k}".encode()) for k in range(3)] == [Admission.HOLD] * 3
    assert channel.gate.held == b"2"
    assert channel.beacon(up=True, release_s={TOPIC: 0.0}) == b"2"
    assert not channel.gate.holding(channel.now)
    assert channel.gate.held is None


def test_an_up_beacon_keeps_the_link_deadline_ahead() -> None:
    channel = Channel()
    channel.beacon(up=True)
    assert channel.gate.link_deadline == START_S + LINK_SILENCE_S
    channel.advance(LINK_SILENCE_S)
    assert not channel.gate.holding(channel.now)
    channel.beacon(up=True)
    channel.advance(LINK_SILENCE_S)
    assert not channel.gate.holding(channel.now)


def test_the_release_waits_for_its_place_in_the_order() -> None:
    channel = silent(Channel())
    channel.admit(b"newest")
    order = {OTHER: 0.0, TOPIC: 0.25}
    assert channel.beacon(up=True, release_s=order) is None
    assert channel.gate.holding(channel.now)
    channel.advance(PERIOD_S)
    assert channel.admit(b"newer") is Admission.HOLD  # not yet its place
    channel.advance(0.25 - PERIOD_S)
    assert channel.admit(b"newest of all") == SENT  # a publish at its place
    assert not channel.gate.holding(channel.now)


def test_the_release_banks_no_credit_from_the_outage() -> None:
    channel = silent(Channel())
    channel.advance(HOLD_MAX_S - 1.0)
    assert channel.beacon(up=True) is None  # nothing held: nothing to send
    assert [channel.steady() for _ in range(3)] == [True, False, False]
    channel.advance(PERIOD_S)
    assert channel.steady()


def test_the_release_owes_what_went_into_the_dead_link() -> None:
    channel = Channel()
    channel.beacon(up=True)
    unheard = 3
    for _ in range(unheard):  # the link died just after the beacon
        channel.advance(PERIOD_S)
        assert channel.steady()
    channel.advance(LINK_SILENCE_S)
    assert channel.admit(b"held") is Admission.HOLD
    assert channel.beacon(up=True, release_s={TOPIC: 0.0}) is None  # the owed frames first
    went = []
    for _ in range(unheard + 1):
        channel.advance(PERIOD_S)
        went.append(channel.steady())
    assert went == [False, False, True, True]  # 3 owed less the frame the release had


def test_what_a_release_owes_is_bounded_by_one_window_of_the_rate() -> None:
    channel = Channel(rate_hz=1.0)
    channel.beacon(up=True)
    channel.sent += 100  # far more than a window went unconfirmed (the fail-safe's, say)
    channel.advance(LINK_SILENCE_S + 0.01)
    channel.admit(b"held")
    assert channel.beacon(up=True, release_s={TOPIC: 0.0}) is None  # its frame is owed
    channel.advance(OWED_WINDOW_S - 0.01)  # one window at 1 Hz is one frame, not 100
    assert not channel.steady()
    channel.advance(0.02)
    assert channel.steady()


def _after_a_long_outage(heard: Heard | None) -> list[bool]:
    """Eight frames into the dead link, the last two heard after it: what a release lets go.

    As after an outage longer than the lease: the session that held the first six closed and
    dropped them, and the two sent as the link came back (the fail-safe's, say) arrived.
    """
    channel = Channel()
    channel.beacon(up=True)
    channel.advance(LINK_SILENCE_S + 0.01)
    channel.admit(b"held")
    channel.sent += 8
    channel.beacon(up=True, release_s={TOPIC: 0.0}, heard=None if heard is None else {TOPIC: heard})
    went = []
    for _ in range(8):
        channel.advance(PERIOD_S)
        went.append(channel.steady())
    return went


def test_a_release_owes_only_what_lands_in_its_window() -> None:
    # heard: the newest is the last sent, two arrived in the last second: two owed, less the
    # release's own frame
    assert _after_a_long_outage(Heard(newest_seq=8, recent_frames=2)) == [False] + [True] * 7
    # one more sent after the newest heard is still in the link: owed too
    assert _after_a_long_outage(Heard(newest_seq=7, recent_frames=2)) == [False] * 2 + [True] * 6
    # no word of what arrived: all eight are owed, as before the estimator counted
    assert _after_a_long_outage(None) == [False] * 7 + [True]


def test_a_count_never_owes_more_than_was_sent_and_at_most_nothing() -> None:
    # a count above what was sent cannot owe more than all of it
    assert _after_a_long_outage(Heard(newest_seq=0, recent_frames=1000)) == [False] * 7 + [True]
    # the most a forged count can give: nothing owed, as after an outage in which nothing went
    # into the dead link; never more credit than that
    assert _after_a_long_outage(Heard(newest_seq=8, recent_frames=0)) == [True] * 8


def test_a_newest_number_above_ours_is_another_runs_and_owes_everything() -> None:
    """An estimator that counted a publisher before it restarted has a higher newest number."""
    assert _after_a_long_outage(Heard(newest_seq=10**9, recent_frames=0)) == [False] * 7 + [True]


def test_what_was_heard_before_a_second_outage_is_not_owed_by_its_release() -> None:
    channel = Channel()
    channel.beacon(up=True)
    channel.advance(LINK_SILENCE_S + 0.01)
    channel.admit(b"held")
    channel.sent += 8
    # back: heard (nothing owed by that count), but not yet at its place in the order ...
    late = {TOPIC: 0.5}
    assert channel.beacon(up=True, release_s=late, heard={TOPIC: Heard(8, 0)}) is None
    # ... and down again before it: the count is of the link as it was, not as it will be
    assert channel.beacon(up=False, release_s=late) is None
    channel.advance(0.5)
    channel.beacon(up=True, release_s={TOPIC: 0.0}, heard=None)
    assert not channel.gate.holding(channel.now)
    went = []
    for _ in range(8):
        channel.advance(PERIOD_S)
        went.append(channel.steady())
    assert went == [False] * 7 + [True]  # no word this time: all eight owed


def test_a_backlog_releases_once_heard_or_after_the_wait() -> None:
    heard = Channel()
    heard.beacon(up=True)
    heard.advance(PERIOD_S)
    assert heard.steady()  # into the dead link
    heard.advance(LINK_SILENCE_S + 0.01)
    heard.admit(b"held")
    nobody: dict[str, Heard] = {}
    other = {OTHER: Heard(newest_seq=7, recent_frames=1)}
    assert heard.beacon(up=True, release_s={TOPIC: 0.0}, heard=other) is None
    assert heard.gate.holding(heard.now)
    heard.advance(HEARD_WAIT_S - 0.01)
    assert heard.beacon(up=True, release_s={TOPIC: 0.0}, heard=nobody) is None
    assert heard.gate.holding(heard.now)
    heard.advance(0.02)
    heard.beacon(up=True, release_s={TOPIC: 0.0}, heard=nobody)
    assert not heard.gate.holding(heard.now)  # never heard: the wait is bounded


def test_a_channel_heard_again_releases_at_once() -> None:
    channel = Channel()
    channel.beacon(up=True)
    channel.advance(PERIOD_S)
    assert channel.steady()
    channel.advance(LINK_SILENCE_S + 0.01)
    channel.admit(b"held")
    channel.beacon(up=True, release_s={TOPIC: 0.0}, heard={TOPIC: Heard(channel.sent, 1)})
    assert not channel.gate.holding(channel.now)


def test_what_went_before_the_last_up_beacon_is_neither_owed_nor_awaited() -> None:
    channel = Channel()
    for _ in range(3):
        channel.advance(PERIOD_S)
        assert channel.steady()
    channel.beacon(up=True)  # the link carried them
    channel.advance(LINK_SILENCE_S + 0.01)
    channel.admit(b"held")
    assert channel.beacon(up=True, release_s={TOPIC: 0.0}, heard={}) == b"held"


def test_nothing_sent_into_the_dead_link_need_not_be_heard() -> None:
    channel = silent(Channel())
    channel.admit(b"held")
    assert channel.beacon(up=True, release_s={TOPIC: 0.0}, heard={}) == b"held"


def test_a_hold_lasts_at_most_its_bound_and_says_so_once() -> None:
    channel = silent(Channel())
    start = channel.now - 0.01
    channel.advance(start + HOLD_MAX_S - channel.now)
    assert channel.gate.holding(channel.now)
    assert channel.admit() is Admission.HOLD
    channel.advance(0.02)
    assert not channel.gate.holding(channel.now)
    assert channel.admit() is Admission.EXPIRED
    assert channel.admit() is Admission.OUTLASTED
    assert channel.gate.held is None


def test_repeated_outage_beacons_do_not_extend_the_hold() -> None:
    channel = Channel()
    channel.beacon(up=True)
    for _ in range(round((HOLD_MAX_S + 1.0) / PERIOD_S)):
        channel.beacon(up=False)
        channel.advance(PERIOD_S)
    assert not channel.gate.holding(channel.now)
    assert channel.admit() is Admission.EXPIRED


def test_a_channel_awaiting_its_first_allocation_holds_nothing() -> None:
    channel = silent(Channel())
    channel.waiting = True
    assert channel.admit(b"unallocated") is Admission.HOLD
    assert channel.gate.held is None
    assert channel.beacon(up=True, release_s={TOPIC: 0.0}) is None
    assert channel.sent == 0


@pytest.mark.parametrize(("topic", "turns"), [(TOPIC, [0, 2]), (OTHER, [1, 3])])
def test_the_release_order_takes_turns_to_probe(topic: str, turns: list[int]) -> None:
    channel = Channel(topic)
    channel.beacon(up=True)
    channel.advance(PERIOD_S)
    channel.beacon(up=False, release_s={TOPIC: 0.0, OTHER: 0.1})
    start = channel.now
    probed = []
    for _ in range(round(4 * PROBE_INTERVAL_S / PERIOD_S)):
        if channel.admit() == SENT:
            probed.append(int((channel.now - start) / PROBE_INTERVAL_S))
        channel.advance(PERIOD_S)
    assert probed == turns
    assert channel.gate.holding(channel.now)


def test_without_a_release_order_nobody_probes() -> None:
    channel = silent(Channel())
    admitted = set()
    for _ in range(round(HOLD_MAX_S / PERIOD_S) - 1):
        admitted.add(channel.admit())
        channel.advance(PERIOD_S)
    assert admitted == {Admission.HOLD}


def test_a_probe_never_exceeds_the_channels_own_rate() -> None:
    slow_hz = PROBE_RATE_HZ / 4
    channel = Channel(rate_hz=slow_hz)
    channel.beacon(up=True)
    channel.beacon(up=False, release_s={TOPIC: 0.0})
    hold_s = HOLD_MAX_S - 0.5
    probes = 0
    for _ in range(round(hold_s / PERIOD_S)):
        probes += channel.admit() == SENT
        channel.advance(PERIOD_S)
    assert 1 <= probes <= RateLimiter.BANKED_FRAMES + hold_s * slow_hz
    assert channel.limiter.rate_hz == slow_hz


def test_a_beacon_buffered_through_the_outage_is_out_of_line() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    for _ in range(BEACON_WINDOW):
        assert gate.in_line(now, now - 0.01)
        now += PERIOD_S
    assert not gate.in_line(now, now - 2.0)  # sat in a buffer for 2 s
    assert not gate.in_line(now, now + 2.0)  # stamped ahead
    assert gate.in_line(now, now - 0.01)


def test_beacons_out_of_line_for_long_are_a_new_clock_offset() -> None:
    gate = OutageGate(TOPIC, min_rate_hz=MIN_RATE_HZ)
    now = START_S
    assert gate.in_line(now, now)
    lines = []
    for _ in range(round(STALE_RESET_S / PERIOD_S) + 2):
        now += PERIOD_S
        lines.append(gate.in_line(now, now - 2.0))  # the estimator's clock stepped back 2 s
    assert lines[0] is False
    assert lines[-1] is True
    assert gate.in_line(now + PERIOD_S, now + PERIOD_S - 2.0)  # the new yardstick holds
