"""The ros1 graph's polling thread: a failed poll is retried, and its death is said.

A fake master: the graph is the master's XML-RPC API, no rospy needed.
"""

from __future__ import annotations

import threading
from typing import Any

import pytest

from dbml.core.errors import TransportError
from dbml.transports.ros1.graph import Ros1Graph
from dbml.transports.worker import death_count
from tests.conftest import wait_for

TIMEOUT_S = 10.0
"""How long a test waits for a poll (one every ``POLL_S``)."""
POLL_S = 0.01
"""The test's polling period: fast, so that a few polls take no time."""


class Master:
    """A master API whose ``getSystemState`` fails as told, then lists ``node`` publishing."""

    caller_id = "/graph_test"

    def __init__(self, *failures: BaseException) -> None:
        self.failures = list(failures)
        self.polls = 0
        self.lock = threading.Lock()

    def call(self, method: str, *args: Any, missing_ok: bool = False) -> Any:
        if method == "lookupNode":
            return None  # no URI: the node is left out, with no ping to make
        assert method == "getSystemState", method
        with self.lock:
            self.polls += 1
            if self.failures:
                raise self.failures.pop(0)
        return [[["/r1/camera", ["/camera"]]], [], []]


def test_a_poll_that_raises_anything_is_logged_and_retried(
    caplog: pytest.LogCaptureFixture,
) -> None:
    master = Master(TransportError("master away"), ValueError("a malformed answer"))
    graph = Ros1Graph(master, POLL_S)  # type: ignore[arg-type]
    try:
        graph.watch(lambda: None)
        wait_for(lambda: master.polls >= 3, timeout_s=TIMEOUT_S, what="polls after failures")
        assert graph.alive
        assert "graph: master away" in caplog.text
        assert "dbml-ros1-graph: tick failed" in caplog.text
    finally:
        graph.close()


def test_a_polling_thread_that_dies_says_so(caplog: pytest.LogCaptureFixture) -> None:
    master = Master(SystemExit("ends the thread"))
    graph = Ros1Graph(master, POLL_S)  # type: ignore[arg-type]
    deaths = death_count()
    try:
        graph.watch(lambda: None)
        wait_for(lambda: not graph.alive, timeout_s=TIMEOUT_S, what="the thread's death")
        assert death_count() == deaths + 1
        assert "dbml-ros1-graph: the thread died" in caplog.text
    finally:
        graph.close()
