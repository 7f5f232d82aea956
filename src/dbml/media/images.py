"""``sensor_msgs/msg/Image`` and ``CompressedImage`` in CDR, through rosbags' typestore.

The same CDR bytes travel on every transport that carries ROS 2 messages (rclpy, rmw_zenoh's
wire) and on zenoh: what a ROS 2 tool or Foxglove reads. Everything decoded here may come from
the network: a malformed message is a ``SpecError`` naming what is wrong, never a crash.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError
from dbml.core.extras import require
from dbml.media.jpeg import PIXEL_CHANNELS

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = [
    "COMPRESSED_TYPE",
    "IMAGE_TYPE",
    "MAX_PIXELS",
    "Compressed",
    "Frame",
    "decode_compressed",
    "decode_image",
    "encode_compressed",
    "encode_image",
]

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
MAX_PIXELS = 4096 * 4096
"""The largest image a camera channel takes (width x height): a frame from the network that
claims more is refused before anything is allocated for it."""
_NS = 1_000_000_000
_CDR_LE = b"\x00\x01\x00\x00"
"""The encapsulation header of little-endian CDR."""


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """One camera frame: its pixels (height x width x channels, or height x width for mono8)."""

    pixels: npt.NDArray[np.uint8]
    encoding: str
    stamp_ns: int = 0
    frame_id: str = "camera"

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``."""
        return int(self.pixels.shape[0]), int(self.pixels.shape[1])


@dataclass(frozen=True, slots=True)
class Compressed:
    """A received ``CompressedImage``: its stamp, its format string and its JPEG."""

    stamp_ns: int
    frame_id: str
    format: str
    data: bytes


@functools.cache
def _store() -> Typestore:
    require("rosbags", extra="quality", what="ROS 2 images without ROS 2")
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _header(stamp_ns: int, frame_id: str) -> Any:
    types = _store().types
    sec, nanosec = divmod(max(0, int(stamp_ns)), _NS)
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def encode_image(frame: Frame) -> bytes:
    """``frame`` as a CDR ``sensor_msgs/msg/Image``."""
    height, width = frame.shape
    channels = PIXEL_CHANNELS.get(frame.encoding)
    if channels is None:
        raise SpecError(f"image encoding={frame.encoding!r}: one of {', '.join(PIXEL_CHANNELS)}")
    message = _store().types[IMAGE_TYPE](
        header=_header(frame.stamp_ns, frame.frame_id),
        height=height,
        width=width,
        encoding=frame.encoding,
        is_bigendian=0,
        step=width * channels,
        data=np.ascontiguousarray(frame.pixels).reshape(-1),
    )
    return bytes(_store().serialize_cdr(message, IMAGE_TYPE))


def decode_image(payload: bytes) -> Frame:
    """A CDR ``sensor_msgs/msg/Image`` of rgb8, bgr8 or mono8 as a ``Frame``; else ``SpecError``."""
    try:
        message: Any = _store().deserialize_cdr(bytes(payload), IMAGE_TYPE)
    except Exception as err:  # rosbags raises its own errors for bytes that are not an Image
        raise SpecError(f"a message of {len(payload)} bytes is not a {IMAGE_TYPE}: {err}") from None
    encoding = str(message.encoding)
    channels = PIXEL_CHANNELS.get(encoding)
    if channels is None:
        raise SpecError(
            f"image encoding={encoding!r} cannot be laddered: one of {', '.join(PIXEL_CHANNELS)}"
        )
    height, width, step = int(message.height), int(message.width), int(message.step)
    if not 0 < height * width <= MAX_PIXELS or step < width * channels:
        raise SpecError(f"image of {width}x{height}, step={step}: not an image dbml takes")
    data = np.asarray(message.data, dtype=np.uint8)
    if data.size < step * height:
        due = step * height
        raise SpecError(f"image of {width}x{height}: {data.size} bytes of data, {due} due")
    rows = data[: step * height].reshape(height, step)[:, : width * channels]
    pixels = rows.reshape(height, width) if channels == 1 else rows.reshape(height, width, 3)
    stamp = message.header.stamp
    stamp_ns = int(stamp.sec) * _NS + int(stamp.nanosec)
    return Frame(pixels, encoding, stamp_ns, str(message.header.frame_id))


def encode_compressed(frame: Frame, data: bytes, *, format: str) -> bytes:
    """A CDR ``sensor_msgs/msg/CompressedImage`` of ``data`` with ``frame``'s header.

    Packed here (little-endian CDR: the stamp, two strings, a byte sequence), not through the
    typestore: it is every frame's path, and rosbags' general serialiser cost a camera 0.3 ms
    of its 1.6 a frame. The tests read it back with rosbags.
    """
    sec, nanosec = divmod(max(0, int(frame.stamp_ns)), _NS)
    body = bytearray(struct.pack("<iI", sec, nanosec))
    for text in (frame.frame_id, format):
        raw = text.encode() + b"\x00"
        body += struct.pack("<I", len(raw)) + raw
        body += bytes(-len(body) % 4)
    body += struct.pack("<I", len(data))
    return _CDR_LE + bytes(body) + bytes(data)


def decode_compressed(payload: bytes) -> Compressed:
    """A received CDR ``CompressedImage``; ``SpecError`` if it is not one."""
    try:
        message: Any = _store().deserialize_cdr(bytes(payload), COMPRESSED_TYPE)
    except Exception as err:  # rosbags raises its own errors for bytes that are not one
        raise SpecError(
            f"a message of {len(payload)} bytes is not a {COMPRESSED_TYPE}: {err}"
        ) from None
    stamp = message.header.stamp
    return Compressed(
        int(stamp.sec) * _NS + int(stamp.nanosec),
        str(message.header.frame_id),
        str(message.format),
        bytes(np.asarray(message.data, dtype=np.uint8)),
    )
