"""A link outage at the publisher: hold the newest message, release it in priority order.

The hold is never worse than the fail-safe: it is bounded, every channel of the release order
can find the link back, nothing in a beacon raises a rate or breaks a thread. Releases happen
on a beacon or a ``publish``, so everything here runs on the manual clock, deterministically.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import replace

import pytest

from dbml.protocol import names
from dbml.protocol.keys import LINK_TOPIC
from dbml.protocol.messages import RELEASE_MAX_CHANNELS, RELEASE_MAX_S, Heard, LinkBeacon
from dbml.protocol.metadata import MessageMeta
from dbml.runtime import ManagedPublisher
from dbml.runtime.estimator import LinkEstimator, release_offsets
from dbml.runtime.publisher import HEARD_WAIT_S, HOLD_MAX_S, LINK_SILENCE_S, PROBE_INTERVAL_S
from dbml.runtime.rate import RateLimiter
from dbml.testing import BASE, Fleet
from dbml.transports import ManualClock, MemoryNetwork, MemoryTransport, Sample, Variant
from dbml.transports.base import TransportPriority
from dbml.transports.memory import _MemoryPublisher
from tests.protocol.test_messages import BAD_BEACONS

RATE_HZ = 10.0
PERIOD_S = 1 / RATE_HZ
MIN_RATE_HZ = 1.0
TWO_CAMERAS = {"/r1/camera": (0.9, 84_000), "/r2/camera": (0.1, 21_000)}


class Outage(Fleet):
    """Cameras, the operator's arrivals in order, an estimator's beacon; no optimizer."""

    def __init__(self) -> None:
        super().__init__(optimizer=False)
        self.beacon = self.host(BASE).declare_publisher(LINK_TOPIC)
        self.arrivals: list[Sample] = []

    def stream(
        self, topic: str, priority: float, *, rate_hz: float | None = RATE_HZ
    ) -> ManagedPublisher:
        publisher = self.publisher(topic, min_rate_hz=MIN_RATE_HZ, priority=priority)
        self.operator.subscribe(topic, self.arrivals.append, Variant.OPTIMIZED)
        publisher.publish(b"size")  # the size is known before the allocation
        if rate_hz is not None:
            self.allocate(topic, rate_hz)
        return publisher

    def say(self, beacon: LinkBeacon) -> None:
        self.beacon.put(replace(beacon, sent_s=self.clock()).encode())

    def payloads(self) -> list[bytes]:
        return [bytes(s.payload) for s in self.arrivals]

    def from_topic(self, topic: str) -> list[bytes]:
        return [bytes(s.payload) for s in self.arrivals if s.topic == topic]


@pytest.fixture
def fleet() -> Iterator[Outage]:
    with Outage() as outage:
        yield outage


def _confirmed_then_silent(fleet: Outage, topic: str) -> ManagedPublisher:
    """A channel whose last message went before a beacon (the link carried it), then silence."""
    camera = fleet.stream(topic, 0.9)
    fleet.advance(PERIOD_S)
    assert camera.publish(b"before")
    fleet.say(LinkBeacon(up=True))  # after "before": nothing unconfirmed
    fleet.advance(LINK_SILENCE_S + 0.01)  # the beacons stop: down both ways
    return camera


def test_a_silent_link_holds_only_the_newest_message_and_sends_it_when_back(
    fleet: Outage,
) -> None:
    camera = _confirmed_then_silent(fleet, "/r1/camera")
    sent = len(fleet.arrivals)
    for k in range(5):
        assert not camera.publish(f"during {k}".encode())
        fleet.advance(PERIOD_S)
    assert camera.holding
    assert len(fleet.arrivals) == sent
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}))
    assert fleet.payloads()[sent:] == [b"during 4"]  # the newest only, on the beacon itself
    assert not camera.holding


def test_the_release_banks_no_credit_from_the_outage(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    fleet.advance(HOLD_MAX_S - 1.0)  # a long outage, nothing published
    assert camera.holding
    fleet.host(BASE).params.set(names.ROUND, 1)  # the optimizer's heartbeat is back too
    fleet.say(LinkBeacon(up=True))
    sent = len(fleet.arrivals)
    went = [camera.publish(f"after {k}".encode()) for k in range(5)]  # all at one instant
    assert went == [True, False, False, False, False]
    fleet.advance(PERIOD_S)
    assert camera.publish(b"next period")
    assert len(fleet.arrivals) == sent + 2


def test_the_release_owes_what_went_into_the_dead_link(fleet: Outage) -> None:
    """Frames sent after the last beacon sit in TCP's buffer and arrive with the release."""
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    unheard = 0
    for k in range(3):  # the link died just after the beacon; nobody knows it yet
        unheard += camera.publish(f"unheard {k}".encode())
        fleet.advance(PERIOD_S)
    assert unheard == 3
    fleet.advance(LINK_SILENCE_S)
    assert not camera.publish(b"held")
    assert camera.holding
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}))
    assert not camera.holding
    sent = len(fleet.arrivals)
    went = []
    for k in range(6):
        went.append(camera.publish(f"after {k}".encode()))
        fleet.advance(PERIOD_S)
        fleet.say(LinkBeacon(up=True))
    # the three owed frames are the first 0.3 s of the rate; then one a period
    assert went == [False, False, False, True, True, True]
    assert len(fleet.arrivals) == sent + 3


def _stuck(fleet: Outage, topic: str) -> ManagedPublisher:
    """A channel that sent into the link just before it died, now holding."""
    camera = fleet.stream(topic, 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    assert camera.publish(b"unheard")
    fleet.advance(LINK_SILENCE_S + 0.01)
    assert not camera.publish(b"held")
    assert camera.holding
    return camera


def test_a_channel_with_a_backlog_releases_once_it_is_heard(fleet: Outage) -> None:
    camera = _stuck(fleet, "/r1/camera")
    back = {"/r1/camera": 0.0}
    fleet.say(LinkBeacon(up=True, release_s=back, heard={"/r2/camera": Heard(3, 1)}))
    assert camera.holding  # the link is back, but our backlog is not through yet
    fleet.advance(PERIOD_S)
    assert not camera.publish(b"newer")
    fleet.say(LinkBeacon(up=True, release_s=back, heard={"/r1/camera": Heard(1, 1)}))
    assert not camera.holding
    fleet.advance(2 * PERIOD_S)  # the owed frame paid for
    fleet.say(LinkBeacon(up=True))
    assert camera.publish(b"fresh")


def test_a_backlog_never_heard_waits_only_so_long(fleet: Outage) -> None:
    """Frames the middleware dropped in the outage never arrive: the wait is bounded."""
    camera = _stuck(fleet, "/r1/camera")
    nobody: dict[str, Heard] = {}
    waited = 0.0
    while camera.holding and waited < 3 * HEARD_WAIT_S:
        fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}, heard=nobody))
        fleet.advance(PERIOD_S)
        waited += PERIOD_S
    assert not camera.holding
    assert HEARD_WAIT_S <= waited <= HEARD_WAIT_S + 2 * PERIOD_S


def test_a_channel_that_sent_nothing_into_the_dead_link_need_not_be_heard(
    fleet: Outage,
) -> None:
    camera = _confirmed_then_silent(fleet, "/r1/camera")
    assert not camera.publish(b"held")
    sent = len(fleet.arrivals)
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}, heard={}))
    assert not camera.holding
    assert fleet.payloads()[sent:] == [b"held"]


def test_a_release_owes_at_most_one_window_of_the_rate(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9, rate_hz=MIN_RATE_HZ)
    fleet.say(LinkBeacon(up=True))
    unheard = 0
    for k in range(3 * round(RATE_HZ)):  # 3 s of a 1 Hz channel; beacon silence from 0.3 s
        unheard += camera.publish(f"unheard {k}".encode())
        fleet.advance(PERIOD_S)
    assert unheard <= 1  # the rest was held
    fleet.advance(HOLD_MAX_S)  # past the hold: the fail-safe minimum, 1 Hz, into the void
    for k in range(4 * round(RATE_HZ)):
        unheard += camera.publish(f"fail-safe {k}".encode())
        fleet.advance(PERIOD_S)
    assert unheard >= 4
    fleet.say(LinkBeacon(up=True))
    went = []
    for k in range(round(3 * RATE_HZ)):
        went.append(camera.publish(f"after {k}".encode()))
        fleet.advance(PERIOD_S)
        fleet.say(LinkBeacon(up=True))
    # one second's worth owed (one frame at 1 Hz), not all four: the first goes 1 s on, or
    # 2 s when the fail-safe had just spent its frame
    first = went.index(True)
    assert 0.9 * RATE_HZ <= first <= 2.1 * RATE_HZ


def test_in_an_outage_the_channels_take_turns_to_probe(fleet: Outage) -> None:
    urgent = fleet.stream("/r1/camera", 0.9)
    calm = fleet.stream("/r2/camera", 0.1)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    fleet.say(LinkBeacon(up=False, release_s=release_offsets(TWO_CAMERAS, 1e6)))
    start = fleet.clock()
    probes: list[tuple[int, str]] = []  # (probe interval of the hold, who)
    for _ in range(round(4 * PROBE_INTERVAL_S / PERIOD_S)):
        turn = int((fleet.clock() - start) / PROBE_INTERVAL_S)
        if urgent.publish(b"urgent"):
            probes.append((turn, "urgent"))
        if calm.publish(b"calm"):
            probes.append((turn, "calm"))
        fleet.advance(PERIOD_S)
    # the release order's first probes first, then the next: one channel per interval
    assert probes == [(0, "urgent"), (1, "calm"), (2, "urgent"), (3, "calm")]
    assert urgent.holding
    assert calm.holding


def test_an_idle_first_channel_does_not_keep_the_others_from_probing(fleet: Outage) -> None:
    """The most urgent channel's publisher stopped: the others still find the link back."""
    fleet.stream("/r1/camera", 0.9)  # never publishes again
    calm = fleet.stream("/r2/camera", 0.1)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    for _ in range(round(2 * PROBE_INTERVAL_S / PERIOD_S) + 1):
        fleet.say(LinkBeacon(up=False, release_s=release_offsets(TWO_CAMERAS, 1e6)))
        calm.publish(b"calm")
        fleet.advance(PERIOD_S)
    assert fleet.from_topic("/r2/camera").count(b"calm") >= 1


def test_a_probe_never_exceeds_the_channel_s_own_rate(fleet: Outage) -> None:
    slow_hz = 0.5  # allocated below the probe rate (and below its minimum: infeasible floors)
    camera = fleet.stream("/r1/camera", 0.9, rate_hz=slow_hz)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    fleet.say(LinkBeacon(up=False, release_s={"/r1/camera": 0.0}))
    sent = len(fleet.arrivals)
    hold_s = HOLD_MAX_S - 0.5
    steps = round(hold_s / PERIOD_S)
    for _ in range(steps):
        camera.publish(b"frame")
        fleet.host(BASE).params.set(names.ROUND, 1)  # the allocation stands throughout
        fleet.advance(PERIOD_S)
    assert len(fleet.arrivals) - sent <= RateLimiter.BANKED_FRAMES + hold_s * slow_hz


def test_the_release_goes_in_priority_order(fleet: Outage) -> None:
    urgent = fleet.stream("/r1/camera", 0.9)
    calm = fleet.stream("/r2/camera", 0.1)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(LINK_SILENCE_S + 0.01)
    assert not calm.publish(b"calm newest")
    assert not urgent.publish(b"urgent newest")
    order = release_offsets(TWO_CAMERAS, 1e6)
    assert order == {"/r1/camera": 0.0, "/r2/camera": pytest.approx(0.084)}
    sent = len(fleet.arrivals)
    fleet.say(LinkBeacon(up=True, release_s=order))
    assert fleet.payloads()[sent:] == [b"urgent newest"]
    fleet.advance(0.1)  # the calm channel's turn: the urgent frame has crossed
    fleet.say(LinkBeacon(up=True))  # the next beacon releases it (or its next publish)
    assert fleet.payloads()[sent:] == [b"urgent newest", b"calm newest"]


def test_a_release_puts_outside_the_lock_and_numbers_stay_unique(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    locked: list[bool] = []
    fleet.operator.subscribe(
        "/r1/camera", lambda _s: locked.append(camera._lock.locked()), Variant.OPTIMIZED
    )
    fleet.say(LinkBeacon(up=True))
    fleet.advance(LINK_SILENCE_S + 0.01)
    assert not camera.publish(b"held")
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}))
    fleet.advance(PERIOD_S)
    assert camera.publish(b"next")
    assert locked == [False, False]
    seqs = [MessageMeta.decode(s.attachment).seq for s in fleet.arrivals]
    assert seqs == sorted(set(seqs))


def test_a_dead_estimator_leaves_the_fail_safe_minimum_not_a_hold(fleet: Outage) -> None:
    """Beacons were heard, then never again: after HOLD_MAX_S the channel runs at its minimum."""
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(LINK_SILENCE_S + HOLD_MAX_S + 0.01)
    assert not camera.holding
    sent = len(fleet.arrivals)
    went = []
    for _ in range(round(2 / MIN_RATE_HZ / PERIOD_S)):  # two minimum periods
        fleet.host(BASE).params.set(names.ROUND, 1)  # the optimizer is alive: the rate stands
        went.append(camera.publish(b"frame"))
        fleet.advance(PERIOD_S)
    assert 1 <= sum(went) <= 2 + 1  # the minimum, never the allocation of 10 Hz
    assert len(fleet.arrivals) - sent == sum(went)
    fleet.say(LinkBeacon(up=True))  # the estimator is back: the allocation again
    for _ in range(sum(went) + 2):  # once the fail-safe's frames are paid for
        fleet.advance(PERIOD_S)
        fleet.say(LinkBeacon(up=True))
    assert camera.publish(b"a")
    fleet.advance(PERIOD_S)
    assert camera.publish(b"b")


def test_repeated_outage_beacons_do_not_extend_the_hold(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    for _ in range(round((HOLD_MAX_S + 1.0) / PERIOD_S)):  # the estimator hears nothing
        fleet.say(LinkBeacon(up=False))
        fleet.advance(PERIOD_S)
    assert not camera.holding
    assert camera.publish(b"fail-safe")


def test_a_channel_never_allocated_sends_nothing_through_an_outage(fleet: Outage) -> None:
    fresh = fleet.stream("/r3/camera", 0.9, rate_hz=None)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(PERIOD_S)
    fleet.say(LinkBeacon(up=False, release_s={"/r3/camera": 0.0}))
    assert not fresh.publish(b"would probe")
    fleet.advance(PROBE_INTERVAL_S)
    assert not fresh.publish(b"held")
    fleet.say(LinkBeacon(up=True, release_s={"/r3/camera": 0.0}))
    fleet.advance(PERIOD_S)
    assert not fresh.publish(b"after")
    assert fleet.from_topic("/r3/camera") == []


def test_the_release_order_stays_within_its_bound() -> None:
    many = {f"/r{k}/camera": (0.5, 84_000) for k in range(40)}
    offsets = release_offsets(many, 125_000)  # 1 Mbit: 27 s of frames
    assert max(offsets.values()) == RELEASE_MAX_S
    assert LinkBeacon.decode(LinkBeacon(up=True, release_s=offsets).encode()).release_s == offsets


def test_the_release_order_names_no_more_channels_than_a_beacon_takes() -> None:
    """Channels come from parameters any peer writes: the highest priorities are named."""
    many = {f"/r{k}/camera": (k / 10_000, 1_000) for k in range(RELEASE_MAX_CHANNELS + 10)}
    offsets = release_offsets(many, 125_000)
    assert len(offsets) == RELEASE_MAX_CHANNELS
    assert "/r9/camera" not in offsets  # among the ten lowest
    assert "/r10/camera" in offsets
    assert LinkBeacon.decode(LinkBeacon(up=True, release_s=offsets).encode()).release_s == offsets


def test_malformed_beacons_are_ignored_and_reported_once(
    fleet: Outage, caplog: pytest.LogCaptureFixture
) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(LINK_SILENCE_S + 0.01)
    assert not camera.publish(b"held")
    with caplog.at_level(logging.WARNING, logger="dbml.publisher"):
        for data in BAD_BEACONS:  # a release of a huge or non-finite delay among them
            fleet.beacon.put(data)
    assert camera.holding  # none of them released, none of them broke anything
    assert [r.levelno for r in caplog.records if "malformed link beacon" in r.message] == [
        logging.WARNING
    ]
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}))
    assert fleet.payloads()[-1] == b"held"


def test_without_a_beacon_nothing_is_ever_held(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.advance(10.0)  # no estimator runs: silence means nothing
    assert not camera.holding


def test_a_beacon_buffered_through_the_outage_is_stale(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    sent_before_the_outage = fleet.clock()
    fleet.advance(2.0)
    assert camera.holding
    fleet.beacon.put(LinkBeacon(up=True, sent_s=sent_before_the_outage).encode())
    assert camera.holding  # an old "up" is no news of the link now
    fleet.say(LinkBeacon(up=True))
    assert camera.publish(b"fresh")


def test_a_beacon_stamped_ahead_does_not_make_the_genuine_ones_stale(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.beacon.put(LinkBeacon(up=True, sent_s=fleet.clock() + 100.0).encode())
    for _ in range(5):  # genuine beacons go on: the link is up throughout
        fleet.advance(PERIOD_S)
        fleet.say(LinkBeacon(up=True))
        assert not camera.holding


def test_beacons_late_for_long_are_a_new_clock_offset_not_a_backlog(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    step = 0.1
    for _ in range(15):  # the estimator's clock stepped back 2 s: every beacon looks late
        fleet.advance(step)
        fleet.beacon.put(LinkBeacon(up=True, sent_s=fleet.clock() - 2.0).encode())
    # held meanwhile (nothing counted for STALE_RESET_S), then they count again: released
    assert camera.publish(b"after the step")
    assert not camera.holding


def test_after_close_a_beacon_sends_nothing(fleet: Outage) -> None:
    camera = fleet.stream("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.advance(LINK_SILENCE_S + 0.01)
    assert not camera.publish(b"held")
    sent = len(fleet.arrivals)
    camera.close()
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}))
    assert len(fleet.arrivals) == sent


class _Recording(MemoryTransport):
    """A memory transport that remembers each declared publisher's class."""

    declared: dict[str, tuple[TransportPriority | None, bool]]

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _MemoryPublisher:
        self.declared = getattr(self, "declared", {})
        self.declared[variant.key(topic)] = (priority, express)
        return super().declare_publisher(topic, variant, priority=priority, express=express)


def test_the_beacon_travels_in_the_datas_own_class() -> None:
    """Behind the frames queued for the link: the "up" beacon must not overtake the backlog."""
    transport = _Recording(MemoryNetwork(), host="base", clock=ManualClock(0.0))
    estimator = LinkEstimator(transport)
    try:
        assert transport.declared[LINK_TOPIC] == (None, False)
    finally:
        estimator.close()
