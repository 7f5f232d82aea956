"""The one callback list every transport uses."""

from __future__ import annotations

import logging
import threading

import pytest

from dbml.transports.base import Handle
from dbml.transports.callbacks import CallbackList
from tests.conftest import wait_for


def test_fire_calls_every_callback_in_order_until_its_handle_closes() -> None:
    callbacks: CallbackList[[int]] = CallbackList()
    seen: list[tuple[str, int]] = []
    first = callbacks.add(lambda n: seen.append(("first", n)))
    callbacks.add(lambda n: seen.append(("second", n)))
    assert callbacks
    callbacks.fire(1)
    first.close()
    first.close()  # twice is harmless
    callbacks.fire(2)
    assert seen == [("first", 1), ("second", 1), ("second", 2)]


def test_an_empty_list_is_false() -> None:
    callbacks: CallbackList[[]] = CallbackList()
    handle = callbacks.add(lambda: None)
    handle.close()
    assert not callbacks


def test_a_failing_callback_is_logged_and_the_rest_still_run(
    caplog: pytest.LogCaptureFixture,
) -> None:
    callbacks: CallbackList[[str]] = CallbackList()
    seen: list[str] = []

    def fail(_: str) -> None:
        raise ValueError("broken watcher")

    callbacks.add(fail)
    callbacks.add(seen.append)
    with caplog.at_level(logging.ERROR, logger="dbml.transports"):
        callbacks.fire("x")
    assert seen == ["x"]
    assert "broken watcher" in caplog.text


def test_a_callback_closed_during_a_fire_is_not_called_after() -> None:
    callbacks: CallbackList[[]] = CallbackList()
    seen: list[str] = []
    handles: list[Handle] = []

    def close_the_next() -> None:
        handles[1].close()

    handles.append(callbacks.add(close_the_next))
    handles.append(callbacks.add(lambda: seen.append("late")))
    callbacks.fire()
    assert seen == []


def test_callbacks_run_outside_the_lock_so_they_may_add_and_fire() -> None:
    callbacks: CallbackList[[int]] = CallbackList()
    seen: list[int] = []

    def reenter(n: int) -> None:
        seen.append(n)
        if n == 0:
            callbacks.add(lambda m: seen.append(100 + m))
            callbacks.fire(1)

    callbacks.add(reenter)
    done = threading.Event()

    def run() -> None:
        callbacks.fire(0)
        done.set()

    threading.Thread(target=run, daemon=True).start()
    wait_for(done.is_set, timeout_s=2.0, what="a re-entrant fire to return")
    assert seen == [0, 1, 101]
