"""Transports by name: the mapping, its order and flags, and opening by name."""

from __future__ import annotations

from typing import Any

import pytest

from dbml import MemoryNetwork, open_transport
from dbml.core.errors import TransportError
from dbml.transports import DEFAULT_TRANSPORT, TRANSPORTS, MemoryTransport, Transport
from dbml.transports.registry import Discovery, camera_frame


def test_names_are_in_one_order_with_the_default_first() -> None:
    assert list(TRANSPORTS) == ["zenoh", "ros1", "rclpy", "ros2", "memory"]
    assert next(iter(TRANSPORTS)) == DEFAULT_TRANSPORT


def test_the_registry_is_read_only() -> None:
    with pytest.raises(TypeError):
        TRANSPORTS["x"] = TRANSPORTS["memory"]  # type: ignore[index]


def test_entries_say_what_a_caller_must_know() -> None:
    spans = {name for name, entry in TRANSPORTS.items() if entry.spans_processes}
    assert spans == {"zenoh", "ros1", "rclpy", "ros2"}
    assert not TRANSPORTS["ros1"].carries_metadata
    assert not TRANSPORTS["rclpy"].carries_metadata  # DDS carries no attachment...
    timed = {name for name, entry in TRANSPORTS.items() if entry.send_times}
    assert timed == {"zenoh", "rclpy", "memory"}  # ...but its sample info says when and which
    assert TRANSPORTS["zenoh"].carries_metadata
    assert TRANSPORTS["memory"].carries_metadata
    complete = {name for name, entry in TRANSPORTS.items() if entry.params_complete_at_start}
    assert complete == {"ros1"}
    for entry in TRANSPORTS.values():
        assert entry.summary
        assert "\n" not in entry.summary


def test_entries_name_themselves_and_how_their_processes_meet() -> None:
    assert all(name == entry.name for name, entry in TRANSPORTS.items())
    assert {name: entry.discovery for name, entry in TRANSPORTS.items()} == {
        "zenoh": Discovery.ZENOH,
        "ros1": Discovery.ROS_MASTER,
        "rclpy": Discovery.DDS,
        "ros2": Discovery.ZENOH_ROUTER,
        "memory": Discovery.IN_PROCESS,
    }
    assert all(
        (entry.discovery is Discovery.IN_PROCESS) != entry.spans_processes
        for entry in TRANSPORTS.values()
    )


def test_an_unknown_name_lists_the_known_ones() -> None:
    with pytest.raises(
        TransportError, match=r"transport='x' is not one of: zenoh, ros1, rclpy, ros2, memory"
    ):
        open_transport("x")


def test_memory_joins_a_given_network() -> None:
    network = MemoryNetwork()
    with (
        open_transport("memory", network=network, host="robot1") as robot,
        open_transport("memory", network=network, host="operator") as operator,
    ):
        assert isinstance(robot, MemoryTransport)
        assert robot.host == "robot1"
        robot.params.set("/dbm/strategy", "fair")
        assert operator.params.get("/dbm/strategy") == "fair"


def test_memory_alone_is_private() -> None:
    with open_transport("memory", host="a") as a, open_transport("memory", host="b") as b:
        a.params.set("/dbm/round", 1)
        assert b.params.get("/dbm/round") is None


def test_options_a_transport_cannot_use_are_refused() -> None:
    with pytest.raises(TransportError, match=r"transport='memory' takes no endpoints or config"):
        open_transport("memory", connect=["tcp/127.0.0.1:7447"])
    with pytest.raises(TransportError, match=r"transport='ros1' takes no endpoints or config"):
        open_transport("ros1", listen=["tcp/127.0.0.1:7447"])
    with pytest.raises(TransportError, match=r"transport='zenoh' takes no network"):
        open_transport("zenoh", network=MemoryNetwork())
    with pytest.raises(TransportError, match=r"transport='rclpy' takes no endpoints .* DDS"):
        open_transport("rclpy", connect=["tcp/127.0.0.1:7447"])
    with pytest.raises(TransportError, match=r"transport='rclpy' takes no ros_distro \('jazzy'\)"):
        open_transport("rclpy", ros_distro="jazzy")
    with pytest.raises(TransportError, match=r"transport='rclpy' has no priority links"):
        open_transport("rclpy", priority_links=True)


def test_optional_capabilities_have_defaults_on_every_transport() -> None:
    transport: Transport = open_transport("memory", host="h")
    with transport:
        assert transport.wait_for_peers(0.0) is True
        assert transport.confirm_param("/x", timeout_s=0.0) is True
    with pytest.raises(TransportError, match="is closed"):
        transport.declare_publisher("/t")


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"connect": ["tcp/127.0.0.1:99999"]}, r"port must be 1-65535"),
        ({"connect": ["tcp/127.0.0.1:0"]}, r"port must be 1-65535"),
        ({"listen": ["tcp/127.0.0.1:x"]}, r"port must be 0-65535"),
        ({"connect": ["127.0.0.1:7447"]}, r"must look like 'tcp/192.168.1.2:7447'"),
        ({"host": ""}, r"^host='' must be letters"),
    ],
)
def test_bad_endpoints_and_hosts_are_refused_before_a_session_opens(
    options: dict[str, Any], message: str
) -> None:
    with pytest.raises(TransportError, match=message):
        open_transport("zenoh", **options)


def test_priority_links_reach_zenoh_and_are_refused_elsewhere(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import dbml.transports.zenoh as zenoh_module

    seen: dict[str, object] = {}

    def fake(**options: object) -> object:
        seen.update(options)
        return object()

    monkeypatch.setattr(zenoh_module, "ZenohTransport", fake)
    open_transport("zenoh", connect=["tcp/127.0.0.1:7447"], priority_links=True)
    assert seen["priority_links"] is True
    for name in ("memory", "ros1"):
        with pytest.raises(TransportError, match=f"transport='{name}' has no priority links"):
            open_transport(name, priority_links=True)


class Typing(MemoryTransport):
    """A memory transport that records the topic types declared to it."""

    def __init__(self) -> None:
        super().__init__(host="h")
        self.types: dict[str, str] = {}

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        self.types[topic] = msg_type


@pytest.mark.parametrize(
    ("name", "size_bytes", "msg_type"),
    [
        ("memory", 12, None),
        ("zenoh", 12, None),
        ("ros1", 42 + 12, "sensor_msgs/Image"),
        ("rclpy", 52 + 12, "sensor_msgs/msg/Image"),
        ("ros2", 52 + 12, "sensor_msgs/msg/Image"),
    ],
)
def test_a_camera_frame_is_its_transports_and_types_its_topic(
    name: str, size_bytes: int, msg_type: str | None
) -> None:
    with Typing() as transport:
        frame = camera_frame(transport, name, "/r1/camera", size_bytes)
        assert len(frame) == size_bytes
        made = TRANSPORTS[name].frame.encode(size_bytes)
        if name == "ros2":  # stamped with the wall clock when made: bytes 4-12 of its CDR
            frame, made = frame[:4] + frame[12:], made[:4] + made[12:]
        assert frame == made
        assert transport.types == ({} if msg_type is None else {"/r1/camera": msg_type})
        if msg_type is None:
            assert frame == bytes(range(12))  # a ramp of bytes, not zeros
        else:
            with pytest.raises(TransportError, match="size_bytes=1 is below the"):
                camera_frame(transport, name, "/r2/camera", 1)
            assert "/r2/camera" not in transport.types  # refused before anything was declared
    with pytest.raises(TransportError, match=r"transport='nope' is not one of: zenoh"):
        camera_frame(transport, "nope", "/r1/camera", 12)
