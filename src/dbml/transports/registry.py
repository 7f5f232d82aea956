"""Transports by name; middleware is imported only when its transport is opened."""

from __future__ import annotations

import importlib
import os
from collections.abc import Sequence
from pathlib import Path

from dbml.core.errors import TransportError
from dbml.transports.base import Transport
from dbml.transports.memory import MemoryTransport

__all__ = ["TRANSPORTS", "open_transport"]

TRANSPORTS = ("zenoh", "memory", "ros1")
"""Registered names; the first is the default."""


def open_transport(
    name: str = "zenoh",
    *,
    host: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: str | Path | None = None,
) -> Transport:
    """Open a transport by name. ``memory`` gives a private in-process network; ``ros1``
    joins the ROS master at ``ROS_MASTER_URI`` (``host`` sets ``ROS_HOSTNAME``)."""
    if name == "memory":
        if connect or listen or config_file:
            raise TransportError("transport='memory' takes no endpoints or config file")
        return MemoryTransport(host=host)
    if name == "zenoh":
        module = importlib.import_module("dbml.transports.zenoh")
        transport: Transport = module.ZenohTransport(
            host=host, connect=connect, listen=listen, config_file=config_file
        )
        return transport
    if name == "ros1":
        if connect or listen or config_file:
            raise TransportError(
                "transport='ros1' takes no endpoints or config file: it uses ROS_MASTER_URI"
            )
        if host is not None:
            # rospy names this process's host from the environment, before the node starts.
            os.environ["ROS_HOSTNAME"] = host
        try:
            module = importlib.import_module("dbml.transports.ros1")
        except ImportError as err:
            raise TransportError(str(err)) from err
        ros1: Transport = module.Ros1Transport()
        return ros1
    raise TransportError(f"transport={name!r} is not one of: {', '.join(TRANSPORTS)}")
