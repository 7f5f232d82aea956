"""The live view over the memory transport, into a sink that keeps what it is given."""

from __future__ import annotations

import functools
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import pytest

from dbml import (
    DbmSettings,
    ManagedPublisher,
    ManagedSubscriber,
    MemoryNetwork,
    OptimizerNode,
    open_transport,
)
from dbml.protocol import names
from dbml.protocol.schema import ParamError, ParamValue, Writer
from dbml.runtime.params import ParamView
from dbml.transports.base import Transport
from dbml.view import frames
from dbml.view.frames import LogLevel
from dbml.view.live import MAX_QUEUED_FRAMES, LiveView, ViewSettings
from dbml.view.target import ViewEndpoint
from tests.conftest import wait_for

R1 = "/r1/camera"


@dataclass
class MemorySink:
    """Every call, in order (the view's one thread writes; the test reads under the lock)."""

    json: list[tuple[str, dict[str, Any], int]] = field(default_factory=list)
    cdr: list[tuple[str, str, bytes, int]] = field(default_factory=list)
    text: list[tuple[LogLevel, str]] = field(default_factory=list)
    parameters: list[dict[str, ParamValue]] = field(default_factory=list)
    closed: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def address(self) -> ViewEndpoint | None:
        return None

    def log_json(
        self, topic: str, schema: Mapping[str, Any], message: Mapping[str, Any], *, time_ns: int
    ) -> None:
        assert schema["type"] == "object"
        with self.lock:
            self.json.append((topic, dict(message), time_ns))

    def log_cdr(
        self, topic: str, schema_name: str, definition: str, payload: bytes, *, time_ns: int
    ) -> None:
        assert definition.startswith("std_msgs/Header header")
        with self.lock:
            self.cdr.append((topic, schema_name, payload, time_ns))

    def log_text(self, level: LogLevel, message: str, *, time_ns: int) -> None:
        with self.lock:
            self.text.append((level, message))

    def publish_parameters(self, values: Mapping[str, ParamValue]) -> None:
        with self.lock:
            self.parameters.append(dict(values))

    def close(self) -> None:
        self.closed = True

    def on(self, topic: str) -> list[dict[str, Any]]:
        with self.lock:
            return [message for t, message, _ in self.json if t == topic]


@dataclass
class Fleet:
    network: MemoryNetwork
    publisher: ManagedPublisher
    optimizer: OptimizerNode
    operator: Transport
    sink: MemorySink


@pytest.fixture
def fleet() -> Iterator[Fleet]:
    network = MemoryNetwork()
    publisher = ManagedPublisher(
        open_transport("memory", network=network, host="robot1"),
        R1,
        min_rate_hz=1,
        max_rate_hz=16,
    )
    operator = open_transport("memory", network=network, host="operator")
    subscriber = ManagedSubscriber(operator, R1, lambda _s: None)  # remote: R1 is managed
    optimizer = OptimizerNode(
        open_transport("memory", network=network, host="base"),
        settings=DbmSettings(max_bandwidth_mbit=4),
    )
    publisher.publish(bytes(84_000))
    yield Fleet(network, publisher, optimizer, operator, MemorySink())
    optimizer.stop()
    subscriber.close()
    publisher.close()


OPERATOR = frozenset({Writer.OPERATOR})


def live_view(fleet: Fleet, writers: frozenset[Writer] = OPERATOR, **options: Any) -> LiveView:
    """The operator's view of the fleet, into the fleet's memory sink."""
    settings = ViewSettings(fleet.operator, ParamView.of(fleet.operator.params), writers=writers)
    return LiveView(fleet.operator, fleet.sink, settings=settings, **options)


def allocations_are(sink: MemorySink, count: int) -> bool:
    return len(sink.on(frames.ALLOCATION_TOPIC)) == count


def test_one_allocation_and_one_rate_sample_per_round(fleet: Fleet) -> None:
    view = live_view(fleet, interval_s=60).start()
    try:
        wait_for(lambda: bool(fleet.sink.on(frames.ALLOCATION_TOPIC)), what="the first look")
        seen = len(fleet.sink.on(frames.ALLOCATION_TOPIC))
        for k in range(1, 6):  # each round heard before the next (faster ones coalesce)
            fleet.optimizer.optimize()
            wait_for(functools.partial(allocations_are, fleet.sink, seen + k), what=f"round {k}")
    finally:
        view.close()
    allocations = fleet.sink.on(frames.ALLOCATION_TOPIC)
    rounds = [a["round"] for a in allocations[seen:]]
    assert rounds == sorted(set(rounds)), rounds  # one message per round, in order
    assert len(rounds) == 5
    last = allocations[-1]
    assert [c["topic"] for c in last["channels"]] == [R1]
    assert last["channels"][0]["rate_hz"] == pytest.approx(4e6 / 8 / 84_000)
    rated = sum(1 for a in allocations if a["channels"] and a["channels"][0]["rate_hz"])
    assert len(fleet.sink.on(frames.frequency_topic(R1))) == rated
    assert fleet.sink.closed


def test_status_changes_and_refused_values_are_logged_once(fleet: Fleet) -> None:
    view = live_view(fleet, interval_s=0.05).start()
    try:
        fleet.optimizer.optimize()
        wait_for(lambda: any(m.startswith("optimal:") for _, m in fleet.sink.text), what="status")
        fleet.network.forge({names.priority(R1): 5.0}, writer="rogue")  # a peer's bad value
        wait_for(
            lambda: any("/r1/camera/dbm/priority=5.0" in m for _, m in fleet.sink.text),
            what="the refused priority",
        )
        fleet.optimizer.optimize()
        fleet.optimizer.optimize()
        wait_for(lambda: len(fleet.sink.on(frames.ALLOCATION_TOPIC)) >= 3, what="rounds")
    finally:
        view.close()
    with fleet.sink.lock:
        lines = list(fleet.sink.text)
    refused = [(level, m) for level, m in lines if m.startswith("ignored:")]
    assert refused == [(LogLevel.WARNING, refused[0][1])]  # once, however many rounds
    statuses = [m for _, m in lines if m.startswith("optimal:")]
    assert len(statuses) == 2, statuses  # the message changed once: it names the bad value
    assert "ignored: /r1/camera/dbm/priority=5.0" in statuses[1]


def test_frames_become_images_and_the_delivered_rate(fleet: Fleet) -> None:
    now = [10 * 10**9]
    view = live_view(fleet, interval_s=60, clock=lambda: now[0], monotonic=lambda: now[0])
    for k in range(5):  # 5 frames 0.1 s apart, then the view looks 0.5 s after the first
        now[0] = 10 * 10**9 + k * 10**8
        view.frame(R1, bytes(range(256)) * 82 + bytes(8))  # 21,000 bytes
    now[0] = 10 * 10**9 + 5 * 10**8
    view.close()  # writes what is queued, and looks once
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    assert [(t, n) for t, n, _, _ in fleet.sink.cdr] == [
        (f"{R1}/optimized", "sensor_msgs/msg/Image")
    ] * 5
    image: Any = store.deserialize_cdr(fleet.sink.cdr[0][2], "sensor_msgs/msg/Image")
    assert (image.height, image.width, image.encoding) == (100, 210, "mono8")
    assert bytes(image.data[:256]) == bytes(range(256))
    assert (image.header.stamp.sec, image.header.stamp.nanosec) == (10, 0)
    assert fleet.sink.on(frames.delivered_topic(R1)) == [{"data": 5.0}]


def test_frames_past_the_queue_drop_the_oldest(fleet: Fleet) -> None:
    now = [0]
    view = live_view(fleet, clock=lambda: now[0])  # not started: no drain
    for k in range(MAX_QUEUED_FRAMES + 10):
        now[0] = k
        view.frame(R1, bytes(100))
    view.close()
    stamps = [t for _, _, _, t in fleet.sink.cdr]
    assert stamps == list(range(10, MAX_QUEUED_FRAMES + 10))


def test_settings_write_as_dbml_budget_does_and_refuse_what_it_refuses(fleet: Fleet) -> None:
    view = live_view(fleet, interval_s=0.05).start()
    try:
        settings = view.settings
        wait_for(lambda: R1 in settings.topics(), what="the channel")
        assert settings.current()[names.BANDWIDTH] == 4.0
        with pytest.raises(ParamError, match="max_bandwidth_in_mbit=-3"):
            settings.set(names.BANDWIDTH, -3)
        with pytest.raises(ParamError, match=r"max_bandwidth_in_mbit='8': is not a number|'8'"):
            settings.set(names.BANDWIDTH, "8")
        # Nothing was written: the store itself (not a view that would refuse -3 anyway).
        assert fleet.operator.params.get(names.BANDWIDTH) == 4.0
        assert fleet.optimizer.dbm().bandwidth_mbit == 4.0
        assert settings.set(names.BANDWIDTH, 8) == 8.0
        wait_for(lambda: fleet.optimizer.budget_mbit() == 8.0, what="the optimizer's budget")
        wait_for(
            lambda: any(p.get(names.BANDWIDTH) == 8.0 for p in list(fleet.sink.parameters)),
            what="the changed value published to the clients",
        )
    finally:
        view.close()
    assert fleet.optimizer.optimize().rates_hz[R1] == pytest.approx(8e6 / 8 / 84_000)


def test_a_process_sets_only_what_its_role_writes(fleet: Fleet) -> None:
    """An optimizer's process serving the view does not write the budget.

    Its own store would take the value, whatever a secure fleet's rules let through to others.
    """
    view = live_view(fleet, writers=frozenset({Writer.OPTIMIZER, Writer.ESTIMATOR}))
    try:
        wait_for(lambda: R1 in view.settings.topics(), what="the channel")
        with pytest.raises(ParamError, match=r"does not write it \(written by: operator\)"):
            view.settings.set(names.BANDWIDTH, 8.0)
        with pytest.raises(ParamError, match="written by: operator, publisher"):
            view.settings.set(names.priority(R1), 1.0)
        assert fleet.operator.params.get(names.BANDWIDTH) == 4.0
    finally:
        view.close()
