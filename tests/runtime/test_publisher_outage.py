"""A link outage at the publisher: hold the newest message, release it in priority order."""

from __future__ import annotations

from dataclasses import replace

import pytest

from dbml.runtime import ManagedPublisher, names
from dbml.runtime.estimator import LINK_TOPIC, LinkBeacon, release_offsets
from dbml.runtime.publisher import LINK_SILENCE_S, PROBE_INTERVAL_S
from dbml.transports import ManualClock, MemoryNetwork, MemoryTransport, Sample, Variant
from tests.conftest import wait_for

RATE_HZ = 10.0
PERIOD_S = 1 / RATE_HZ


class Fleet:
    """Publishers on robots, an operator receiving ``[topic]/optimized``, an estimator's beacon."""

    def __init__(self) -> None:
        self.clock = ManualClock(100.0)
        self.network = MemoryNetwork()
        self.base = MemoryTransport(self.network, host="base", clock=self.clock)
        self.beacon = self.base.declare_publisher(LINK_TOPIC)
        self.operator = MemoryTransport(self.network, host="op", clock=self.clock)
        self.received: list[Sample] = []

    def publisher(self, topic: str, priority: float) -> ManagedPublisher:
        host = topic.split("/")[1]
        transport = MemoryTransport(self.network, host=host, clock=self.clock)
        publisher = ManagedPublisher(
            transport, topic, min_rate_hz=1.0, max_rate_hz=16.0, priority=priority
        )
        self.operator.subscribe(topic, self.received.append, Variant.OPTIMIZED)
        publisher.publish(b"size")  # the size is known before the allocation
        self.base.params.set(names.current_value(topic), RATE_HZ)
        return publisher

    def say(self, beacon: LinkBeacon) -> None:
        self.beacon.put(replace(beacon, sent_s=self.clock()).encode())

    def payloads(self) -> list[bytes]:
        return [bytes(s.payload) for s in self.received]


@pytest.fixture
def fleet() -> Fleet:
    return Fleet()


def test_a_silent_link_holds_only_the_newest_message_and_sends_it_when_back(
    fleet: Fleet,
) -> None:
    camera = fleet.publisher("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.clock.advance(PERIOD_S)
    assert camera.publish(b"before")
    # the beacons stop: the link is down both ways
    fleet.clock.advance(LINK_SILENCE_S + 0.01)
    sent = len(fleet.received)
    for k in range(5):
        assert not camera.publish(f"during {k}".encode())
        fleet.clock.advance(PERIOD_S)
    assert camera.holding
    assert len(fleet.received) == sent
    fleet.say(LinkBeacon(up=True, release_s={"/r1/camera": 0.0}))
    wait_for(lambda: len(fleet.received) == sent + 1, timeout_s=2, what="the held message")
    assert fleet.payloads()[-1] == b"during 4"  # the newest only
    assert not camera.holding


def test_the_release_banks_no_credit_from_the_outage(fleet: Fleet) -> None:
    camera = fleet.publisher("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    fleet.clock.advance(PERIOD_S)
    fleet.clock.advance(LINK_SILENCE_S + 5.0)  # a long outage, nothing published
    assert camera.holding
    fleet.base.params.set(names.ROUND, 1)  # the optimizer's heartbeat is back too
    fleet.say(LinkBeacon(up=True))
    sent = len(fleet.received)
    went = [camera.publish(f"after {k}".encode()) for k in range(5)]  # all at one instant
    assert went == [True, False, False, False, False]
    fleet.clock.advance(PERIOD_S)
    assert camera.publish(b"next period")
    assert len(fleet.received) == sent + 2


def test_an_outage_beacon_holds_and_the_most_urgent_channel_probes(fleet: Fleet) -> None:
    urgent = fleet.publisher("/r1/camera", 0.9)
    calm = fleet.publisher("/r2/camera", 0.1)
    fleet.say(LinkBeacon(up=True))
    fleet.clock.advance(PERIOD_S)
    order = release_offsets({"/r1/camera": (0.9, 84_000), "/r2/camera": (0.1, 21_000)}, 1e6)
    fleet.say(LinkBeacon(up=False, release_s=order))
    sent = len(fleet.received)
    assert urgent.publish(b"probe")  # the first of the release order probes
    assert not calm.publish(b"calm")
    assert not urgent.publish(b"held")
    fleet.clock.advance(PROBE_INTERVAL_S)
    assert urgent.publish(b"probe again")
    assert fleet.payloads()[sent:] == [b"probe", b"probe again"]


def test_the_release_goes_in_priority_order(fleet: Fleet) -> None:
    urgent = fleet.publisher("/r1/camera", 0.9)
    calm = fleet.publisher("/r2/camera", 0.1)
    fleet.say(LinkBeacon(up=True))
    fleet.clock.advance(LINK_SILENCE_S + 0.01)
    assert not calm.publish(b"calm newest")
    assert not urgent.publish(b"urgent newest")
    order = release_offsets({"/r1/camera": (0.9, 84_000), "/r2/camera": (0.1, 21_000)}, 1e6)
    assert order == {"/r1/camera": 0.0, "/r2/camera": pytest.approx(0.084)}
    sent = len(fleet.received)
    fleet.say(LinkBeacon(up=True, release_s=order))
    wait_for(lambda: len(fleet.received) == sent + 1, timeout_s=2, what="the urgent release")
    assert fleet.payloads()[-1] == b"urgent newest"
    fleet.clock.advance(0.1)  # the calm channel's turn: the urgent frame has crossed
    wait_for(lambda: len(fleet.received) == sent + 2, timeout_s=2, what="the calm release")
    assert fleet.payloads()[-1] == b"calm newest"


def test_without_a_beacon_nothing_is_ever_held(fleet: Fleet) -> None:
    camera = fleet.publisher("/r1/camera", 0.9)
    fleet.clock.advance(10.0)  # no estimator runs: silence means nothing
    assert not camera.holding


def test_a_malformed_beacon_is_ignored(fleet: Fleet, caplog: pytest.LogCaptureFixture) -> None:
    camera = fleet.publisher("/r1/camera", 0.9)
    fleet.beacon.put(b"{not json")
    assert "malformed link beacon" in caplog.text
    assert not camera.holding


def test_a_beacon_buffered_through_the_outage_is_stale(fleet: Fleet) -> None:
    camera = fleet.publisher("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    sent_before_the_outage = fleet.clock()
    fleet.clock.advance(2.0)
    assert camera.holding
    fleet.beacon.put(LinkBeacon(up=True, sent_s=sent_before_the_outage).encode())
    assert camera.holding  # an old "up" is no news of the link now
    fleet.say(LinkBeacon(up=True))
    assert camera.publish(b"fresh")


def test_beacons_late_for_long_are_a_new_clock_offset_not_a_backlog(fleet: Fleet) -> None:
    camera = fleet.publisher("/r1/camera", 0.9)
    fleet.say(LinkBeacon(up=True))
    step = 0.1
    for _ in range(15):  # the estimator's clock stepped back 2 s: every beacon looks late
        fleet.clock.advance(step)
        fleet.beacon.put(LinkBeacon(up=True, sent_s=fleet.clock() - 2.0).encode())
    # held meanwhile (nothing counted for STALE_RESET_S), then they count again: released
    assert camera.publish(b"after the step")
    assert not camera.holding
