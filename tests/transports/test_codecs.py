"""The messages dbml makes itself, checked against rosbags' serialisation (CDR) and by layout."""

from __future__ import annotations

import math
import struct

import pytest

from dbml.core.errors import TransportError
from dbml.transports.codecs import (
    CDR_FLOAT64,
    FLOAT64_TYPE,
    IMAGE_OVERHEAD_BYTES,
    IMAGE_TYPE,
    ROS1_FLOAT64,
    ROS1_IMAGE_OVERHEAD_BYTES,
    decode_float64,
    decode_ros1_float64,
    encode_float64,
    encode_ros1_float64,
    image_cdr,
    image_ros1,
    ramp,
)
from dbml.transports.ros2.wire import MessageTypes


@pytest.fixture(scope="module")
def types() -> MessageTypes:
    return MessageTypes()


@pytest.mark.parametrize("size_bytes", [IMAGE_OVERHEAD_BYTES, 21_000, 84_000])
def test_image_is_exactly_the_size_asked(types: MessageTypes, size_bytes: int) -> None:
    frame = image_cdr(size_bytes, stamp_ns=1_700_000_000_123_456_789)
    assert len(frame) == size_bytes
    image = types.store.deserialize_cdr(frame, IMAGE_TYPE)
    assert image.header.frame_id == "camera"  # type: ignore[attr-defined]
    assert image.header.stamp.sec == 1_700_000_000  # type: ignore[attr-defined]
    assert image.encoding == "mono8"  # type: ignore[attr-defined]
    assert len(image.data) == size_bytes - IMAGE_OVERHEAD_BYTES  # type: ignore[attr-defined]
    assert bytes(types.store.serialize_cdr(image, IMAGE_TYPE)) == frame


def test_image_below_its_overhead_is_refused() -> None:
    with pytest.raises(TransportError, match="size_bytes=51 is below the 52-byte minimum"):
        image_cdr(51)


def test_float64_cdr(types: MessageTypes) -> None:
    assert encode_float64(1.5).hex() == "00010000000000000000f83f"
    assert decode_float64(encode_float64(0.25)) == 0.25
    message = types.store.types[FLOAT64_TYPE](data=0.75)
    assert decode_float64(bytes(types.store.serialize_cdr(message, FLOAT64_TYPE))) == 0.75
    assert math.isnan(decode_float64(encode_float64(math.nan)))
    with pytest.raises(TransportError, match="is not 12 bytes of CDR"):
        decode_float64(b"\x00\x01\x00\x00\x00")


def test_the_codecs_name_the_types_their_topics_are_declared_as() -> None:
    assert (CDR_FLOAT64.msg_type, ROS1_FLOAT64.msg_type) == (FLOAT64_TYPE, "std_msgs/Float64")
    assert CDR_FLOAT64.decode(CDR_FLOAT64.encode(0.5)) == 0.5
    assert ROS1_FLOAT64.decode(ROS1_FLOAT64.encode(0.5)) == 0.5


def test_float64_ros1_is_its_eight_bytes() -> None:
    assert encode_ros1_float64(1.5).hex() == "000000000000f83f"
    assert decode_ros1_float64(encode_ros1_float64(0.25)) == 0.25
    for payload in (b"", bytes(7), encode_float64(0.5)):  # a CDR one is 12 bytes: refused
        with pytest.raises(TransportError, match="is not 8 bytes"):
            decode_ros1_float64(payload)


@pytest.mark.parametrize("size_bytes", [ROS1_IMAGE_OVERHEAD_BYTES, 21_000, 84_000])
def test_a_ros1_image_is_exactly_the_size_asked_in_rospys_layout(size_bytes: int) -> None:
    frame = image_ros1(size_bytes)
    assert len(frame) == size_bytes
    pixels = size_bytes - ROS1_IMAGE_OVERHEAD_BYTES
    seq, secs, nsecs, frame_id, height, width, encoding = struct.unpack_from("<7I", frame)
    assert (seq, secs, nsecs, frame_id, height, width, encoding) == (0, 0, 0, 0, 1, pixels, 5)
    assert frame[28:33] == b"mono8"
    assert struct.unpack_from("<BII", frame, 33) == (0, pixels, pixels)
    assert frame[42:] == bytes(pixels)
    with pytest.raises(TransportError, match="size_bytes=41 is below the 42-byte minimum"):
        image_ros1(41)


def test_a_raw_frame_is_a_ramp_of_the_size_asked() -> None:
    assert ramp(12) == bytes(range(12))
    assert ramp(600) == (bytes(range(256)) * 3)[:600]
    assert ramp(0) == b""
