"""The plain ROS 2 peers: their messages, priorities and reports, checked without the SDK.

The peers talk through zenoh-ros2-sdk; these tests read and write rmw_zenoh's wire format with
plain zenoh and rosbags, a third view, so a mistake the SDK and dbml share would still show.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from dbml.core.errors import DbmlError
from dbml.experiment import entry, ros2peers
from dbml.experiment.analysis import Arrival
from dbml.experiment.entry import Kind
from dbml.experiment.peers import (
    FLOAT64_TYPE,
    IMAGE_TYPE,
    OPTIMIZED_SUFFIX,
    PRIORITY_SUFFIX,
    step_priority,
)
from dbml.experiment.report import OperatorReport
from dbml.experiment.ros2peers import (
    DEFINITIONS,
    image_fields,
    router_address,
    type_hash,
)
from dbml.experiment.spec import TICK_S, RoleSpec
from dbml.harness.processes import free_port
from dbml.protocol import names
from dbml.runtime.priority import collision_priority_source
from dbml.scenarios.teleop import MAX_RATE_HZ, PAPER_TABLE2, ROBOTS, STEPS
from dbml.transports.base import Variant
from dbml.transports.memory import MemoryTransport
from dbml.transports.registry import TRANSPORTS, open_transport
from dbml.transports.zenoh.transport import open_router
from tests.conftest import wait_for
from tests.experiment.peer_process import Peer

JAZZY = get_typestore(Stores.ROS2_JAZZY)
READY_TIMEOUT_S = 30.0
"""A peer opens the SDK's session and declares its endpoints within this."""
REPORT_TIMEOUT_S = 10.0
ATTACHMENT_BYTES = 33
"""rmw_zenoh's attachment: sequence number, timestamp, GID length and 16-byte GID."""


def sdk_like_store() -> Any:
    """A typestore holding only the peers' ``.msg`` texts, as the SDK's session builds it."""
    store = get_typestore(Stores.EMPTY)
    for msg_type, definition in DEFINITIONS:
        store.register(get_types_from_msg(definition, msg_type))
    return store


def rmw_key(topic: str, msg_type: str) -> str:
    pkg, kind, name = msg_type.split("/")
    return f"0/{topic.removeprefix('/')}/{pkg}::{kind}::dds_::{name}_/{type_hash(msg_type)}"


@pytest.mark.parametrize("camera", ROBOTS, ids=lambda c: c.robot)
def test_an_image_serialises_to_the_camera_size_with_the_peers_definitions(camera: Any) -> None:
    store = sdk_like_store()
    stamp_ns = 1_795_454_170_709_408_768
    ours = bytes(
        store.serialize_cdr(
            store.types[IMAGE_TYPE](**image_fields(store.types, camera.size_bytes, stamp_ns)),
            IMAGE_TYPE,
        )
    )
    reference = bytes(
        JAZZY.serialize_cdr(
            JAZZY.types[IMAGE_TYPE](**image_fields(JAZZY.types, camera.size_bytes, stamp_ns)),
            IMAGE_TYPE,
        )
    )
    assert len(ours) == camera.size_bytes
    assert ours == reference
    message: Any = JAZZY.deserialize_cdr(ours, IMAGE_TYPE)
    assert (message.header.frame_id, message.encoding, message.height) == ("camera", "mono8", 1)
    assert message.header.stamp.sec * 10**9 + message.header.stamp.nanosec == stamp_ns


@pytest.mark.parametrize("msg_type", [IMAGE_TYPE, FLOAT64_TYPE])
def test_the_definitions_hash_as_ros2s_types(msg_type: str) -> None:
    assert sdk_like_store().hash_rihs01(msg_type) == type_hash(msg_type)
    assert type_hash(msg_type) == JAZZY.hash_rihs01(msg_type)


def test_an_image_smaller_than_its_overhead_is_refused() -> None:
    with pytest.raises(DbmlError, match="size_bytes=51"):
        image_fields(JAZZY.types, 51, 0)


def test_step_priorities_are_table2s_and_the_managed_robots() -> None:
    source = collision_priority_source(MemoryTransport(), ROBOTS[0].topic)
    for step, paper in zip(STEPS, PAPER_TABLE2, strict=True):
        for index, cell in enumerate(paper):
            event = step.events[index]
            assert step_priority(step, index) == source.update(
                event.distance_m, event.speed_m_per_s
            )
            assert round(step_priority(step, index), 2) == cell.priority


def test_the_peers_topic_names_are_dbmls() -> None:
    topic = ROBOTS[0].topic
    assert topic + OPTIMIZED_SUFFIX == Variant.OPTIMIZED.key(topic)
    assert topic + PRIORITY_SUFFIX == names.priority(topic)


@pytest.mark.parametrize(
    ("endpoint", "address"),
    [("tcp/127.0.0.1:7447", ("127.0.0.1", 7447)), ("tcp/[::1]:17447", ("[::1]", 17447))],
)
def test_router_address_takes_tcp_endpoints(endpoint: str, address: tuple[str, int]) -> None:
    assert router_address(endpoint) == address


@pytest.mark.parametrize(
    "endpoint", ["udp/127.0.0.1:7447", "tcp/127.0.0.1", "tcp/:7447", "tcp/h:0"]
)
def test_router_address_refuses_what_the_sdk_cannot_connect_to(endpoint: str) -> None:
    with pytest.raises(DbmlError, match=f"endpoint='{endpoint}'"):
        router_address(endpoint)


def test_a_missing_sdk_names_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ZENOH_CONFIG_OVERRIDE", raising=False)
    monkeypatch.setitem(sys.modules, "zenoh_ros2_sdk", None)
    with pytest.raises(DbmlError, match=r"needs zenoh-ros2-sdk, .*: pip install 'dbml\[ros2\]'$"):
        ros2peers.SdkSession("tcp/127.0.0.1:7447")


# -- the peers as processes, at a router of the test's own --------------------------------------


def session_config(endpoint: str) -> zenoh.Config:
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    return config


def _peer_env() -> dict[str, str]:
    """A peer's environment: this one's, without a zenoh override, in ROS 2 domain 0."""
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_CONFIG_OVERRIDE"}
    return {**env, "ROS_DOMAIN_ID": "0"}


@pytest.fixture
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_router([endpoint])
    try:
        yield endpoint
    finally:
        session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs


@pytest.mark.integration
def test_a_camera_publishes_images_at_its_maximum_and_table2s_priorities(router: str) -> None:
    step_s = 2.5
    camera = ROBOTS[1]
    frames: list[tuple[float, bytes, bytes | None]] = []
    priorities: list[tuple[float, float]] = []
    lock = threading.Lock()

    def on_frame(sample: zenoh.Sample) -> None:
        attachment = None if sample.attachment is None else sample.attachment.to_bytes()
        with lock:
            frames.append((time.time(), sample.payload.to_bytes(), attachment))

    def on_priority(sample: zenoh.Sample) -> None:
        message: Any = JAZZY.deserialize_cdr(sample.payload.to_bytes(), FLOAT64_TYPE)
        value = float(message.data)
        with lock:
            priorities.append((time.time(), value))

    session = zenoh.open(session_config(router))
    spec = RoleSpec(step_s=step_s, transport=TRANSPORTS["ros2"], connect=(router,))
    peer = Peer(Kind.ROS2_PEER, "r2", spec, env=_peer_env())
    try:
        session.declare_subscriber(rmw_key(camera.topic, IMAGE_TYPE), on_frame)
        session.declare_subscriber(
            rmw_key(camera.topic + PRIORITY_SUFFIX, FLOAT64_TYPE), on_priority
        )
        assert peer.next(READY_TIMEOUT_S) == {"type": "ready", "role": "r2"}

        def frames_in() -> int:
            with lock:
                return len(frames)

        wait_for(
            lambda: frames_in() >= 2 * MAX_RATE_HZ,
            timeout_s=REPORT_TIMEOUT_S,
            what="frames before start: a camera publishes before start, as a driver does",
        )
        with lock:
            got = list(frames)
        arrival_s, payload, attachment = got[-1]
        assert len(payload) == camera.size_bytes
        assert attachment is not None
        assert len(attachment) == ATTACHMENT_BYTES
        image: Any = JAZZY.deserialize_cdr(payload, IMAGE_TYPE)
        stamp = image.header.stamp
        assert 0 <= arrival_s - (stamp.sec + stamp.nanosec / 1e9) < 0.5  # stamped when sent
        span = got[-1][0] - got[-int(2 * MAX_RATE_HZ)][0]
        assert span == pytest.approx((2 * MAX_RATE_HZ - 1) / MAX_RATE_HZ, rel=0.1)

        t0 = time.time() + 0.5
        peer.send(f"start {t0!r}")

        def second_step_heard() -> bool:
            with lock:
                return any(t >= t0 + step_s for t, _ in priorities)

        wait_for(
            second_step_heard,
            timeout_s=2 * step_s + REPORT_TIMEOUT_S,
            what="a priority published in the second step",
        )
        peer.send("stop")
        assert peer.wait(REPORT_TIMEOUT_S) == 0
    finally:
        peer.close()
        session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
    first = [v for t, v in priorities if t0 <= t < t0 + step_s - 0.1]
    second = [v for t, v in priorities if t >= t0 + step_s]
    assert not [t for t, _ in priorities if t < t0 - 0.1], "no priority before step 1"
    assert len(first) >= 2, "republished within the step"
    assert set(first) == {step_priority(STEPS[0], 1)}
    assert second
    assert second[0] == step_priority(STEPS[1], 1)


@pytest.mark.integration
def test_the_operator_reports_each_frame_and_the_parameters_in_force(router: str) -> None:
    transport = open_transport(
        "ros2", host="base-station", connect=[router], listen=["tcp/127.0.0.1:0"]
    )
    session = zenoh.open(session_config(router))
    publishers = [
        session.declare_publisher(rmw_key(c.topic + OPTIMIZED_SUFFIX, IMAGE_TYPE)) for c in ROBOTS
    ]
    gid = uuid.uuid4().bytes
    sent: list[list[float]] = [[] for _ in ROBOTS]
    stop = threading.Event()

    def cameras() -> None:
        seq = 1
        while not stop.wait(1 / MAX_RATE_HZ):
            for i, camera in enumerate(ROBOTS):
                stamp_ns = time.time_ns()
                message = JAZZY.types[IMAGE_TYPE](
                    **image_fields(JAZZY.types, camera.size_bytes, stamp_ns)
                )
                attachment = struct.pack("<qqB", seq, stamp_ns, 16) + gid
                publishers[i].put(
                    bytes(JAZZY.serialize_cdr(message, IMAGE_TYPE)), attachment=attachment
                )
                sent[i].append(stamp_ns / 1e9)
            seq += 1

    thread = threading.Thread(target=cameras, daemon=True)
    peer = Peer(
        Kind.ROS2_PEER,
        "operator",
        RoleSpec(
            step_s=1.0,
            transport=TRANSPORTS["ros2"],
            host="operator",
            connect=(router,),
            listen=("tcp/127.0.0.1:0",),
        ),
        env=_peer_env(),
    )
    try:
        transport.params.set(names.current_value(ROBOTS[0].topic), 7.5)
        thread.start()
        assert peer.next(READY_TIMEOUT_S) == {"type": "ready", "role": "operator"}
        peer.send(f"start {time.time()!r}")
        rows: list[Arrival] = []
        allocated: list[tuple[float | None, ...]] = []
        deadline = time.monotonic() + REPORT_TIMEOUT_S

        def fewest() -> int:
            return min(sum(r.robot == i for r in rows) for i in range(len(ROBOTS)))

        while fewest() < 20 and time.monotonic() < deadline:
            message = peer.next(REPORT_TIMEOUT_S)
            assert message["type"] == "tick"
            report = OperatorReport.decode(message)
            assert report.tick.variants == ("optimized", "optimized")
            rows.extend(report.frames)
            allocated.append(report.tick.allocated_hz)
        peer.send("stop")
        for _ in range(int(REPORT_TIMEOUT_S / TICK_S)):  # the ticks still queued, then done
            if peer.next(REPORT_TIMEOUT_S)["type"] == "done":
                break
        else:
            pytest.fail("the operator never reported done")
        assert peer.wait(REPORT_TIMEOUT_S) == 0
    finally:
        stop.set()
        thread.join(timeout=5)
        peer.close()
        session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
        transport.close()
    assert allocated[-1][0] == 7.5, "the parameters in force, through a dbml session"
    for i, camera in enumerate(ROBOTS):
        mine = [r for r in rows if r.robot == i]
        assert len(mine) >= 20
        assert [r.seq for r in mine] == list(range(len(mine))), "a per-topic count from 0"
        assert {r.size_bytes for r in mine} == {camera.size_bytes}
        assert all(r.rate_hz is None for r in mine), "a plain ROS 2 message carries no rate"
        stamps = [r.sent_s for r in mine if r.sent_s is not None]
        assert len(stamps) == len(mine), "every frame carries its send time"
        assert all(min(abs(t - s) for s in sent[i]) < 1e-6 for t in stamps), "header.stamp"
        assert all(0 <= r.arrival_s - t < 0.5 for r, t in zip(mine, stamps, strict=True)), (
            "arrival after the send time"
        )


class _StdinUntil:
    """stdin giving ``lines``, then held open (no EOF, which would end the role) until ``eof``."""

    def __init__(self, *lines: str) -> None:
        self.lines = lines
        self.eof = threading.Event()

    def __iter__(self) -> Iterator[str]:
        yield from self.lines
        self.eof.wait(READY_TIMEOUT_S)


class _DeadCameraSdk:
    """An SDK session whose image publisher fails: the camera driver's thread dies."""

    def __init__(self, endpoint: str) -> None:
        self.store = sdk_like_store()
        self.closed = False

    def publisher(self, topic: str, msg_type: str, *, node_name: str) -> Any:
        failing = msg_type == IMAGE_TYPE

        class Publisher:
            def publish(self, **fields: Any) -> None:
                if failing:
                    raise RuntimeError("camera unplugged")

            def close(self) -> None:
                pass

        return Publisher()

    def close(self) -> None:
        self.closed = True


def test_a_camera_whose_driver_dies_ends_early_and_exits_1(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A camera peer that sends no frame must not look alive: the runner fails the run."""
    step_s = 3.0
    stdin = _StdinUntil(f"start {time.time()!r}\n")
    monkeypatch.setattr(sys, "stdin", stdin)
    monkeypatch.setattr(ros2peers, "SdkSession", _DeadCameraSdk)
    spec = RoleSpec(step_s=step_s, connect=("tcp/127.0.0.1:7447",))
    started = time.monotonic()
    try:
        with caplog.at_level(logging.CRITICAL, logger="dbml"):
            code = entry.main(["ros2-peer", "r1", spec.to_json()])
    finally:
        stdin.eof.set()
    assert code == 1
    assert time.monotonic() - started < step_s * len(STEPS) / 2  # not at the last step
    assert "camera-r1: the thread died" in caplog.text
    assert "RuntimeError: camera unplugged" in caplog.text
