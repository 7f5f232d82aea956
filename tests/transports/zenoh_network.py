"""A zenoh 'network' for the contract suite: sessions on loopback, no flags, a private port."""

from __future__ import annotations

from collections.abc import Callable, Iterator

from dbml.harness.processes import free_port
from dbml.transports.base import Transport
from dbml.transports.zenoh import ZenohTransport
from tests.conftest import wait_for

Factory = Callable[[str], Transport]


def zenoh_network() -> Iterator[Factory]:
    port = free_port()  # the no-flags rendezvous, private to this test
    made: list[ZenohTransport] = []

    def make(host: str) -> Transport:
        transport = ZenohTransport(host=host, port=port)
        if made:
            assert transport.wait_for_peers(5.0), "no peer found on the loopback rendezvous"
            peers = [t.node_id for t in made]
            wait_for(lambda: all(t.wait_for_peers(0.0) for t in made), what=f"peers {peers}")
        made.append(transport)
        return transport

    yield make
    for transport in made:
        transport.close()


def zenoh_endpoints_network() -> Iterator[Factory]:
    """Explicit endpoints, as across machines: the first listens, the others connect to it."""
    port = free_port()
    made: list[ZenohTransport] = []

    def make(host: str) -> Transport:
        if not made:
            transport = ZenohTransport(host=host, listen=[f"tcp/127.0.0.1:{port}"], port=0)
        else:
            transport = ZenohTransport(
                host=host,
                connect=[f"tcp/127.0.0.1:{port}"],
                listen=["tcp/127.0.0.1:0"],
                port=0,
            )
            assert transport.wait_for_peers(5.0), "no peer reached on the explicit endpoint"
            wait_for(lambda: all(t.wait_for_peers(0.0) for t in made), what="peers")
        made.append(transport)
        return transport

    yield make
    for transport in made:
        transport.close()
