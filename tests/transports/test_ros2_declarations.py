"""The ros2 transport declares nothing under a lock: a slow declaration holds up nobody else."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from dbml.transports import Publisher, Variant
from dbml.transports.ros2 import Ros2Transport
from tests.transports.ros2_network import Factory, ros2_network

TIMEOUT_S = 10.0
"""How long a test waits for a thread that should not be held up at all."""


@pytest.fixture
def make() -> Iterator[Factory]:
    yield from ros2_network()


def test_a_priority_subscription_is_declared_outside_every_lock(
    make: Factory, monkeypatch: pytest.MonkeyPatch
) -> None:
    transport = make("robot-1")
    assert isinstance(transport, Ros2Transport)
    real = transport._subscribe_key
    declaring = threading.Event()
    release = threading.Event()

    def slow(name: str, *args: Any) -> Any:
        if name == "/r1/cam/dbm/priority":
            declaring.set()
            assert release.wait(TIMEOUT_S), "the test never released the declaration"
        return real(name, *args)

    monkeypatch.setattr(transport, "_subscribe_key", slow)
    made: dict[str, Publisher] = {}

    def declare(topic: str) -> None:
        made[topic] = transport.declare_publisher(topic, Variant.OPTIMIZED)

    first = threading.Thread(target=declare, args=("/r1/cam",), daemon=True)
    first.start()
    assert declaring.wait(TIMEOUT_S)
    # While zenoh declares the first channel's subscription: the transport's state is free
    # (a zenoh callback may need it), and another channel declares without waiting.
    assert transport._lock.acquire(timeout=TIMEOUT_S)
    transport._lock.release()
    other = threading.Thread(target=declare, args=("/r2/cam",), daemon=True)
    other.start()
    other.join(timeout=TIMEOUT_S)
    assert not other.is_alive(), "the second channel waited for the first one's declaration"
    assert first.is_alive()  # still declaring
    release.set()
    first.join(timeout=TIMEOUT_S)
    assert set(made) == {"/r1/cam", "/r2/cam"}
    assert {topic: count for topic, (_, count) in transport._priorities.items()} == {
        "/r1/cam": 1,
        "/r2/cam": 1,
    }
    for publisher in made.values():
        publisher.close()
    assert transport._priorities == {}
    assert transport._declaring == {}


def test_a_failed_declaration_lets_a_waiting_publisher_declare_its_own(
    make: Factory, monkeypatch: pytest.MonkeyPatch
) -> None:
    transport = make("robot-1")
    assert isinstance(transport, Ros2Transport)
    real = transport._subscribe_key
    calls: list[str] = []
    declaring = threading.Event()
    release = threading.Event()

    def failing_once(name: str, *args: Any) -> Any:
        calls.append(name)
        if len(calls) == 1:
            declaring.set()
            assert release.wait(TIMEOUT_S), "the test never released the declaration"
            raise RuntimeError("refused")
        return real(name, *args)

    monkeypatch.setattr(transport, "_subscribe_key", failing_once)
    failures: list[BaseException] = []
    made: list[Publisher] = []

    def declare() -> None:
        try:
            made.append(transport.declare_publisher("/r1/cam", Variant.OPTIMIZED))
        except RuntimeError as err:
            failures.append(err)

    threads = [threading.Thread(target=declare, daemon=True) for _ in range(2)]
    threads[0].start()
    assert declaring.wait(TIMEOUT_S)
    threads[1].start()  # finds the declaration under way, and waits for it
    release.set()
    for thread in threads:
        thread.join(timeout=TIMEOUT_S)
    assert [str(err) for err in failures] == ["refused"]
    assert calls == ["/r1/cam/dbm/priority", "/r1/cam/dbm/priority"]
    assert transport._priorities["/r1/cam"][1] == 1
    made[0].close()
    assert transport._priorities == {}
