"""The ros2 transport declares nothing under a lock: a slow declaration holds up nobody else."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from dbml.transports import Publisher, Variant
from dbml.transports.ros2 import Ros2Transport
from dbml.transports.ros2 import transport as ros2
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
    assert {topic: hearing.users for topic, hearing in transport._priorities.items()} == {
        "/r1/cam": 1,
        "/r2/cam": 1,
    }
    for publisher in made.values():
        publisher.close()
    assert transport._priorities == {}
    assert transport._handles == set()  # the publishers and their subscriptions


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
    assert transport._priorities["/r1/cam"].users == 1
    made[0].close()
    assert transport._priorities == {}


class HeldDeclaration:
    """``_subscribe_key`` for the transport: its priority subscriptions wait to be released."""

    def __init__(self, transport: Ros2Transport) -> None:
        self._real = transport._subscribe_key
        self.declaring = threading.Event()
        self.release = threading.Event()

    def __call__(self, name: str, *args: Any) -> Any:
        if name.endswith("/dbm/priority"):
            self.declaring.set()
            assert self.release.wait(TIMEOUT_S), "the test never released the declaration"
        return self._real(name, *args)


def test_a_publisher_waits_for_a_hung_declaration_only_so_long_then_shares_it(
    make: Factory, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    transport = make("robot-1")
    assert isinstance(transport, Ros2Transport)
    held = HeldDeclaration(transport)
    monkeypatch.setattr(transport, "_subscribe_key", held)
    monkeypatch.setattr(ros2, "_PRIORITY_WAIT_S", 0.05)  # the declaration is held till released
    made: list[Publisher] = []
    first = threading.Thread(
        target=lambda: made.append(transport.declare_publisher("/r1/cam", Variant.OPTIMIZED)),
        daemon=True,
    )
    first.start()
    assert held.declaring.wait(TIMEOUT_S)
    with caplog.at_level(logging.WARNING, logger="dbml.ros2"):
        second = transport.declare_publisher("/r1/cam", Variant.OPTIMIZED)  # not held for good
    assert [r.getMessage() for r in caplog.records if r.name == "dbml.ros2"] == [
        "/r1/cam: its priority subscription is still being declared after 0.05 s; going on, "
        "hearing priority once it is"
    ]
    hearing = transport._priorities["/r1/cam"]
    assert (hearing.users, hearing.done.is_set()) == (2, False)
    second.close()  # during the declaration: taken off at once
    assert hearing.users == 1
    held.release.set()
    first.join(timeout=TIMEOUT_S)
    assert not first.is_alive()
    assert transport._priorities == {"/r1/cam": hearing}
    assert (hearing.users, hearing.done.is_set()) == (1, True)
    made[0].close()  # the last user: the subscription is undeclared
    assert transport._priorities == {}
    assert transport._handles == set()


def test_a_subscription_whose_users_all_closed_during_its_declaration_is_undeclared_at_once(
    make: Factory, monkeypatch: pytest.MonkeyPatch
) -> None:
    transport = make("robot-1")
    assert isinstance(transport, Ros2Transport)
    held = HeldDeclaration(transport)
    monkeypatch.setattr(transport, "_subscribe_key", held)
    heard: list[ros2._PriorityHearing] = []
    declaring = threading.Thread(
        target=lambda: heard.append(transport._hear_priority("/r1/cam")), daemon=True
    )
    declaring.start()
    assert held.declaring.wait(TIMEOUT_S)
    pending = transport._priorities["/r1/cam"]
    transport._unhear_priority("/r1/cam", pending)  # finds no subscription yet: recorded
    held.release.set()
    declaring.join(timeout=TIMEOUT_S)
    assert heard == [pending]
    assert pending.handle is not None  # declared, then undeclared at once by the declaration
    assert transport._priorities == {}
    assert transport._handles == set()
