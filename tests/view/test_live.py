"""The live view over the memory transport, into a sink that keeps what it is given."""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from dbml import DbmSettings
from dbml.protocol import names
from dbml.protocol.schema import ParamError, ParamValue, Writer
from dbml.runtime.params import ParamView
from dbml.testing import Fleet
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


class Viewed(Fleet):
    """R1's camera on robot1, managed by the operator's subscriber, 4 Mbit/s, and a sink."""

    def __init__(self) -> None:
        super().__init__(settings=DbmSettings(max_bandwidth_mbit=4), clock=time.monotonic)
        self.publisher(R1, host="robot1", size_bytes=84_000)
        self.watch(R1)
        self.sink = MemorySink()


@pytest.fixture
def fleet() -> Iterator[Viewed]:
    with Viewed() as viewed:
        yield viewed


OPERATOR = frozenset({Writer.OPERATOR})


def live_view(fleet: Viewed, writers: frozenset[Writer] = OPERATOR, **options: Any) -> LiveView:
    """The operator's view of the fleet, into the fleet's memory sink."""
    settings = ViewSettings(fleet.operator, ParamView.of(fleet.operator.params), writers=writers)
    return LiveView(fleet.operator, fleet.sink, settings=settings, **options)


def allocations_are(sink: MemorySink, count: int) -> bool:
    return len(sink.on(frames.ALLOCATION_TOPIC)) == count


def test_one_allocation_and_one_rate_sample_per_round(fleet: Viewed) -> None:
    view = live_view(fleet, interval_s=0.05).start()
    try:
        wait_for(lambda: bool(fleet.sink.on(frames.BUDGET_TOPIC)), what="the first look")
        assert fleet.sink.on(frames.ALLOCATION_TOPIC) == []  # nothing before a round's report
        for k in range(1, 6):  # each round heard before the next (faster ones coalesce)
            fleet.optimizer.optimize()
            wait_for(functools.partial(allocations_are, fleet.sink, k), what=f"round {k}")
    finally:
        view.close()
    allocations = fleet.sink.on(frames.ALLOCATION_TOPIC)
    rounds = [a["round"] for a in allocations]
    assert rounds == [1, 2, 3, 4, 5]  # one message per round, the optimizer's own counter
    last = allocations[-1]
    assert [c["topic"] for c in last["channels"]] == [R1]
    assert last["channels"][0]["rate_hz"] == pytest.approx(4e6 / 8 / 84_000)
    assert len(fleet.sink.on(frames.frequency_topic(R1))) == 5
    assert fleet.sink.closed


def test_the_allocation_is_the_optimizer_s_not_one_made_again(fleet: Viewed) -> None:
    """The view shows the round as reported: a floor the optimizer's links pulled back too."""
    view = live_view(fleet, interval_s=0.05).start()
    try:
        reported = fleet.optimizer.optimize().report()
        wait_for(functools.partial(allocations_are, fleet.sink, 1), what="the round")
    finally:
        view.close()
    (shown,) = fleet.sink.on(frames.ALLOCATION_TOPIC)
    assert shown == reported.as_json()
    assert set(shown) == set(frames.ALLOCATION_SCHEMA["properties"])
    assert set(shown["channels"][0]) == set(
        frames.ALLOCATION_SCHEMA["properties"]["channels"]["items"]["properties"]
    )


def test_status_changes_and_refused_values_are_logged_once(fleet: Viewed) -> None:
    view = live_view(fleet, interval_s=0.05).start()
    try:
        fleet.optimizer.optimize()
        wait_for(lambda: any(m.startswith("optimal:") for _, m in fleet.sink.text), what="status")
        fleet.network.forge({names.priority(R1): 5.0}, writer="rogue")  # a peer's bad value
        wait_for(
            lambda: any("/r1/camera/dbm/priority=5.0" in m for _, m in fleet.sink.text),
            what="the refused priority",
        )
        for k in (2, 3):  # each round heard before the next
            fleet.optimizer.optimize()
            wait_for(functools.partial(allocations_are, fleet.sink, k), what=f"round {k}")
    finally:
        view.close()
    with fleet.sink.lock:
        lines = list(fleet.sink.text)
    refused = [(level, m) for level, m in lines if m.startswith("ignored:")]
    assert refused == [(LogLevel.WARNING, refused[0][1])]  # once, however many rounds
    statuses = [m for _, m in lines if m.startswith("optimal:")]
    assert len(statuses) == 2, statuses  # the message changed once: it names the bad value
    assert "ignored: /r1/camera/dbm/priority=5.0" in statuses[1]


def test_frames_become_images_and_the_delivered_rate(fleet: Viewed) -> None:
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


def test_frames_past_the_queue_drop_the_oldest(fleet: Viewed) -> None:
    now = [0]
    view = live_view(fleet, clock=lambda: now[0])  # not started: no drain
    for k in range(MAX_QUEUED_FRAMES + 10):
        now[0] = k
        view.frame(R1, bytes(100))
    view.close()
    stamps = [t for _, _, _, t in fleet.sink.cdr]
    assert stamps == list(range(10, MAX_QUEUED_FRAMES + 10))


def test_settings_write_as_dbml_budget_does_and_refuse_what_it_refuses(fleet: Viewed) -> None:
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


def test_a_process_sets_only_what_its_role_writes(fleet: Viewed) -> None:
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


def test_a_cameras_compressed_frames_are_shown_as_they_came(fleet: Viewed) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = store.types
    message = types["sensor_msgs/msg/CompressedImage"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="pan/0"
        ),
        format="rgb8; jpeg compressed bgr8",
        data=np.frombuffer(b"\xff\xd8 not really a jpeg \xff\xd9", dtype=np.uint8),
    )
    payload = bytes(store.serialize_cdr(message, "sensor_msgs/msg/CompressedImage"))
    view = live_view(fleet, interval_s=60)
    view.frame(R1, payload, compressed=True)
    view.close()
    assert [(t, n, p) for t, n, p, _ in fleet.sink.cdr] == [
        (f"{R1}/optimized/compressed", "sensor_msgs/msg/CompressedImage", payload)
    ]
