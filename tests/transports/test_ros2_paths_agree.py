"""Where dbml's two ROS 2 paths meet: rosbags' CDR (``ros2``) and rclpy's (``rclpy``) agree.

Each parses what the other writes, field by field; the bytes may differ only in alignment
padding (Fast CDR leaves stale bytes there), so messages are compared parsed, not raw. The
RIHS01 hashes ``ros2`` puts in its keys equal the ones rclpy's graph shows.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from dbml.transports.codecs import IMAGE_OVERHEAD_BYTES, encode_float64, image_cdr
from dbml.transports.ros2.wire import MessageTypes

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")

from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Float64

from dbml.harness.ros2node import private_node

KILTED = MessageTypes(distro="kilted")
"""The wheels here are Kilted's: the hashes compared are that distro's."""


def _image() -> Any:
    image = Image(height=2, width=3, encoding="rgb8", is_bigendian=0, step=9, data=bytes(range(18)))
    image.header.stamp.sec = 1_700_000_000
    image.header.stamp.nanosec = 123_456_789
    image.header.frame_id = "cam"  # an odd length: padding follows
    return image


def _fields(image: Any) -> tuple[object, ...]:
    return (
        image.header.stamp.sec,
        image.header.stamp.nanosec,
        image.header.frame_id,
        image.height,
        image.width,
        image.encoding,
        image.is_bigendian,
        image.step,
        bytes(image.data),
    )


def test_rosbags_parses_rclpys_cdr_and_back() -> None:
    store = KILTED.store
    ours = _image()
    by_rclpy = serialize_message(ours)
    parsed = store.deserialize_cdr(by_rclpy, "sensor_msgs/msg/Image")
    assert _fields(parsed) == _fields(ours)
    by_rosbags = store.serialize_cdr(parsed, "sensor_msgs/msg/Image")
    assert len(by_rosbags) == len(by_rclpy)
    assert _fields(deserialize_message(bytes(by_rosbags), Image)) == _fields(ours)


def test_dbmls_hand_written_cdr_is_what_rclpy_writes() -> None:
    frame = image_cdr(84_000, stamp_ns=1_700_000_000_123_456_789)
    image = deserialize_message(frame, Image)
    assert image.header.frame_id == "camera"
    assert image.encoding == "mono8"
    assert len(image.data) == 84_000 - IMAGE_OVERHEAD_BYTES
    assert (image.header.stamp.sec, image.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    again = serialize_message(image)
    assert len(again) == len(frame)
    assert _fields(deserialize_message(again, Image)) == _fields(image)
    assert deserialize_message(encode_float64(0.8), Float64).data == 0.8
    assert serialize_message(Float64(data=0.8)) == encode_float64(0.8)


@pytest.fixture
def node(ros_domain: int) -> Iterator[Any]:
    with private_node("hashes", domain_id=ros_domain) as made:
        yield made


@pytest.mark.parametrize(
    ("msg_type", "cls"), [("sensor_msgs/msg/Image", Image), ("std_msgs/msg/Float64", Float64)]
)
def test_the_type_hashes_agree(node: Any, msg_type: str, cls: type) -> None:
    topic = f"/hash_{cls.__name__.lower()}"
    node.create_publisher(cls, topic, 1)
    (info,) = node.get_publishers_info_by_topic(topic)
    assert str(info.topic_type_hash) == KILTED.type_hash(msg_type)
