"""A channel's priority from ``std_msgs/Float64`` on ``[topic]/dbm/priority``, on memory.

Every transport runs the same class; these drive it with a manual clock (the flood rule) and a
real one (its worker), and through a managed publisher and a bridge. Each middleware's own
integration test publishes the message with that middleware's tools.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import pytest

from dbml.core.config import BridgeChannel
from dbml.core.errors import TransportError
from dbml.protocol import names
from dbml.runtime.bridge import Bridge
from dbml.runtime.priority import BAD_PRIORITY_LOG_S, PRIORITY_INTERVAL_S, PriorityTopic
from dbml.runtime.publisher import ManagedPublisher
from dbml.testing import BASE, Fleet
from dbml.transports import MemoryNetwork, MemoryTransport, Publisher
from dbml.transports.codecs import encode_float64, encode_ros1_float64
from tests.conftest import wait_for

CAMERA = "/r1/camera"
NAME = names.priority(CAMERA)
SOURCE = f"{CAMERA}/dbm/priority"


class PriorityLink(Fleet):
    """A robot hearing its priority topic, the operator publishing on it, the base's store."""

    def __init__(self, *, interval_s: float = PRIORITY_INTERVAL_S) -> None:
        super().__init__(optimizer=False)
        self.robot = self.host("r1")
        # the test's tick() alone writes what is held: the manual clock is the only time
        self.topic = PriorityTopic(self.robot, CAMERA, interval_s=interval_s, worker=False)
        self.source: Publisher = self.operator.declare_publisher(SOURCE)
        self.observer = self.host(BASE)
        self.written: list[object] = []
        self.observer.params.watch(lambda n, v: self.written.append(v) if n == NAME else None)

    def publish(self, value: float) -> None:
        self.source.put(encode_float64(value))


def test_a_float64_sets_the_priority_everyone_sees() -> None:
    fleet = PriorityLink()
    fleet.publish(0.25)
    assert fleet.observer.params.get(NAME) == 0.25
    assert fleet.written == [0.25]
    fleet.topic.close()
    fleet.advance(1.0)
    fleet.publish(0.75)  # closed: heard no more
    assert fleet.written == [0.25]


def test_a_flood_writes_at_most_once_per_interval_and_the_newest_held_at_its_end() -> None:
    fleet = PriorityLink(interval_s=0.05)
    fleet.publish(0.1)  # the first: written at once
    for step, value in ((0.01, 0.2), (0.02, 0.3), (0.01, 0.4)):
        fleet.advance(step)
        fleet.publish(value)  # within the interval: held, the newest replacing the older
        assert not fleet.topic.tick()
    assert fleet.written == [0.1]
    fleet.advance(0.01)  # 0.05 after the first write: the interval is over
    assert fleet.topic.tick()
    assert fleet.written == [0.1, 0.4]
    assert not fleet.topic.tick()  # nothing held
    fleet.advance(0.03)
    fleet.publish(0.5)  # 0.03 after the last write: held
    fleet.advance(0.05)
    fleet.publish(0.6)  # past the interval: written at once, what was held is dropped
    assert not fleet.topic.tick()
    assert fleet.written == [0.1, 0.4, 0.6]
    fleet.topic.close()


def test_the_same_value_again_is_no_write() -> None:
    fleet = PriorityLink(interval_s=0.0)
    for _ in range(3):
        fleet.publish(0.5)
    assert fleet.written == [0.5]
    fleet.topic.close()


def test_the_held_value_is_written_by_the_worker_never_on_the_callback_thread() -> None:
    """Over a real clock: the message's thread returns at once, the worker writes later."""
    network = MemoryNetwork()
    robot = MemoryTransport(network, host="r1")
    topic = PriorityTopic(robot, CAMERA, interval_s=0.2)
    operator = MemoryTransport(network, host="op").declare_publisher(SOURCE)
    events: list[str] = []  # each write's thread, and when the held message's put returned
    robot.params.watch(lambda n, _v: events.append(threading.current_thread().name))
    try:
        operator.put(encode_float64(0.1))
        started = time.monotonic()
        operator.put(encode_float64(0.9))  # held: delivery is synchronous, and returns at once
        events.append("returned")
        assert robot.params.get(NAME) == 0.1
        wait_for(lambda: robot.params.get(NAME) == 0.9, timeout_s=5, what="the held value")
        assert time.monotonic() - started >= 0.15  # not before its interval ended
        # The put returned before the held value was written, and the worker wrote it.
        assert events == [threading.current_thread().name, "returned", f"dbml-priority {CAMERA}"]
        assert topic.alive
    finally:
        topic.close()


@pytest.mark.parametrize(
    ("payload", "logged"),
    [
        (encode_float64(1.5), f"ignoring a priority: {NAME}=1.5 must be within [0, 1]"),
        (encode_float64(-0.1), f"ignoring a priority: {NAME}=-0.1 must be within [0, 1]"),
        (encode_float64(math.nan), f"ignoring a priority: {NAME}=nan is not finite"),
        (encode_ros1_float64(0.5), f"{NAME}: ignoring an undecodable priority: Float64 payload"),
        (b"", f"{NAME}: ignoring an undecodable priority: Float64 payload"),
    ],
)
def test_a_bad_priority_is_ignored_and_a_flood_of_them_logged_once_per_interval(
    payload: bytes, logged: str, caplog: pytest.LogCaptureFixture
) -> None:
    fleet = PriorityLink()
    fleet.publish(0.5)
    with caplog.at_level(logging.WARNING, logger="dbml.priority"):
        for _ in range(1000):
            fleet.source.put(payload)
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1, messages
    assert messages[0].startswith(logged)
    assert messages[0].endswith(
        f"(1 value(s) ignored; logged at most every {BAD_PRIORITY_LOG_S:g} s)"
    )
    assert fleet.written == [0.5]
    fleet.topic.close()


def test_a_managed_publisher_and_a_bridge_hear_their_channels_priority() -> None:
    network = MemoryNetwork()
    robot = MemoryTransport(network, host="r1")
    operator = MemoryTransport(network, host="op")
    publisher = ManagedPublisher(robot, CAMERA, min_rate_hz=1.0, max_rate_hz=10.0, priority=0.1)
    source = robot.declare_publisher("/r2/lidar")
    bridge = Bridge(robot, BridgeChannel("/r2/lidar", min_rate_hz=1.0, max_rate_hz=10.0))
    source.put(b"scan")
    bridge.start(pace=False)
    try:
        assert operator.params.get(NAME) == 0.1
        operator.declare_publisher(SOURCE).put(encode_float64(0.8))
        operator.declare_publisher("/r2/lidar/dbm/priority").put(encode_float64(0.6))
        assert operator.params.get(NAME) == 0.8
        assert operator.params.get(names.priority("/r2/lidar")) == 0.6
    finally:
        bridge.close()
        publisher.close()
    operator.declare_publisher(SOURCE).put(encode_float64(0.3))  # closed: heard no more
    assert operator.params.get(NAME) == 0.8


def test_a_reserved_topic_is_refused() -> None:
    with pytest.raises(TransportError, match="is reserved"):
        PriorityTopic(MemoryTransport(), "/r1/camera/optimized")
