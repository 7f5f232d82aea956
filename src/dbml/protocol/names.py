"""Names: a channel's topic and its copies, and the paper's parameter names, from the schema.

A user of the original package finds every parameter where it was (``/dbm/max_bandwidth_in_mbit``,
``/r1/camera/dbm/priority``); the names are spelled once, in ``dbml.protocol.schema``.
"""

from __future__ import annotations

import re

from dbml.core.errors import TransportError
from dbml.protocol import schema

__all__ = [
    "APPLIED_FIELD",
    "BANDWIDTH",
    "COMPRESSED",
    "CURRENT_FIELD",
    "ENCODING_FIELD",
    "ESTIMATE",
    "ESTIMATOR_STATE",
    "FRAME_HEADROOM",
    "MANAGED_FIELD",
    "MAX_FIELD",
    "MIN_FIELD",
    "OPTIMIZED",
    "PERIOD",
    "PRIORITY_FIELD",
    "PRIORITY_SUFFIX",
    "ROUND",
    "SIZE_FIELD",
    "STATUS",
    "STATUS_MESSAGE",
    "STRATEGY",
    "UTILIZATION",
    "applied",
    "check_channel",
    "check_topic",
    "current_value",
    "encoding",
    "encoding_applied",
    "ladder",
    "managed",
    "max_rate",
    "min_quality",
    "min_rate",
    "preference",
    "priority",
    "sent",
    "size",
    "topic_of",
]

OPTIMIZED = "optimized"
"""The last segment of a channel's managed copy: ``/r1/camera/optimized``."""
COMPRESSED = "compressed"
"""After ``optimized``, a camera's managed copy as JPEG: ``/r1/camera/optimized/compressed``."""

BANDWIDTH = schema.BANDWIDTH.name
UTILIZATION = schema.UTILIZATION.name
PERIOD = schema.PERIOD.name
STRATEGY = schema.STRATEGY.name
FRAME_HEADROOM = schema.FRAME_HEADROOM.name
STATUS = schema.STATUS.name
STATUS_MESSAGE = schema.STATUS_MESSAGE.name
ROUND = schema.ROUND.name
ESTIMATE = schema.ESTIMATE.name
ESTIMATOR_STATE = schema.ESTIMATOR_STATE.name

MIN_FIELD = schema.MIN_RATE.field
MAX_FIELD = schema.MAX_RATE.field
SIZE_FIELD = schema.SIZE.field
PRIORITY_FIELD = schema.PRIORITY.field
CURRENT_FIELD = schema.CURRENT.field
APPLIED_FIELD = schema.APPLIED.field
MANAGED_FIELD = schema.MANAGED.field
ENCODING_FIELD = schema.ENCODING.field
PRIORITY_SUFFIX = f"/{schema.PRIORITY.relative}"
"""A channel's priority parameter after its topic (over ROS 2 also a ``Float64`` topic)."""

_RESERVED_SEGMENT = schema.GLOBAL_PREFIX[1:]
_TOPIC = re.compile(r"^(/[A-Za-z0-9_\-.~]+)+$")


def check_topic(topic: str) -> str:
    """A topic is a ROS-style name: ``/`` then segments of letters, digits and ``_-.~``."""
    if not isinstance(topic, str) or not _TOPIC.match(topic):
        raise TransportError(
            f"topic={topic!r} must look like '/robot/sensor' (segments of letters, digits, _-.~)"
        )
    return topic


def min_rate(topic: str) -> str:
    """The channel's declared minimum rate (Hz)."""
    return schema.MIN_RATE.key(topic)


def max_rate(topic: str) -> str:
    """The channel's declared maximum rate (Hz)."""
    return schema.MAX_RATE.key(topic)


def size(topic: str) -> str:
    """The serialised size of the channel's messages, as the publisher measures it."""
    return schema.SIZE.key(topic)


def priority(topic: str) -> str:
    """The channel's raw priority in [0, 1]."""
    return schema.PRIORITY.key(topic)


def current_value(topic: str) -> str:
    """The allocated rate, pushed by the optimizer to the publisher."""
    return schema.CURRENT.key(topic)


def applied(topic: str) -> str:
    """The rate the publisher is applying: its acknowledgement of ``current_value``."""
    return schema.APPLIED.key(topic)


def sent(topic: str) -> str:
    """``[topic]/dbm/frequency/sent_value``: the rate the publisher sent, as it last said."""
    return schema.SENT.key(topic)


def encoding(topic: str) -> str:
    """``[topic]/dbm/encoding/current_value``: the rung the optimizer chose."""
    return schema.ENCODING.key(topic)


def encoding_applied(topic: str) -> str:
    """``[topic]/dbm/encoding/applied_value``: the encoding the publisher applies."""
    return schema.ENCODING_APPLIED.key(topic)


def preference(topic: str) -> str:
    """``[topic]/dbm/preference``: what a laddered channel gives up first."""
    return schema.PREFERENCE.key(topic)


def min_quality(topic: str) -> str:
    """``[topic]/dbm/quality/min``: a laddered channel's quality floor."""
    return schema.MIN_QUALITY.key(topic)


def ladder(topic: str) -> str:
    """``[topic]/dbm/ladder``: the ladder the publisher measured."""
    return schema.LADDER.key(topic)


def managed(topic: str) -> str:
    """Whether the optimizer manages the channel (a remote host subscribes)."""
    return schema.MANAGED.key(topic)


def check_channel(topic: str) -> str:
    """A channel's topic: a valid topic that no dbml name reserves.

    ``[topic]/optimized`` is a channel's managed copy and ``.../dbm/...`` its parameters (and
    ``/dbm/...`` dbml's own); a publisher declared there would mix into another channel.
    """
    check_topic(topic)
    segments = topic.split("/")
    if (
        segments[-1] == OPTIMIZED
        or segments[-2:] == [OPTIMIZED, COMPRESSED]
        or _RESERVED_SEGMENT in segments
    ):
        raise TransportError(
            f"topic={topic!r} is reserved: '.../{OPTIMIZED}' and "
            f"'.../{_RESERVED_SEGMENT}/...' are dbml's own names, not channels"
        )
    return topic


topic_of = schema.split_channel_name
"""Split ``/r1/camera/dbm/priority`` into ``('/r1/camera', 'priority')``; None if global."""
