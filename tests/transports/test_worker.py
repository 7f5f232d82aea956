"""dbml's background threads: the ordered sender's queue, and every thread's death said."""

from __future__ import annotations

import logging
import threading

import pytest

from dbml.transports.worker import BackgroundThread, OrderedSender, PeriodicWorker, death_count
from tests.conftest import wait_for

TIMEOUT_S = 10.0
"""How long a test waits for a thread that acts within milliseconds."""
log = logging.getLogger("dbml.test")


class Gate:
    """A send that blocks until opened (a stalled network), recording what it sent."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.opened = threading.Event()
        self.sent: list[str] = []

    def __call__(self, item: str) -> None:
        self.entered.set()
        assert self.opened.wait(TIMEOUT_S), "the test never opened the gate"
        self.sent.append(item)


def test_items_go_in_order_and_a_slots_newer_item_replaces_the_queued_one() -> None:
    gate = Gate()
    sender: OrderedSender[str] = OrderedSender(gate, name="test-send", log=log)
    sender.put("first")
    assert gate.entered.wait(TIMEOUT_S)  # in flight: the rest waits in the queue
    sender.put("a1", slot="a")
    sender.put("batch")
    sender.put("b1", slot="b")
    sender.put("a2", slot="a")  # replaces a1, and goes to the back
    assert sender.pending() == ["first", "batch", "b1", "a2"]
    assert not sender.flush(0.01)
    gate.opened.set()
    assert sender.flush(TIMEOUT_S)
    assert gate.sent == ["first", "batch", "b1", "a2"]
    assert sender.close(TIMEOUT_S)
    sender.put("late")  # ignored once closed
    assert sender.pending() == []


def test_a_full_queue_drops_its_oldest_item_and_says_so_once_per_stall(
    caplog: pytest.LogCaptureFixture,
) -> None:
    gate = Gate()
    sender: OrderedSender[str] = OrderedSender(gate, name="test-send", log=log, capacity=3)
    with caplog.at_level(logging.WARNING, logger="dbml.test"):
        sender.put("in flight")
        assert gate.entered.wait(TIMEOUT_S)
        for item in ("1", "2", "3", "4", "5"):
            sender.put(item)
        assert sender.pending() == ["in flight", "3", "4", "5"]
        assert sender.dropped == 2
        assert caplog.records == []  # ``put`` logs nothing: its caller may hold a lock
        gate.opened.set()
        assert sender.flush(TIMEOUT_S)
    assert gate.sent == ["in flight", "3", "4", "5"]
    # Told by the sender's thread once the stalled send returned, and the end of the stall too.
    assert [(r.threadName, r.getMessage()) for r in caplog.records] == [
        (
            "test-send",
            "test-send: unsent items: 3 held, the most kept; evicting the oldest "
            "(told once until half of them are gone)",
        ),
        ("test-send", "test-send: unsent items: room again; 2 evicted meanwhile"),
    ]
    sender.close(TIMEOUT_S)


def test_a_failed_send_loses_that_item_only(caplog: pytest.LogCaptureFixture) -> None:
    sent: list[str] = []

    def send(item: str) -> None:
        if item == "bad":
            raise OSError("session closed")
        sent.append(item)

    sender: OrderedSender[str] = OrderedSender(send, name="test-send", log=log)
    with caplog.at_level(logging.WARNING, logger="dbml.test"):
        for item in ("a", "bad", "b"):
            sender.put(item)
        assert sender.flush(TIMEOUT_S)
    assert sent == ["a", "b"]
    assert "test-send: 'bad' not sent: session closed" in caplog.text
    assert sender.alive
    sender.close(TIMEOUT_S)


def test_a_close_with_the_network_stalled_is_bounded_and_says_so() -> None:
    gate = Gate()
    sender: OrderedSender[str] = OrderedSender(gate, name="test-send", log=log)
    sender.put("stuck")
    assert gate.entered.wait(TIMEOUT_S)
    sender.put("never")
    assert not sender.close(0.05)  # returns with "stuck" in flight and "never" queued
    assert sender.pending() == ["stuck"]  # what was queued is given up
    gate.opened.set()
    wait_for(lambda: not sender.pending(), timeout_s=TIMEOUT_S, what="the send in flight")
    assert gate.sent == ["stuck"]


def test_the_capacity_must_be_positive() -> None:
    with pytest.raises(ValueError, match="capacity=0 must be at least 1"):
        OrderedSender(lambda _item: None, name="test-send", log=log, capacity=0)


def test_a_sender_whose_thread_dies_says_so(caplog: pytest.LogCaptureFixture) -> None:
    def send(_item: str) -> None:
        raise SystemExit("not an Exception: it ends the thread")

    deaths = death_count()
    sender: OrderedSender[str] = OrderedSender(send, name="test-send-dies", log=log)
    sender.put("x")
    wait_for(lambda: not sender.alive, timeout_s=TIMEOUT_S, what="the thread's death")
    assert death_count() == deaths + 1
    assert "test-send-dies: the thread died" in caplog.text


def test_a_background_thread_that_raises_is_dead_and_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ended = threading.Event()

    def target() -> None:
        ended.set()
        raise RuntimeError("broken loop")

    deaths = death_count()
    thread = BackgroundThread(target, name="test-loop-dies", log=log).start()
    assert ended.wait(TIMEOUT_S)
    wait_for(lambda: not thread.alive, timeout_s=TIMEOUT_S, what="the thread's death")
    assert death_count() == deaths + 1
    assert "test-loop-dies: the thread died" in caplog.text
    clean = BackgroundThread(lambda: None, name="test-loop-ends", log=log).start()
    clean.join(TIMEOUT_S)
    assert clean.alive  # returning is a normal end, not a death
    assert death_count() == deaths + 1
    assert "test-loop-ends" not in caplog.text


def test_a_periodic_worker_survives_a_failing_tick_and_reports_its_death(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ticks: list[int] = []

    def tick() -> None:
        ticks.append(1)
        if len(ticks) == 1:
            raise ValueError("a bad input: the next tick retries")
        if len(ticks) == 2:
            raise SystemExit("ends the thread")

    deaths = death_count()
    worker = PeriodicWorker(tick, interval_s=0.01, name="test-worker-dies", log=log).start()
    wait_for(lambda: not worker.alive, timeout_s=TIMEOUT_S, what="the thread's death")
    assert len(ticks) == 2
    assert death_count() == deaths + 1
    assert "test-worker-dies: the thread died" in caplog.text


def test_a_periodic_worker_is_alive_while_its_thread_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A run polls ``alive`` from another thread; read while the thread was made but not yet
    # started, it once said dead and the optimizer exited 1 right after its activation.
    worker = PeriodicWorker(lambda: None, interval_s=10.0, name="test-worker-starts", log=log)
    seen: list[bool] = []
    start = threading.Thread.start

    def look_then_start(thread: threading.Thread) -> None:
        seen.append(worker.alive)
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", look_then_start)
    worker.start()
    monkeypatch.undo()
    try:
        assert seen == [True]
        assert worker.alive
    finally:
        worker.stop()


def test_a_background_thread_tells_its_own_calls_from_others_from_its_first_instruction() -> None:
    seen: list[bool] = []

    def target() -> None:
        seen.append(thread.is_current())  # at once: no window before the thread is known

    thread = BackgroundThread(target, name="test-current", log=log)
    assert not thread.is_current()
    thread.start()
    thread.join(TIMEOUT_S)
    assert seen == [True]
    assert not thread.is_current()
