"""One contract, every transport: each test runs against each registered transport.

Tests wait on conditions, so the same assertions hold for synchronous (memory) and
asynchronous (zenoh, ros1) delivery. ROS 1's are marked ``ros1`` (make test runs them in the
environment that imports rospy; skipped elsewhere, a failure when CI=true), one peer process
per host (rospy runs one node per process).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from dbml.core.errors import TransportError
from dbml.protocol.schema import ParamError
from dbml.transports import (
    TRANSPORTS,
    MemoryNetwork,
    MemoryTransport,
    Role,
    Sample,
    Transport,
    Variant,
)
from dbml.transports.base import resolve_host
from dbml.transports.replica import Replica
from dbml.transports.ros1.master import CALL_TIMEOUT_S, MasterClient
from dbml.transports.ros2.transport import Ros2Transport
from dbml.transports.zenoh.keyed import KeyedParams
from dbml.transports.zenoh.transport import ZenohTransport
from tests.conftest import wait_for
from tests.transports.rclpy_network import rclpy_network, stalled_executor
from tests.transports.ros1_network import PeerTransport, ros1_network
from tests.transports.ros2_network import ros2_network
from tests.transports.zenoh_network import zenoh_endpoints_network, zenoh_network

Factory = Callable[[str], Transport]
Stall = Callable[[Transport], AbstractContextManager[None]]
"""Makes the network under one transport stop taking its writes, for the ``with`` block."""

PRIORITY = "/r1/camera/dbm/priority"
ROUND = "/dbm/round"
SET_BOUND_S = 0.5
"""How long ``params.set`` may take while the network stalls: ample for a call (over ROS 1, a
round trip to the peer process), far below the stall (a ROS 1 call waits 2 s for the master)."""
STALL_LIMIT_S = 10.0
"""A stall ends by itself after this long, should a failing test never end it."""


def memory_network() -> Iterator[Factory]:
    network = MemoryNetwork()
    made: list[Transport] = []

    def make(host: str) -> Transport:
        transport = MemoryTransport(network, host=host)
        made.append(transport)
        return transport

    yield make
    for transport in made:
        transport.close()


@contextmanager
def stalled_sends(transport: Transport) -> Iterator[None]:
    """The zenoh store's network send blocks (a congested zenoh link) until the end."""
    zenoh = transport._dbml if isinstance(transport, Ros2Transport) else transport
    assert isinstance(zenoh, ZenohTransport)
    store: KeyedParams = zenoh._sync.keyed
    real = store._send
    released = threading.Event()

    def stalled(key: str, data: bytes) -> None:
        released.wait(STALL_LIMIT_S)
        real(key, data)

    store._send = stalled
    try:
        yield
    finally:
        store._send = real
        released.set()


@contextmanager
def stalled_master(transport: Transport) -> Iterator[None]:
    """The ROS master stops (SIGSTOP) until the end, as a master too busy to answer.

    Ours: each test starts its own. Its URI is in the peer process's environment.
    """
    assert isinstance(transport, PeerTransport)
    environ = Path(f"/proc/{transport._peer.process.pid}/environ").read_bytes().split(b"\0")
    uri = next(e.split(b"=", 1)[1].decode() for e in environ if e.startswith(b"ROS_MASTER_URI="))
    with MasterClient(uri) as master:
        pid = int(master.call("getPid"))
    os.kill(pid, signal.SIGSTOP)
    stopped_at = time.monotonic()
    try:
        yield
    finally:
        os.kill(pid, signal.SIGCONT)
    # Longer, and the write's call would time out in the peer (and be dropped, logged).
    assert time.monotonic() - stopped_at < CALL_TIMEOUT_S, "the stall outlasted a ROS call"


@dataclass(frozen=True)
class Network:
    transport: str
    """The registered transport it runs."""
    open: Callable[[], Iterator[Factory]]
    stall: Stall | None = None
    """How to stall the network under a transport (None: nothing to stall)."""


NETWORKS = {
    "memory": Network("memory", memory_network),
    "rclpy": Network("rclpy", rclpy_network, stalled_executor),
    "ros1": Network("ros1", ros1_network, stalled_master),
    "ros2": Network("ros2", ros2_network, stalled_sends),
    "zenoh": Network("zenoh", zenoh_network, stalled_sends),
    "zenoh-endpoints": Network("zenoh", zenoh_endpoints_network, stalled_sends),
}

_ANNOUNCE = "ROS 1's graph is the master's registrations: announce() declares nothing of its own"
_DDS_GRAPH = "ROS 2's graph is the DDS endpoints: announce() declares nothing of its own"
DOES_NOT_APPLY = {
    ("rclpy", "test_graph_announce_withdraw_and_watch"): _DDS_GRAPH,
    ("rclpy", "test_two_identical_declarations_are_two_entries"): _DDS_GRAPH,
    ("rclpy", "test_closing_a_transport_withdraws_its_graph"): _DDS_GRAPH,
    ("rclpy", "test_a_topics_entries_and_its_watch"): _DDS_GRAPH,
    ("memory", "test_a_write_never_waits_for_a_stalled_network"): (
        "memory's store is the network itself: a write sends nothing that could stall"
    ),
    ("ros1", "test_graph_announce_withdraw_and_watch"): _ANNOUNCE,
    ("ros1", "test_two_identical_declarations_are_two_entries"): _ANNOUNCE,
    ("ros1", "test_closing_a_transport_withdraws_its_graph"): _ANNOUNCE,
    ("ros1", "test_a_topics_entries_and_its_watch"): _ANNOUNCE,
}
"""(transport, test) pairs a test cannot hold for, with the reason."""


def test_every_registered_transport_is_in_the_contract() -> None:
    assert {network.transport for network in NETWORKS.values()} == set(TRANSPORTS)


NEEDS = {"ros1": pytest.mark.ros1}
"""Networks that need an environment of their own (make test runs ros1's in .venv-ros1)."""


@pytest.fixture(params=[pytest.param(name, marks=NEEDS.get(name, ())) for name in sorted(NETWORKS)])
def network(request: pytest.FixtureRequest) -> Network:
    chosen = NETWORKS[request.param]
    reason = DOES_NOT_APPLY.get((chosen.transport, request.function.__name__))
    if reason is not None:
        pytest.skip(reason)
    return chosen


@pytest.fixture
def make(network: Network) -> Iterator[Factory]:
    yield from network.open()


def test_publish_reaches_a_subscriber_on_another_host_with_attachment(
    make: Factory, network: Network
) -> None:
    a, b = make("host-a"), make("host-b")
    got: list[Sample] = []
    b.subscribe("/r1/camera", got.append)
    publisher = a.declare_publisher("/r1/camera")
    wait_for(lambda: publisher.has_subscribers, what="publisher to see its subscriber")
    publisher.put(b"\x00" * 84_000, attachment=b"meta")
    wait_for(lambda: len(got) == 1, what="one sample")
    assert got[0].topic == "/r1/camera"
    assert got[0].payload == b"\x00" * 84_000
    # ROS 1 messages carry no attachment, ROS 2's carry rmw's own: the registry says dbml's is
    # not carried, and the sample does not have it.
    if TRANSPORTS[network.transport].carries_metadata:
        assert got[0].attachment == b"meta"
    else:
        assert got[0].attachment != b"meta"


def test_variants_are_separate_keys(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    full: list[Sample] = []
    optimized: list[Sample] = []
    b.subscribe("/t", full.append, Variant.FULL)
    b.subscribe("/t", optimized.append, Variant.OPTIMIZED)
    pub_full = a.declare_publisher("/t", Variant.FULL)
    pub_opt = a.declare_publisher("/t", Variant.OPTIMIZED)
    wait_for(lambda: pub_full.has_subscribers and pub_opt.has_subscribers, what="matching")
    pub_full.put(b"f")
    pub_opt.put(b"o")
    wait_for(lambda: len(full) == 1 and len(optimized) == 1, what="one sample on each variant")
    assert full[0].payload == b"f"
    assert optimized[0].payload == b"o"


def test_has_subscribers_follows_the_subscription(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    publisher = a.declare_publisher("/lonely")
    assert not publisher.has_subscribers
    handle = b.subscribe("/lonely", lambda _s: None)
    wait_for(lambda: publisher.has_subscribers, what="a match")
    handle.close()
    wait_for(lambda: not publisher.has_subscribers, what="the match to go")


def test_closed_subscription_receives_nothing(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    got: list[Sample] = []
    probe: list[Sample] = []
    handle = b.subscribe("/t", got.append)
    b.subscribe("/t", probe.append)
    publisher = a.declare_publisher("/t")
    wait_for(lambda: publisher.has_subscribers, what="matching")
    handle.close()

    def heard() -> bool:
        # Sent until the open subscription hears one: "a subscriber matched" may be the closed
        # one alone (over rclpy the other is made once the graph shows the topic's type).
        publisher.put(b"x")
        return len(probe) >= 1

    wait_for(heard, what="the probe to receive")
    assert got == []


def test_params_are_shared_and_watched(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    seen: list[tuple[str, object]] = []
    b.params.watch(lambda name, value: seen.append((name, value)))
    a.params.set("/r1/camera/dbm/priority", 0.5)
    wait_for(lambda: b.params.get("/r1/camera/dbm/priority") == 0.5, what="the value")
    wait_for(lambda: ("/r1/camera/dbm/priority", 0.5) in seen, what="the notification")
    b.params.set("/r1/camera/dbm/priority", 0.75)  # newest write wins everywhere
    wait_for(lambda: a.params.get("/r1/camera/dbm/priority") == 0.75, what="the update")
    a.params.set("/dbm/max_bandwidth_in_mbit", 11)
    a.params.set("/dbm/strategy", "paper")
    a.params.set("/r1/camera/dbm/managed", True)
    # Wait for the last write: one writer's writes arrive in order, so the earlier ones are in
    # too. Seeing the first two says nothing about the third, which may still be on its way.
    wait_for(lambda: b.params.get("/r1/camera/dbm/managed") is True, what="the last write")
    assert b.params.snapshot("/dbm/") == {
        "/dbm/max_bandwidth_in_mbit": 11,
        "/dbm/strategy": "paper",
    }
    assert b.params.get("/nope") is None


def test_a_write_never_waits_for_a_stalled_network(make: Factory, network: Network) -> None:
    """``set`` returns while the network takes no writes (it may run on a middleware thread).

    The value holds here at once, and reaches the others once the network takes it.
    """
    assert network.stall is not None
    a, b = make("host-a"), make("host-b")
    name = "/r1/camera/dbm/priority"
    with network.stall(a):
        started = time.monotonic()
        a.params.set(name, 0.25)
        took_s = time.monotonic() - started
        held_here = a.params.get(name)
        held_there = b.params.get(name)
    assert took_s < SET_BOUND_S, f"set took {took_s:.3f} s while the network stalled"
    assert held_here == 0.25
    assert held_there is None  # the stall was real: the write had not gone out
    wait_for(lambda: b.params.get(name) == 0.25, what="the write once the stall ended")


def test_a_late_joiner_sees_existing_params(make: Factory) -> None:
    a = make("host-a")
    a.params.set("/r1/camera/dbm/frequency/min", 1.0)
    late = make("host-late")
    wait_for(lambda: late.params.get("/r1/camera/dbm/frequency/min") == 1.0, what="history")


def test_graph_announce_withdraw_and_watch(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    changes: list[int] = []
    b.graph.watch(lambda: changes.append(1))
    token = a.graph.announce(Role.SUBSCRIBER, "/r1/camera", Variant.OPTIMIZED)

    def entries() -> set[tuple[Role, str, str, Variant]]:
        return {(e.role, e.host, e.topic, e.variant) for e in b.graph.entries()}

    wanted = (Role.SUBSCRIBER, "host-a", "/r1/camera", Variant.OPTIMIZED)
    wait_for(lambda: wanted in entries(), what="the announcement")
    wait_for(lambda: len(changes) >= 1, what="a graph notification")
    token.close()
    wait_for(lambda: wanted not in entries(), what="the withdrawal")


def test_a_topics_entries_and_its_watch(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    changes: list[int] = []
    b.graph.watch(lambda: changes.append(1), topic="/r1/camera")
    a.graph.announce(Role.PUBLISHER, "/r2/lidar", Variant.FULL)
    a.graph.announce(Role.PUBLISHER, "/r1/camera", Variant.FULL)
    wait_for(lambda: len(b.graph.entries()) == 2, what="both announcements")
    assert {e.topic for e in b.graph.entries(topic="/r1/camera")} == {"/r1/camera"}
    assert b.graph.entries(topic="/r3/none") == frozenset()
    wait_for(lambda: len(changes) >= 1, what="the topic's notification")


def test_two_identical_declarations_are_two_entries(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    first = a.graph.announce(Role.PUBLISHER, "/t", Variant.FULL)
    a.graph.announce(Role.PUBLISHER, "/t", Variant.FULL)
    wait_for(lambda: len(b.graph.entries()) == 2, what="two entries")
    first.close()
    wait_for(lambda: len(b.graph.entries()) == 1, what="one entry left")


def test_closing_a_transport_withdraws_its_graph(make: Factory) -> None:
    a, b = make("host-a"), make("host-b")
    a.graph.announce(Role.PUBLISHER, "/t", Variant.FULL)
    wait_for(lambda: len(b.graph.entries()) == 1, what="the entry")
    a.close()
    wait_for(lambda: len(b.graph.entries()) == 0, what="the entry to vanish")


def test_host_identity(make: Factory, monkeypatch: pytest.MonkeyPatch) -> None:
    assert make("robot-7").host == "robot-7"
    monkeypatch.setenv("DBML_HOST", "from-env")
    assert resolve_host() == "from-env"
    assert resolve_host("explicit") == "explicit"
    with pytest.raises(TransportError, match=r"host='a/b' must be letters"):
        resolve_host("a/b")


@pytest.mark.parametrize("topic", ["r1/camera", "/r1//camera", "/r1/*", "", "/a b"])
def test_bad_topics_are_rejected(make: Factory, topic: str) -> None:
    with pytest.raises(TransportError, match=r"topic=.* must look like '/robot/sensor'"):
        make("host-a").declare_publisher(topic)


REFUSALS: list[tuple[str, object, type[Exception], str]] = [
    (PRIORITY, [1], TransportError, r"^/r1/camera/dbm/priority=\[1\] is not a parameter value"),
    ("/x", 1, TransportError, r"^/x=1: '/x' is not a parameter of dbml's schema"),
    ("/r1/camera/dbm/x", 1, TransportError, r"^/r1/camera/dbm/x=1: '/r1/camera/dbm/x' is not a"),
    (PRIORITY, 1.5, ParamError, r"^/r1/camera/dbm/priority=1\.5 must be within \[0, 1\]"),
    ("/dbm/strategy", "best", ParamError, r"^/dbm/strategy='best' is not valid"),
]
"""What ``ParamStore.set`` refuses, with the error and its message: the same everywhere."""


def test_set_refuses_a_bad_value_or_name_alike_everywhere(make: Factory) -> None:
    a = make("host-a")
    for name, value, error, message in REFUSALS:
        with pytest.raises(error, match=message):
            a.params.set(name, value)  # type: ignore[arg-type]
        with pytest.raises(error, match=message):  # checked first: nothing of it is taken
            a.params.set_many({ROUND: 3, name: value})  # type: ignore[dict-item]
    a.params.set(ROUND, 4)  # a good write after them is taken
    wait_for(lambda: a.params.get(ROUND) == 4, what="the good write")
    assert a.params.get(PRIORITY) is None
    assert a.params.get("/dbm/strategy") is None


def limit(transport: Transport, more: int) -> None:
    """Lower ``transport``'s bound on its own names to what it wrote and ``more`` new ones."""
    if isinstance(transport, PeerTransport):
        transport.params.limit(more)
        return
    store = transport.params
    assert isinstance(store, Replica)
    store._max_params = len(store._own) + more


def test_set_refuses_a_new_name_past_the_bound_alike_everywhere(make: Factory) -> None:
    a = make("host-a")
    limit(a, 2)
    a.params.set("/r1/camera/dbm/priority", 0.5)
    a.params.set("/r2/camera/dbm/priority", 0.5)
    message = r"^/r3/camera/dbm/priority=0\.5: this process wrote \d+ parameter names, and \d+"
    with pytest.raises(TransportError, match=message):
        a.params.set("/r3/camera/dbm/priority", 0.5)
    with pytest.raises(TransportError, match=message):
        a.params.set_many({"/r1/camera/dbm/priority": 0.25, "/r3/camera/dbm/priority": 0.5})
    a.params.set("/r1/camera/dbm/priority", 0.75)  # a name it wrote is always written again
    wait_for(lambda: a.params.get("/r1/camera/dbm/priority") == 0.75, what="the rewrite")
    assert a.params.get("/r3/camera/dbm/priority") is None
