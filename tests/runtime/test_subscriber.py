import sys
import threading

from dbml.core.errors import TransportError
from dbml.runtime import ManagedPublisher, ManagedSubscriber, names
from dbml.transports import MemoryNetwork, MemoryTransport, Role, Sample, Variant
from dbml.transports.base import GraphEntry


def test_local_publisher_means_full_rate_remote_means_optimized() -> None:
    network = MemoryNetwork()
    robot = MemoryTransport(network, host="r1")
    ManagedPublisher(robot, "/r1/camera", min_rate_hz=1, max_rate_hz=16)
    local = ManagedSubscriber(MemoryTransport(network, host="r1"), "/r1/camera", lambda s: None)
    remote = ManagedSubscriber(MemoryTransport(network, host="op"), "/r1/camera", lambda s: None)
    assert local.variant is Variant.FULL
    assert remote.variant is Variant.OPTIMIZED
    subs = {(e.host, e.variant) for e in robot.graph.entries() if e.role is Role.SUBSCRIBER}
    assert subs == {("r1", Variant.FULL), ("op", Variant.OPTIMIZED)}


def test_switches_when_the_publisher_moves() -> None:
    network = MemoryNetwork()
    got: list[Sample] = []
    operator = MemoryTransport(network, host="op")
    subscriber = ManagedSubscriber(operator, "/cam", got.append)

    def variant() -> Variant:
        return subscriber.variant

    assert variant() is Variant.OPTIMIZED  # nobody publishes yet: the safe copy
    on_op = ManagedPublisher(operator, "/cam", min_rate_hz=1, max_rate_hz=16)
    assert variant() is Variant.FULL
    on_op.close()
    elsewhere = ManagedPublisher(
        MemoryTransport(network, host="r9"), "/cam", min_rate_hz=1, max_rate_hz=16
    )
    assert variant() is Variant.OPTIMIZED
    operator.params.set(names.current_value("/cam"), 16.0)  # the optimizer's allocation
    elsewhere.publish(b"frame")
    assert [s.payload for s in got] == [b"frame"]
    tokens = [e for e in operator.graph.entries() if e.role is Role.SUBSCRIBER]
    assert [(t.host, t.variant) for t in tokens] == [("op", Variant.OPTIMIZED)]


def test_close_withdraws_the_subscription() -> None:
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    subscriber = ManagedSubscriber(operator, "/cam", lambda s: None)
    subscriber.close()
    assert not [e for e in operator.graph.entries() if e.role is Role.SUBSCRIBER]


def test_two_subscribers_switching_at_once_from_two_threads_do_not_deadlock() -> None:
    """No subscriber may hold its lock while it announces.

    Announcing fires every graph watcher, other subscribers' among them (each switch below fires
    the other subscriber's update).
    """
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    subscribers = {
        topic: ManagedSubscriber(operator, topic, lambda s: None) for topic in ("/a", "/b")
    }
    rounds = 2000
    done = {topic: threading.Event() for topic in subscribers}

    def flip(topic: str) -> None:
        for _ in range(rounds):  # a local publisher comes and goes: full, then optimized
            ManagedPublisher(operator, topic, min_rate_hz=1, max_rate_hz=16).close()
        done[topic].set()

    threads = [threading.Thread(target=flip, args=(t,), daemon=True) for t in subscribers]
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # interleave the threads inside every switch (found it before)
    try:
        for thread in threads:
            thread.start()
        for topic, event in done.items():
            assert event.wait(timeout=30), f"the thread switching {topic} is stuck (deadlock)"
    finally:
        sys.setswitchinterval(interval)
    for thread in threads:
        thread.join(timeout=5)
    assert all(s.variant is Variant.OPTIMIZED for s in subscribers.values())
    tokens = sorted(
        (e.topic, e.variant) for e in operator.graph.entries() if e.role is Role.SUBSCRIBER
    )
    assert tokens == [("/a", Variant.OPTIMIZED), ("/b", Variant.OPTIMIZED)]


def test_a_failed_graph_read_does_not_freeze_the_subscriber() -> None:
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    subscriber = ManagedSubscriber(operator, "/cam", lambda s: None)
    entries = operator.graph.entries
    failures = [TransportError("master unreachable")]

    def flaky() -> frozenset[GraphEntry]:
        if failures:
            raise failures.pop()
        return entries()

    operator.graph.entries = flaky  # type: ignore[method-assign]
    robot = MemoryTransport(network, host="r9")
    ManagedPublisher(robot, "/other", min_rate_hz=1, max_rate_hz=16)  # a graph event that fails
    assert not failures
    ManagedPublisher(operator, "/cam", min_rate_hz=1, max_rate_hz=16)  # the next one switches
    assert subscriber.variant is Variant.FULL
