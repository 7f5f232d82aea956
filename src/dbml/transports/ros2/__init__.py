"""The ros2 transport: rmw_zenoh's wire format on a zenoh session, no ROS 2 install.

``transport`` is the session's ROS 2 side, ``wire`` rmw_zenoh's formats (pure).

The transport class is imported on first use: importing the package, or a part of it that
needs no middleware, never loads zenoh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbml.core.lazy import lazy_names

if TYPE_CHECKING:
    from dbml.transports.ros2.transport import Ros2Transport

__all__ = ["Ros2Transport"]


__getattr__ = lazy_names(__name__, {"Ros2Transport": "dbml.transports.ros2.transport"})
