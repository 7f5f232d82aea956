"""An rclpy 'network' for the contract suite: transports in one private ROS 2 domain.

rclpy is imported when a network opens, not with this module: the contract suite imports it in
the ROS 1 environment too, which has no rclpy (its ros1 tests run there, marked ``ros1``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from dbml.harness.ros2env import claim_domain
from dbml.transports.base import Transport

if TYPE_CHECKING:
    from dbml.transports.rclpy import RclpyTransport

Factory = Callable[[str], Transport]

STALL_LIMIT_S = 10.0
"""A stall ends by itself after this long, should a failing test never end it."""


def rclpy_network() -> Iterator[Factory]:
    """Each host is a transport (a DDS participant) of its own in a domain claimed for the test."""
    from dbml.transports.rclpy import RclpyTransport

    made: list[RclpyTransport] = []
    with claim_domain() as domain_id:

        def make(host: str) -> Transport:
            transport = RclpyTransport(host=host, domain_id=domain_id)
            made.append(transport)
            return transport

        try:
            yield make
        finally:
            for transport in made:
                transport.close()


@contextmanager
def stalled_executor(transport: Transport) -> Iterator[None]:
    """The transport's executor thread, where every rclpy call of its store runs, is held."""
    from dbml.transports.rclpy import RclpyTransport

    assert isinstance(transport, RclpyTransport)
    released = threading.Event()
    holding = threading.Event()

    def hold() -> None:
        holding.set()
        released.wait(STALL_LIMIT_S)

    transport.call_soon(hold)
    assert holding.wait(STALL_LIMIT_S), "the executor thread never took the stall"
    try:
        yield
    finally:
        released.set()
