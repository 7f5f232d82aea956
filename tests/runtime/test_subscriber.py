"""The managed subscriber over the memory transport: it follows the graph on its own thread."""

import sys
import threading
import time
from collections.abc import Callable

import pytest

from dbml.core.errors import TransportError
from dbml.protocol import names
from dbml.runtime import ManagedPublisher, ManagedSubscriber
from dbml.transports import MemoryNetwork, MemoryTransport, Role, Sample, Variant
from dbml.transports.base import GraphEntry, Handle
from tests.conftest import wait_for

TIMEOUT_S = 10.0
"""How long a test waits for the subscriber's worker to act (it does within milliseconds)."""
CALLBACK_BOUND_S = 1.0
"""How long a graph change may take to report: far below a switch held up for ``TIMEOUT_S``."""


def subscriber_tokens(transport: MemoryTransport) -> list[tuple[str, Variant]]:
    return sorted(
        (e.host, e.variant) for e in transport.graph.entries() if e.role is Role.SUBSCRIBER
    )


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
    wait_for(lambda: variant() is Variant.FULL, timeout_s=TIMEOUT_S, what="the full copy")
    wait_for(
        lambda: subscriber_tokens(operator) == [("op", Variant.FULL)],
        timeout_s=TIMEOUT_S,
        what="the optimized copy's announcement withdrawn",
    )
    on_op.close()
    elsewhere = ManagedPublisher(
        MemoryTransport(network, host="r9"), "/cam", min_rate_hz=1, max_rate_hz=16
    )
    wait_for(
        lambda: subscriber_tokens(operator) == [("op", Variant.OPTIMIZED)],
        timeout_s=TIMEOUT_S,
        what="back to the optimized copy, announced alone",
    )
    assert variant() is Variant.OPTIMIZED
    operator.params.set(names.current_value("/cam"), 16.0)  # the optimizer's allocation
    elsewhere.publish(b"frame")
    assert [s.payload for s in got] == [b"frame"]


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

    def tokens() -> list[tuple[str, Variant]]:
        entries = operator.graph.entries()
        return sorted((e.topic, e.variant) for e in entries if e.role is Role.SUBSCRIBER)

    wait_for(
        lambda: tokens() == [("/a", Variant.OPTIMIZED), ("/b", Variant.OPTIMIZED)],
        timeout_s=TIMEOUT_S,
        what="both subscribers back on the optimized copy",
    )
    assert all(s.variant is Variant.OPTIMIZED for s in subscribers.values())


def test_a_failed_graph_read_does_not_freeze_the_subscriber() -> None:
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    subscriber = ManagedSubscriber(operator, "/cam", lambda s: None)
    entries = operator.graph.entries
    failures = [TransportError("master unreachable")]

    def flaky(*, topic: str | None = None) -> frozenset[GraphEntry]:
        if failures:
            raise failures.pop()
        return entries(topic=topic)

    operator.graph.entries = flaky  # type: ignore[method-assign]
    robot = MemoryTransport(network, host="r9")
    ManagedPublisher(robot, "/other", min_rate_hz=1, max_rate_hz=16)  # a graph event that fails
    wait_for(lambda: not failures, timeout_s=TIMEOUT_S, what="the failing graph read")
    ManagedPublisher(operator, "/cam", min_rate_hz=1, max_rate_hz=16)  # the next one switches
    wait_for(lambda: subscriber.variant is Variant.FULL, timeout_s=TIMEOUT_S, what="the switch")
    assert subscriber.alive


def test_a_graph_change_is_followed_on_the_subscribers_thread_not_the_reporting_one() -> None:
    """A switch subscribes and announces: middleware calls, never made on a callback's thread.

    Here the thread that reports the change is the one whose publisher changed the graph.
    """
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    subscriber = ManagedSubscriber(operator, "/cam", lambda s: None)
    real = operator.subscribe
    release = threading.Event()
    callers: list[str] = []

    def held_up(
        topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        callers.append(threading.current_thread().name)
        assert release.wait(TIMEOUT_S), "the test never released the subscription"
        return real(topic, callback, variant)

    operator.subscribe = held_up  # type: ignore[method-assign]
    started = time.monotonic()
    camera_here = MemoryTransport(network, host="op")  # another process on the same host
    ManagedPublisher(camera_here, "/cam", min_rate_hz=1, max_rate_hz=16)  # fires the watch
    took_s = time.monotonic() - started
    wait_for(lambda: bool(callers), timeout_s=TIMEOUT_S, what="the switch to start")
    release.set()
    assert took_s < CALLBACK_BOUND_S, f"the graph change took {took_s:.3f} s to report"
    assert callers == ["dbml-subscriber /cam"]
    wait_for(lambda: subscriber.variant is Variant.FULL, timeout_s=TIMEOUT_S, what="the switch")
    subscriber.close()
    assert subscriber_tokens(operator) == []


def test_a_subscriber_whose_thread_dies_says_so(caplog: pytest.LogCaptureFixture) -> None:
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    subscriber = ManagedSubscriber(operator, "/cam", lambda s: None)

    def fatal(*, topic: str | None = None) -> frozenset[GraphEntry]:
        raise SystemExit("the graph view is gone")

    operator.graph.entries = fatal  # type: ignore[method-assign]
    ManagedPublisher(operator, "/cam", min_rate_hz=1, max_rate_hz=16)
    wait_for(lambda: not subscriber.alive, timeout_s=TIMEOUT_S, what="the thread's death")
    assert "dbml-subscriber /cam: the thread died" in caplog.text
