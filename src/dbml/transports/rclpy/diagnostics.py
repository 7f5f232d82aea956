"""``/diagnostics`` over rclpy: the optimizer's statuses as ``diagnostic_msgs/msg/DiagnosticArray``.

What rqt_robot_monitor, the diagnostic aggregator and Foxglove's Diagnostics panel read. The
statuses are made without ROS (``dbml.runtime.diagnostics``); this only carries them, from the
transport's own node, once a round.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import QoSProfile

from dbml.core.errors import TransportError
from dbml.runtime.diagnostics import NodeStatus
from dbml.transports.rclpy.transport import RclpyTransport

__all__ = ["DIAGNOSTICS_DEPTH", "DIAGNOSTICS_TOPIC", "DiagnosticsPublisher"]

DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTICS_DEPTH = 10
"""diagnostic_updater's own: reliable, volatile, the last 10 kept."""


class DiagnosticsPublisher:
    """Publishes statuses on ``/diagnostics`` from ``transport``'s node (thread-safe)."""

    def __init__(self, transport: RclpyTransport) -> None:
        self._transport = transport
        made: list[Any] = []
        transport.run(  # where every rclpy call of the transport's node runs
            lambda: made.append(
                transport.node.create_publisher(
                    DiagnosticArray, DIAGNOSTICS_TOPIC, QoSProfile(depth=DIAGNOSTICS_DEPTH)
                )
            )
        )
        if not made:
            raise TransportError(f"{DIAGNOSTICS_TOPIC}: the transport closed before it")
        self._publisher = made[0]

    def publish(self, statuses: Sequence[NodeStatus]) -> None:
        """One array, stamped now, its ``hardware_id`` the transport's host."""
        array = DiagnosticArray()
        array.header.stamp = self._transport.node.get_clock().now().to_msg()
        array.status = [
            DiagnosticStatus(
                level=bytes([status.level.value]),
                name=status.name,
                message=status.message,
                hardware_id=self._transport.host,
                values=[KeyValue(key=key, value=value) for key, value in status.values],
            )
            for status in statuses
        ]
        self._publisher.publish(array)
