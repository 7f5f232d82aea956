"""Transport classes over zenoh: priority-dedicated links and re-declaration, on loopback."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
from collections.abc import Iterator
from typing import SupportsInt, cast

import pytest

from dbml.core.errors import TransportError
from dbml.harness.processes import free_port
from dbml.protocol import names
from dbml.runtime import ManagedPublisher
from dbml.runtime.qos import TransportQos, map_priority
from dbml.transports import Sample, Variant
from dbml.transports.base import EXPEDITED_TOS, TransportPriority
from dbml.transports.zenoh.transport import (
    PRIORITY_LINK_RANGES,
    ZENOH_PRIORITY,
    ZenohTransport,
    _json_list,
    _priority_endpoints,
)
from tests.conftest import wait_for


def test_each_endpoint_gets_one_link_per_priority_range() -> None:
    assert PRIORITY_LINK_RANGES == ("1-3", "4-7")
    assert _priority_endpoints(["tcp/10.0.0.1:7447", "tls/h:7447#iface=eth0"]) == [
        "tcp/10.0.0.1:7447?prio=1-3#dscp=0xb8",
        "tcp/10.0.0.1:7447?prio=4-7",
        "tls/h:7447?prio=1-3#iface=eth0;dscp=0xb8",
        "tls/h:7447?prio=4-7#iface=eth0",
    ]
    assert _priority_endpoints(["tcp/h:1?prio=1-7"]) == ["tcp/h:1?prio=1-7"]  # the author's
    assert _priority_endpoints(["tcp/h:1#dscp=0x20"]) == [  # the author's marking, on both
        "tcp/h:1?prio=1-3#dscp=0x20",
        "tcp/h:1?prio=4-7#dscp=0x20",
    ]
    assert _priority_endpoints(["quic/h:1"]) == ["quic/h:1?prio=1-3", "quic/h:1?prio=4-7"]
    assert EXPEDITED_TOS >> 2 == 46  # DSCP EF (RFC 3246), past the two ECN bits


def tos_of_connections(port: int) -> list[str]:
    """``ss``'s TOS of each established TCP connection made to ``port`` (``tos:0xb8``)."""
    ss = shutil.which("ss")
    if ss is None:
        pytest.skip("needs ss (iproute2) to read a socket's TOS")
    argv = [ss, "-tnH", "--tos", "state", "established", f"( dport = :{port} )"]
    out = subprocess.run(argv, check=True, capture_output=True, text=True, timeout=10).stdout
    return sorted(word for word in out.split() if word.startswith("tos:"))


@contextlib.contextmanager
def linked(port: int) -> Iterator[tuple[ZenohTransport, ZenohTransport]]:
    """An operator listening on ``port`` and a robot connected to it, both with priority links."""
    endpoint = f"tcp/127.0.0.1:{port}"
    operator = ZenohTransport(host="op", listen=[endpoint], priority_links=True)
    robot = ZenohTransport(
        host="r1", listen=["tcp/127.0.0.1:0"], connect=[endpoint], priority_links=True
    )
    try:
        assert robot.wait_for_peers(10.0)
        yield operator, robot
    finally:
        robot.close()
        operator.close()


def test_only_the_urgent_link_is_marked_expedited() -> None:
    """The connecting side's urgent link carries the TOS ``_priority_endpoints`` asks for."""
    port = free_port()
    with linked(port):
        wanted = sorted(["tos:0", f"tos:{EXPEDITED_TOS:#x}"])
        wait_for(lambda: tos_of_connections(port) == wanted, what="two links, one marked EF")


def link_of(priority: TransportPriority) -> int:
    """Which of ``PRIORITY_LINK_RANGES`` carries a class (zenoh's priorities are 1-7)."""
    number = int(cast("SupportsInt", ZENOH_PRIORITY[priority]))  # 1-7; the stubs omit __int__
    for index, span in enumerate(PRIORITY_LINK_RANGES):
        low, high = (int(end) for end in span.split("-"))
        if low <= number <= high:
            return index
    raise AssertionError(f"{priority} is in no range")


def test_camera_frames_never_share_the_urgent_link() -> None:
    """Every class a large frame can map to travels on the second link, urgent ones the first."""
    large = {map_priority(p, 84_000).priority for p in (0.0, 0.1, 0.25, 0.5, 0.75, 1.0)}
    assert {link_of(c) for c in large} == {1}
    assert link_of(map_priority(1.0, 1_000).priority) == 0
    assert link_of(TransportPriority.INTERACTIVE_HIGH) == 0  # dbml's control traffic


def test_endpoints_with_metadata_are_checked_on_their_port() -> None:
    assert _json_list(["tcp/h:7447?prio=1-4", "tcp/h:7447#so_sndbuf=65000"])
    with pytest.raises(TransportError, match=r"endpoint='tcp/h:99999\?prio=1-4': the port"):
        _json_list(["tcp/h:99999?prio=1-4"])


def test_priority_links_carry_every_class_and_a_remote_priority_redeclares() -> None:
    with linked(free_port()) as (operator, robot):
        received: list[Sample] = []
        operator.subscribe("/r1/alarm", received.append, Variant.OPTIMIZED)
        operator.params.set(names.current_value("/r1/alarm"), 20.0)
        publisher = ManagedPublisher(robot, "/r1/alarm", min_rate_hz=1, max_rate_hz=20)
        wait_for(lambda: publisher.publish(bytes(1_000)), what="a first allocated message")
        wait_for(lambda: bool(received), what="the default class delivered")
        # Written by another session: applied on zenoh's callback thread, which must not stall.
        operator.params.set(names.priority("/r1/alarm"), 1.0)
        wanted = TransportQos(TransportPriority.INTERACTIVE_LOW, express=True)

        def republished() -> bool:
            """The publishing thread re-declares (never zenoh's callback thread)."""
            publisher.publish(bytes(1_000))
            return publisher.transport_qos == wanted

        wait_for(republished, what="the interactive class")
        count = len(received)
        wait_for(lambda: publisher.publish(bytes(1_000)), what="a message in the new class")
        wait_for(lambda: len(received) > count, what="the interactive class delivered")
        publisher.close()
