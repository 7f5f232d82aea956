"""A ros2 'network' for the contract suite: a zenoh router on a private port, sessions at it."""

from __future__ import annotations

from collections.abc import Callable, Iterator

from dbml.harness.processes import free_port
from dbml.transports.base import Transport
from dbml.transports.ros2 import Ros2Transport
from dbml.transports.zenoh.transport import open_router
from tests.conftest import wait_for

Factory = Callable[[str], Transport]


def ros2_network() -> Iterator[Factory]:
    """Every session connects to the router, as ROS 2 nodes connect to ``rmw_zenohd``."""
    port = free_port()
    router = open_router([f"tcp/127.0.0.1:{port}"])
    made: list[Ros2Transport] = []

    def make(host: str) -> Transport:
        transport = Ros2Transport(
            host=host, connect=[f"tcp/127.0.0.1:{port}"], listen=["tcp/127.0.0.1:0"]
        )
        if made:
            assert transport.wait_for_peers(5.0), "no dbml peer met at the router"
            wait_for(lambda: all(t.wait_for_peers(0) for t in made), what="peers")
        made.append(transport)
        return transport

    try:
        yield make
    finally:
        for transport in made:
            transport.close()
        router.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
