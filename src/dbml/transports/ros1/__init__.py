"""The ROS 1 transport: rospy topics, the parameter server and the master's graph.

``transport`` holds topics, ``graph`` the master's registrations, ``params`` the parameter
server's sync, ``master`` the master's XML-RPC API (no rospy).

The transport class is imported on first use: importing the package, or a part of it that
needs no middleware, never loads rospy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbml.core.lazy import lazy_names

if TYPE_CHECKING:
    from dbml.transports.ros1.transport import Ros1Transport

__all__ = ["Ros1Transport"]


__getattr__ = lazy_names(__name__, {"Ros1Transport": "dbml.transports.ros1.transport"})
