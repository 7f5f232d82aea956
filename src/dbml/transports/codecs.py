"""The few messages dbml makes or reads itself, in each middleware's serialisation: pure.

- A ``std_msgs/Float64``: a priority published on ``[topic]/dbm/priority`` by any tool
  (``ros2 topic pub``, ``rostopic pub``). A transport supplies its ``Float64Codec``
  (``Transport.float64``): CDR, ROS 2's serialisation, over ``ros2`` and ``rclpy`` as they carry
  it, and over ``zenoh`` and ``memory`` too, so a tool of rmw_zenoh's could publish one on dbml's
  keys; ROS 1's own serialisation over ``ros1``.
- A synthetic ``sensor_msgs/Image`` of an exact size: the demo's camera frame
  (``FrameCodec``, in each transport's registry entry), so the size the optimizer sees is the
  size asked for. Raw bytes where topics carry untyped bytes.

Every function here is one of its arguments: no session, no clock.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

from dbml.core.errors import TransportError

__all__ = [
    "CDR_FLOAT64",
    "CDR_IMAGE",
    "FLOAT64_TYPE",
    "IMAGE_OVERHEAD_BYTES",
    "IMAGE_TYPE",
    "RAW_FRAME",
    "ROS1_FLOAT64",
    "ROS1_IMAGE",
    "ROS1_IMAGE_OVERHEAD_BYTES",
    "Float64Codec",
    "FrameCodec",
    "decode_float64",
    "decode_ros1_float64",
    "encode_float64",
    "encode_ros1_float64",
    "image_cdr",
    "image_ros1",
    "ramp",
]

IMAGE_TYPE = "sensor_msgs/msg/Image"
FLOAT64_TYPE = "std_msgs/msg/Float64"
IMAGE_OVERHEAD_BYTES = 52
"""A mono8 CDR Image of frame ``camera``, serialised with no pixels (encapsulation included)."""
ROS1_IMAGE_OVERHEAD_BYTES = 42
"""A mono8 ROS 1 Image with an empty frame id, serialised with no pixels."""
_CDR_LE = b"\x00\x01\x00\x00"
_CDR_BE = b"\x00\x00\x00\x00"
_FLOAT64 = struct.Struct("<d")
_CDR_FLOAT64_SIZE_BYTES = len(_CDR_LE) + _FLOAT64.size
_FRAME_ID = "camera"
_ENCODING = "mono8"
_RAMP = bytes(range(256))


@dataclass(frozen=True, slots=True)
class Float64Codec:
    """A ``std_msgs/Float64`` as a middleware serialises it, and the type to declare it as."""

    msg_type: str
    encode: Callable[[float], bytes]
    decode: Callable[[bytes], float]
    """``TransportError`` for a payload that is not one."""


@dataclass(frozen=True, slots=True)
class FrameCodec:
    """A synthetic camera frame of an exact size as a middleware carries it.

    ``msg_type`` is the type its topic is declared as first (None: untyped bytes).
    """

    msg_type: str | None
    encode: Callable[[int], bytes]
    """A frame of exactly ``size_bytes``; ``TransportError`` below the message's overhead."""


def encode_float64(value: float) -> bytes:
    """A ``std_msgs/msg/Float64`` as CDR (little-endian, with its encapsulation header)."""
    return _CDR_LE + _FLOAT64.pack(value)


def decode_float64(payload: bytes) -> float:
    """The value of a CDR ``std_msgs/msg/Float64``; ``TransportError`` if it is not one."""
    if len(payload) != _CDR_FLOAT64_SIZE_BYTES or payload[:4] not in {_CDR_LE, _CDR_BE}:
        raise TransportError(f"Float64 payload {payload[:16].hex()} is not 12 bytes of CDR")
    order = "<" if payload[:4] == _CDR_LE else ">"
    value: float = struct.unpack(order + "d", payload[4:])[0]
    return value


def encode_ros1_float64(value: float) -> bytes:
    """A ROS 1 ``std_msgs/Float64``: its 8 bytes, little-endian."""
    return _FLOAT64.pack(value)


def decode_ros1_float64(payload: bytes) -> float:
    """The value of a ROS 1 ``std_msgs/Float64``; ``TransportError`` if it is not one."""
    if len(payload) != _FLOAT64.size:
        raise TransportError(f"Float64 payload {payload[:16].hex()} is not 8 bytes")
    value: float = _FLOAT64.unpack(payload)[0]
    return value


def _cdr_string(text: str) -> bytes:
    raw = text.encode() + b"\x00"
    return struct.pack("<I", len(raw)) + raw


def _pixels(size_bytes: int, overhead: int) -> int:
    pixels = size_bytes - overhead
    if pixels < 0:
        raise TransportError(f"image size_bytes={size_bytes} is below the {overhead}-byte minimum")
    return pixels


def image_cdr(size_bytes: int, *, stamp_ns: int = 0) -> bytes:
    """A mono8 ``sensor_msgs/msg/Image`` of frame ``camera`` serialised to exactly ``size_bytes``.

    One row of ``size_bytes - 52`` pixels: the size the optimizer sees is the size asked for.
    """
    pixels = _pixels(size_bytes, IMAGE_OVERHEAD_BYTES)
    sec, nanosec = divmod(max(0, stamp_ns), 1_000_000_000)
    body = bytearray(struct.pack("<iI", sec, nanosec) + _cdr_string(_FRAME_ID))
    body += bytes(-len(body) % 4)
    body += struct.pack("<II", 1, pixels) + _cdr_string(_ENCODING) + b"\x00"  # is_bigendian
    body += bytes(-len(body) % 4)
    body += struct.pack("<II", pixels, pixels)  # step, then the data's length
    frame = _CDR_LE + bytes(body) + bytes(pixels)
    assert len(frame) == size_bytes, "the Image layout must keep its 52-byte overhead"
    return frame


def image_ros1(size_bytes: int) -> bytes:
    """A mono8 ROS 1 ``sensor_msgs/Image`` serialised to exactly ``size_bytes``.

    A zero header, one row of ``size_bytes - 42`` pixels (as rospy serialises one).
    """
    pixels = _pixels(size_bytes, ROS1_IMAGE_OVERHEAD_BYTES)
    encoding = _ENCODING.encode()
    frame = (
        struct.pack("<IIII", 0, 0, 0, 0)  # seq, stamp (secs, nsecs), an empty frame id
        + struct.pack("<III", 1, pixels, len(encoding))  # height, width, the encoding's length
        + encoding
        + struct.pack("<BII", 0, pixels, pixels)  # is_bigendian, step, the data's length
        + bytes(pixels)
    )
    assert len(frame) == size_bytes, "the Image layout must keep its 42-byte overhead"
    return frame


def ramp(size_bytes: int) -> bytes:
    """``size_bytes`` of a ramp of byte values: a frame where topics carry untyped bytes.

    Not zeros, so a viewer that shows the frames as pictures (the live view's image panels)
    shows stripes, not a black square.
    """
    return (_RAMP * (size_bytes // len(_RAMP) + 1))[:size_bytes]


CDR_FLOAT64 = Float64Codec(FLOAT64_TYPE, encode_float64, decode_float64)
"""ROS 2's ``std_msgs/msg/Float64`` (the default of every transport but ``ros1``)."""
ROS1_FLOAT64 = Float64Codec("std_msgs/Float64", encode_ros1_float64, decode_ros1_float64)
"""ROS 1's ``std_msgs/Float64``."""
RAW_FRAME = FrameCodec(None, ramp)
"""A frame of untyped bytes (zenoh, memory)."""
CDR_IMAGE = FrameCodec(IMAGE_TYPE, image_cdr)
"""A CDR ``sensor_msgs/msg/Image`` (rclpy)."""
ROS1_IMAGE = FrameCodec("sensor_msgs/Image", image_ros1)
"""A ROS 1 ``sensor_msgs/Image``."""
