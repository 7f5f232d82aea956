"""A command's lifetime: a dead dbml thread ends it with exit code 1."""

from __future__ import annotations

import logging
import threading

import pytest

from dbml.runtime.serve import Lifetime
from dbml.transports.worker import BackgroundThread
from tests.conftest import wait_for


def test_a_run_ends_when_stopped_and_exits_zero() -> None:
    stop = threading.Event()
    life = Lifetime(stop, None)
    assert not life.over()
    stop.set()
    assert life.over()
    assert life.exit_code() == 0


def test_a_run_ends_after_its_duration() -> None:
    life = Lifetime(threading.Event(), 0.0)
    assert life.over()
    assert life.exit_code() == 0


def test_a_thread_that_dies_during_the_run_ends_it_with_exit_code_1(
    caplog: pytest.LogCaptureFixture,
) -> None:
    life = Lifetime(threading.Event(), None)

    def fail() -> None:
        raise RuntimeError("broken")

    with caplog.at_level(logging.CRITICAL):
        thread = BackgroundThread(fail, name="doomed", log=logging.getLogger("test")).start()
        wait_for(lambda: not thread.alive, timeout_s=5.0, what="the thread's death")
    assert life.over()
    assert life.exit_code() == 1
    assert "a worker thread died" in caplog.text
    assert not Lifetime(threading.Event(), None).over()  # a later run starts clean


class Part:
    """A node part watched by a run: ``alive`` until the test ends it."""

    def __init__(self) -> None:
        self.alive = True


def test_a_watched_part_that_ends_without_dying_ends_the_run_with_exit_code_1(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A loop that returned (no death counted) leaves a process doing nothing: it exits 1."""
    part = Part()
    life = Lifetime(threading.Event(), None, watching=[Part(), part])
    assert not life.over()
    assert not life.failed
    part.alive = False
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        assert life.over()
        assert life.failed
        part.alive = True  # what ``over`` saw stays seen
        assert life.exit_code() == 1
    assert [r.getMessage() for r in caplog.records] == [
        "a worker thread died (see above); exiting so a supervisor restarts it"
    ]


def test_watched_parts_closed_after_the_run_ended_are_no_failure() -> None:
    stop = threading.Event()
    part = Part()
    life = Lifetime(stop, None, watching=[part])
    stop.set()
    assert life.over()
    part.alive = False  # closed by the command once its run is over
    assert not life.failed
    assert life.exit_code() == 0
