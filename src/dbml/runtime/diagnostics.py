"""The optimizer's health as ROS's diagnostics say it: one status per channel, one for itself.

Pure: a round's report in, statuses out (``dbml.transports.rclpy.diagnostics`` publishes them
as ``diagnostic_msgs/msg/DiagnosticArray`` on ``/diagnostics``, what rqt_robot_monitor and
Foxglove's Diagnostics panel read). The levels:

- the optimizer: OK when its allocation is optimal, WARN when the budget cannot hold every
  managed channel's minimum (infeasible: the rates still respect the budget);
- a channel: ERROR when it is managed and its publisher says it sends nothing (its driver died,
  or nothing reaches the bridge), else WARN while the round is infeasible, else OK.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from dbml.core.allocation import Status
from dbml.protocol.messages import ChannelRound, RoundReport

__all__ = ["OPTIMIZER_NAME", "Level", "NodeStatus", "channel_name", "statuses"]

OPTIMIZER_NAME = "dbml: optimizer"
"""The optimizer's status name; a channel's is ``dbml: <topic>``."""


class Level(enum.IntEnum):
    """``diagnostic_msgs/msg/DiagnosticStatus``'s levels."""

    OK = 0
    WARN = 1
    ERROR = 2


@dataclass(frozen=True, slots=True)
class NodeStatus:
    """One status: its level, name, one-line message and key-values (as text, ROS's way)."""

    level: Level
    name: str
    message: str
    values: tuple[tuple[str, str], ...]


def channel_name(topic: str) -> str:
    """A channel's status name: ``dbml: /r1/camera``."""
    return f"dbml: {topic}"


def _number(value: float | None, spec: str = ".3f") -> str:
    return "" if value is None else format(value, spec)


def _channel(channel: ChannelRound, *, infeasible: bool) -> NodeStatus:
    sent = channel.sent_hz
    size = channel.size_bytes
    if channel.managed and sent == 0:
        level, message = Level.ERROR, "managed, but its publisher sends nothing"
    elif infeasible and channel.managed:
        level, message = Level.WARN, "at its minimum: the budget is infeasible"
    elif channel.managed:
        level, message = Level.OK, f"{_number(channel.rate_hz, '.2f')} Hz allocated"
    else:
        level, message = Level.OK, "unmanaged: no remote subscriber, at its maximum"
    values = [
        ("managed", str(channel.managed).lower()),
        ("allocated_hz", _number(channel.rate_hz)),
        ("sent_hz", _number(sent)),
        ("bytes_per_s", "" if sent is None or size is None else f"{sent * size:.0f}"),
        ("share", _number(channel.share)),
        ("priority", _number(channel.priority)),
    ]
    if channel.encoding is not None:
        values.append(("rung", channel.encoding))
    return NodeStatus(level, channel_name(channel.topic), message, tuple(values))


def statuses(report: RoundReport, *, estimate_mbit: float | None = None) -> tuple[NodeStatus, ...]:
    """The optimizer's status, then each channel's, for one round."""
    infeasible = report.status is Status.INFEASIBLE
    optimizer = NodeStatus(
        Level.WARN if infeasible else Level.OK,
        OPTIMIZER_NAME,
        f"infeasible: {report.message}" if infeasible else f"optimal, round {report.round}",
        (
            ("status", report.status.value),
            ("round", str(report.round)),
            ("strategy", report.strategy.value),
            ("budget_mbit", _number(report.budget_mbit)),
            ("allocated_mbit", f"{report.allocated_mbit:.3f}"),
            ("estimate_mbit", _number(estimate_mbit)),
        ),
    )
    return (optimizer, *(_channel(c, infeasible=infeasible) for c in report.channels))
