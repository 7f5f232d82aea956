"""The rclpy transport: real ROS 2 through rclpy, on whatever RMW it runs.

``transport`` holds topics and the executor thread, ``graph`` the DDS graph by host, ``params``
the parameters as ROS 2 nodes' own, ``nodes`` which node holds a name (pure), ``fastdds`` Fast
DDS's discovery profile and GIDs (no rclpy).

The transport class is imported on first use: importing the package, or a part of it that
needs no middleware, never loads rclpy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbml.core.lazy import lazy_names

if TYPE_CHECKING:
    from dbml.transports.rclpy.transport import RclpyTransport

__all__ = ["RclpyTransport"]


__getattr__ = lazy_names(__name__, {"RclpyTransport": "dbml.transports.rclpy.transport"})
