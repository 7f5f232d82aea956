"""Per-message metadata carried in the attachment: sequence number, send time and applied rate.

24 bytes, fixed layout, so it costs nothing on the hot path and any receiver can measure loss
(sequence gaps), one-way latency (send time, on hosts sharing a clock) and the rate in force.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from dbml.core.errors import TransportError

__all__ = ["SEQ_MAX", "MessageMeta", "pack_meta"]

_LAYOUT = struct.Struct("<Qqd")
SEQ_MAX = 2**64 - 1
"""The largest sequence number the layout carries (an unsigned 64-bit field)."""
pack_meta = _LAYOUT.pack
"""``pack_meta(seq, sent_ns, rate_hz)``: the encoding without building an object (hot path)."""


@dataclass(frozen=True, slots=True)
class MessageMeta:
    """What a managed publisher attaches to every message."""

    seq: int
    sent_ns: int
    """Wall-clock send time (``time.time_ns()``) on the publisher's host."""
    rate_hz: float
    """The rate the publisher applied to ``[topic]/optimized`` when it sent this message (NaN
    where the middleware does not carry it: over rclpy, DDS's sample info gives the rest)."""

    @classmethod
    def decode(cls, data: bytes | None) -> MessageMeta:
        """The metadata in an attachment; ``TransportError`` if it is not dbml's."""
        if data is None or len(data) != _LAYOUT.size:
            raise TransportError(f"attachment={data!r} is not dbml message metadata")
        seq, sent_ns, rate_hz = _LAYOUT.unpack(data)
        return cls(seq, sent_ns, rate_hz)
