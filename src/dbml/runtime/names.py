"""Parameter names: the paper's, so a user of the original finds them where they were."""

from __future__ import annotations

from dbml.core.errors import TransportError
from dbml.transports.base import Variant, check_topic

__all__ = [
    "APPLIED_FIELD",
    "BANDWIDTH",
    "CURRENT_FIELD",
    "ESTIMATE",
    "ESTIMATOR_STATE",
    "FRAME_HEADROOM",
    "MANAGED_FIELD",
    "MAX_FIELD",
    "MIN_FIELD",
    "PERIOD",
    "PRIORITY_FIELD",
    "ROUND",
    "SIZE_FIELD",
    "STATUS",
    "STATUS_MESSAGE",
    "STRATEGY",
    "UTILIZATION",
    "applied",
    "check_channel",
    "current_value",
    "managed",
    "max_rate",
    "min_rate",
    "priority",
    "size",
    "topic_of",
]

BANDWIDTH = "/dbm/max_bandwidth_in_mbit"
UTILIZATION = "/dbm/max_bandwidth_utilization"
PERIOD = "/dbm/optimization_rate_in_seconds"
STRATEGY = "/dbm/strategy"
FRAME_HEADROOM = "/dbm/frame_headroom"
"""Whether the optimizer keeps one message per channel but the largest out of the budget."""
STATUS = "/dbm/status"
"""``optimal`` or ``infeasible``, written by the optimizer after every allocation."""
STATUS_MESSAGE = "/dbm/status_message"
ROUND = "/dbm/round"
"""The optimizer's round counter, written every round: its heartbeat, the one value that changes
when nothing else does (unchanged rates are not rewritten)."""
ESTIMATE = "/dbm/estimated_bandwidth_in_mbit"
"""The bandwidth estimator's current estimate (the budget in use), when one runs."""
ESTIMATOR_STATE = "/dbm/estimator_state"
"""What the estimator sees: phase, receive rate, queueing delay, losses."""

_CHANNEL = "/dbm/"
_RESERVED_SEGMENT = "dbm"

MIN_FIELD = "frequency/min"
MAX_FIELD = "frequency/max"
SIZE_FIELD = "message_size_in_bytes"
PRIORITY_FIELD = "priority"
CURRENT_FIELD = "frequency/current_value"
APPLIED_FIELD = "frequency/applied_value"
MANAGED_FIELD = "managed"


def min_rate(topic: str) -> str:
    """The channel's declared minimum rate (Hz)."""
    return f"{topic}{_CHANNEL}{MIN_FIELD}"


def max_rate(topic: str) -> str:
    """The channel's declared maximum rate (Hz)."""
    return f"{topic}{_CHANNEL}{MAX_FIELD}"


def size(topic: str) -> str:
    """The serialised size of the channel's messages, as the publisher measures it."""
    return f"{topic}{_CHANNEL}{SIZE_FIELD}"


def priority(topic: str) -> str:
    """The channel's raw priority in [0, 1]."""
    return f"{topic}{_CHANNEL}{PRIORITY_FIELD}"


def current_value(topic: str) -> str:
    """The allocated rate, pushed by the optimizer to the publisher."""
    return f"{topic}{_CHANNEL}{CURRENT_FIELD}"


def applied(topic: str) -> str:
    """The rate the publisher is applying: its acknowledgement of ``current_value``."""
    return f"{topic}{_CHANNEL}{APPLIED_FIELD}"


def managed(topic: str) -> str:
    """Whether the optimizer manages the channel (a remote host subscribes)."""
    return f"{topic}{_CHANNEL}{MANAGED_FIELD}"


def check_channel(topic: str) -> str:
    """A channel's topic: a valid topic that no dbml name reserves.

    ``[topic]/optimized`` is a channel's managed copy and ``.../dbm/...`` its parameters (and
    ``/dbm/...`` dbml's own); a publisher declared there would mix into another channel.
    """
    check_topic(topic)
    segments = topic.split("/")
    if segments[-1] == Variant.OPTIMIZED.value or _RESERVED_SEGMENT in segments:
        raise TransportError(
            f"topic={topic!r} is reserved: '.../{Variant.OPTIMIZED.value}' and "
            f"'.../{_RESERVED_SEGMENT}/...' are dbml's own names, not channels"
        )
    return topic


def topic_of(name: str) -> tuple[str, str] | None:
    """Split ``/r1/camera/dbm/priority`` into ``('/r1/camera', 'priority')``; None if global."""
    head, sep, tail = name.rpartition(_CHANNEL)
    if not sep or not head:
        return None
    return head, tail
