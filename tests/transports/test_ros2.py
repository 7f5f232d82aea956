"""The ros2 transport against an independent ROS 2 peer (zenoh-ros2-sdk) over a real router.

Each test runs its own zenoh router (``open_router``) on a free loopback port; dbml's transports
and the SDK's session connect to it, as ROS 2 nodes connect to ``rmw_zenohd``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
import zenoh

from dbml.core.errors import TransportError
from dbml.harness.processes import free_port
from dbml.runtime.graph import summarize
from dbml.runtime.publisher import ManagedPublisher
from dbml.transports import TRANSPORTS, GraphEntry, Role, Sample, Variant, open_transport
from dbml.transports.ros2 import Ros2Transport, node_name_for, open_router, resolve_domain_id
from dbml.transports.ros2msg import (
    FLOAT64_TYPE,
    IMAGE_TYPE,
    LivelinessToken,
    MessageTypes,
    TokenKind,
    decode_attachment,
    parse_token,
)
from tests.conftest import wait_for

sdk = pytest.importorskip("zenoh_ros2_sdk")
sdk_session = pytest.importorskip("zenoh_ros2_sdk.session")

TIMEOUT_S = 10.0
TYPES = MessageTypes()


@pytest.fixture
def router_port() -> Iterator[int]:
    port = free_port()
    router = open_router([f"tcp/127.0.0.1:{port}"])
    yield port
    router.close()  # type: ignore[no-untyped-call]


@pytest.fixture
def ros2(router_port: int) -> Iterator[Callable[[str], Ros2Transport]]:
    made: list[Ros2Transport] = []

    def make(host: str) -> Ros2Transport:
        transport = Ros2Transport(
            host=host, connect=[f"tcp/127.0.0.1:{router_port}"], listen=["tcp/127.0.0.1:0"]
        )
        made.append(transport)
        return transport

    yield make
    for transport in made:
        transport.close()


@dataclass
class Sdk:
    """The SDK's ROS 2 endpoints of one test, on its per-process session (closed after)."""

    port: int
    endpoints: list[Any] = field(default_factory=list)

    def _prepare(self, msg_type: str) -> dict[str, Any]:
        manager = sdk_session.ZenohSession.get_instance("127.0.0.1", self.port)
        # Offline, the SDK can neither fetch definitions nor hash nested types: give it ours.
        manager.store = TYPES.store
        manager._registered_types[msg_type] = msg_type
        return {
            "msg_type": msg_type,
            "msg_definition": TYPES.definition(msg_type),
            "type_hash": TYPES.type_hash(msg_type),
            "router_ip": "127.0.0.1",
            "router_port": self.port,
        }

    def subscriber(self, topic: str, msg_type: str, callback: Callable[[Any], None]) -> Any:
        endpoint = sdk.ROS2Subscriber(topic=topic, callback=callback, **self._prepare(msg_type))
        self.endpoints.append(endpoint)
        return endpoint

    def publisher(self, topic: str, msg_type: str) -> Any:
        endpoint = sdk.ROS2Publisher(topic=topic, **self._prepare(msg_type))
        self.endpoints.append(endpoint)
        return endpoint


@pytest.fixture
def ros2_sdk(router_port: int) -> Iterator[Sdk]:
    peer = Sdk(router_port)
    yield peer
    for endpoint in peer.endpoints:
        endpoint.close()
    instance = sdk_session.ZenohSession._instance
    if instance is not None:
        instance.close()


def remote_optimized(transport: Ros2Transport, topic: str) -> list[GraphEntry]:
    return [
        e
        for e in transport.graph.entries()
        if e.host.startswith("ros2:")
        and (e.role, e.topic, e.variant) == (Role.SUBSCRIBER, topic, Variant.OPTIMIZED)
    ]


def test_registry_entry_and_options() -> None:
    entry = TRANSPORTS["ros2"]
    assert (entry.carries_metadata, entry.spans_processes, entry.params_complete_at_start) == (
        False,
        True,
        False,
    )
    with pytest.raises(TransportError, match=r"transport='zenoh' takes no domain_id \(3\)"):
        open_transport("zenoh", domain_id=3)
    with pytest.raises(TransportError, match="transport='memory' takes no ros_distro"):
        open_transport("memory", ros_distro="jazzy")
    with pytest.raises(TransportError, match="ros distro 'foxy' is not one of"):
        open_transport("ros2", ros_distro="foxy")
    with pytest.raises(TransportError, match=r"ros domain id 233 must be an integer 0\.\.232"):
        open_transport("ros2", domain_id=233)


def test_domain_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert resolve_domain_id() == 42
    assert resolve_domain_id(7) == 7
    monkeypatch.setenv("ROS_DOMAIN_ID", "999")
    with pytest.raises(TransportError, match="ros domain id '999'"):
        resolve_domain_id()
    assert node_name_for("robot-1.lab") == "dbml_robot_1_lab"


def test_types_and_camera_frames(ros2: Callable[[str], Ros2Transport]) -> None:
    transport = ros2("host-a")
    with pytest.raises(TransportError, match="'foo/msg/Bar' is not known to the jazzy"):
        transport.set_topic_type("/x", "foo/msg/Bar")
    assert len(transport.camera_frame("/r1/camera", 84_000)) == 84_000
    with pytest.raises(TransportError, match="size_bytes=10 is below the 52-byte minimum"):
        transport.camera_frame("/r1/camera", 10)
    transport.set_topic_type("/chatter", "std_msgs/msg/String")
    with pytest.raises(TransportError, match="has type 'std_msgs/msg/String', not"):
        transport.camera_frame("/chatter", 100)


def test_sdk_subscriber_receives_managed_frames_and_is_a_graph_entry(
    ros2: Callable[[str], Ros2Transport], ros2_sdk: Sdk
) -> None:
    transport = ros2("robot-1")
    frames: list[Any] = []
    subscriber = ros2_sdk.subscriber("/r1/camera/optimized", IMAGE_TYPE, frames.append)
    wait_for(
        lambda: len(remote_optimized(transport, "/r1/camera")) == 1,
        timeout_s=TIMEOUT_S,
        what="the SDK subscription in the graph",
    )
    frame = transport.camera_frame("/r1/camera", 21_000)
    publisher = ManagedPublisher(
        transport, "/r1/camera", min_rate_hz=50.0, max_rate_hz=100.0, failsafe_periods=0.01
    )
    try:
        wait_for(
            lambda: "/r1/camera" in summarize(transport.graph.entries()).managed,
            timeout_s=TIMEOUT_S,
            what="the channel managed for the ROS 2 subscriber",
        )

        def two_received() -> bool:
            publisher.publish(frame)
            return len(frames) >= 2

        wait_for(two_received, timeout_s=TIMEOUT_S, what="two frames at the SDK subscriber")
    finally:
        publisher.close()
    assert (frames[0].header.frame_id, frames[0].encoding, len(frames[0].data)) == (
        "camera",
        "mono8",
        21_000 - 52,
    )
    subscriber.close()
    wait_for(
        lambda: not remote_optimized(transport, "/r1/camera"),
        timeout_s=TIMEOUT_S,
        what="the SDK subscription to leave the graph",
    )


def test_sdk_publisher_type_and_messages(
    ros2: Callable[[str], Ros2Transport], ros2_sdk: Sdk
) -> None:
    transport = ros2("host-a")
    assert transport.topic_type("/r1/camera", timeout_s=0.05) is None
    got: list[Sample] = []
    transport.subscribe("/r1/camera", got.append)
    publisher = ros2_sdk.publisher("/r1/camera", "std_msgs/msg/String")
    assert transport.topic_type("/r1/camera", timeout_s=TIMEOUT_S) == "std_msgs/msg/String"
    assert not remote_optimized(transport, "/r1/camera"), "a publisher is not a channel"

    def received() -> bool:
        publisher.publish(data="hello")
        return bool(got)

    wait_for(received, timeout_s=TIMEOUT_S, what="the SDK's message")
    message = TYPES.store.deserialize_cdr(got[0].payload, "std_msgs/msg/String")
    assert message.data == "hello"  # type: ignore[attr-defined]
    assert got[0].attachment is not None
    assert len(decode_attachment(got[0].attachment).gid) == 16


def test_ros2_priority_sets_the_param_and_bad_values_are_logged(
    ros2: Callable[[str], Ros2Transport], ros2_sdk: Sdk, caplog: pytest.LogCaptureFixture
) -> None:
    transport = ros2("robot-1")
    managed = transport.declare_publisher("/r1/camera", Variant.OPTIMIZED)
    publisher = ros2_sdk.publisher("/r1/camera/dbm/priority", FLOAT64_TYPE)
    name = "/r1/camera/dbm/priority"

    def applied(value: float) -> Callable[[], bool]:
        def check() -> bool:
            publisher.publish(data=value)
            return transport.params.get(name) == value

        return check

    wait_for(applied(0.25), timeout_s=TIMEOUT_S, what="priority 0.25 from ROS 2")
    with caplog.at_level(logging.WARNING, logger="dbml.ros2"):
        for bad in (1.5, math.nan):
            publisher.publish(data=bad)
            wait_for(
                lambda bad=bad: f"ignoring priority {bad!r}" in caplog.text,  # type: ignore[misc]
                timeout_s=TIMEOUT_S,
                what=f"priority {bad} refused",
            )
    wait_for(applied(0.75), timeout_s=TIMEOUT_S, what="priority 0.75 after the bad ones")
    assert name in caplog.text
    managed.close()


def test_dbml_tokens_describe_its_endpoints_and_are_not_double_counted(
    ros2: Callable[[str], Ros2Transport],
) -> None:
    a, b = ros2("host-a"), ros2("host-b")
    seen: list[str] = []
    gone: list[str] = []

    def on_token(sample: zenoh.Sample) -> None:
        (seen if sample.kind == zenoh.SampleKind.PUT else gone).append(str(sample.key_expr))

    token_subscriber = b.session.liveliness().declare_subscriber(
        f"@ros2_lv/{a.domain_id}/{a.zid}/**", on_token, history=True
    )
    a.subscribe("/r1/camera", lambda _s: None, Variant.OPTIMIZED)
    publisher = a.declare_publisher("/r1/camera", Variant.OPTIMIZED)
    wait_for(lambda: len(seen) >= 4, timeout_s=TIMEOUT_S, what="node, MS, MP and priority MS")
    tokens = [parse_token(key) for key in seen]
    assert {(t.kind.value, t.topic) for t in tokens} >= {
        ("NN", None),
        ("MS", "/r1/camera/optimized"),
        ("MP", "/r1/camera/optimized"),
        ("MS", "/r1/camera/dbm/priority"),
    }
    assert {t.node_name for t in tokens} == {"dbml_host_a"}
    assert all(t.qos == "1:2:1,10:,:,:,," for t in tokens if t.qos is not None)
    # b has read a's tokens (the MP after the MS): a's subscription is in dbml's graph only.
    assert b.topic_type("/r1/camera/optimized", timeout_s=TIMEOUT_S) == IMAGE_TYPE
    assert not remote_optimized(b, "/r1/camera"), "a dbml session's subscription counts once"
    publisher.close()
    wait_for(
        lambda: {parse_token(k).kind.value for k in gone} == {"MP", "MS"},
        timeout_s=TIMEOUT_S,
        what="the publisher's MP and its priority MS withdrawn",
    )
    a.close()
    wait_for(lambda: len(gone) == len(seen), timeout_s=TIMEOUT_S, what="every token withdrawn")
    token_subscriber.undeclare()  # type: ignore[no-untyped-call]


def test_foreign_tokens_are_validated_and_counted(
    ros2: Callable[[str], Ros2Transport], router_port: int, caplog: pytest.LogCaptureFixture
) -> None:
    transport = ros2("host-a")
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{router_port}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    foreign = zenoh.open(config)
    try:
        zid = str(foreign.info.zid())
        liveliness = foreign.liveliness()
        with caplog.at_level(logging.WARNING, logger="dbml.ros2"):
            bad = liveliness.declare_token(f"@ros2_lv/0/{zid}/0/1/XX/%/%/n")
            wait_for(
                lambda: "kind 'XX' is not one of" in caplog.text,
                timeout_s=TIMEOUT_S,
                what="the malformed token logged",
            )
        good = LivelinessToken(
            0,
            zid,
            0,
            2,
            TokenKind.SUBSCRIPTION,
            "viewer",
            topic="/r2/lidar/optimized",
            msg_type=IMAGE_TYPE,
            type_hash=TYPES.type_hash(IMAGE_TYPE),
            qos="::,10:,:,:,,",
        )
        token = liveliness.declare_token(good.key())
        wait_for(
            lambda: (
                remote_optimized(transport, "/r2/lidar")
                == [
                    GraphEntry(
                        Role.SUBSCRIBER,
                        f"ros2:{zid}",
                        "/r2/lidar",
                        Variant.OPTIMIZED,
                        f"ros2:{zid}/0/2",
                    )
                ]
            ),
            timeout_s=TIMEOUT_S,
            what="the foreign subscription as a graph entry",
        )
        token.undeclare()  # type: ignore[no-untyped-call]
        wait_for(lambda: not remote_optimized(transport, "/r2/lidar"), what="its withdrawal")
        bad.undeclare()  # type: ignore[no-untyped-call]
    finally:
        foreign.close()  # type: ignore[no-untyped-call]


def test_the_sdks_topic_list_shows_dbmls_topics_with_their_types(
    router_port: int, ros2: Callable[[str], Ros2Transport]
) -> None:
    """``zenoh-ros2 topic list -t`` (the SDK's ``ros2 topic list``) reads dbml's tokens."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    cli = shutil.which("zenoh-ros2") or str(Path(sys.executable).with_name("zenoh-ros2"))
    router = f"127.0.0.1:{router_port}"
    command = [cli, "--no-daemon", "--router", router, "--timeout", "2", "topic", "list", "-t"]
    transport = ros2("r1")
    publisher = ManagedPublisher(transport, "/r1/camera", min_rate_hz=1.0, max_rate_hz=16.0)
    listed = ""
    try:
        for _ in range(5):  # discovery is bounded by the CLI's own timeout; retried a few times
            done = subprocess.run(
                command,
                capture_output=True,
                text=True,
                timeout=30,
                check=False,
            )
            listed = done.stdout
            if "/r1/camera/optimized" in listed:
                break
        lines = {line.strip() for line in listed.splitlines()}
        assert f"/r1/camera/optimized [{IMAGE_TYPE}]" in lines, listed
        assert f"/r1/camera/dbm/priority [{FLOAT64_TYPE}]" in lines, listed
    finally:
        publisher.close()
