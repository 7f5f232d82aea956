"""Shared test helpers: waiting on conditions (never bare sleeps)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from tests.ros1.rosnet import RosNet


MONITOR_JSON_KEYS = frozenset(
    {
        "topic",
        "host",
        "managed",
        "priority",
        "size_bytes",
        "allocated_hz",
        "share",
        "status",
        "estimate_mbit",
        "estimator",
    }
)
"""``dbml monitor --json``: the keys of each line (a contract scripts read)."""


def require(problem: str | None, *, what: str) -> None:
    """Skip with ``problem`` when something a test needs is missing; in CI (CI=true) fail."""
    if problem is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI must {what}: {problem}")
    pytest.skip(problem)


def wait_for(predicate: Callable[[], bool], *, timeout_s: float = 5.0, what: str = "") -> None:
    """Poll ``predicate`` until it holds; fail the test with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what or predicate}")
        time.sleep(0.005)


@pytest.fixture
def ros(tmp_path: Path) -> Iterator[RosNet]:
    """A private ROS master with its nodes; skipped without ROS 1 (a failure when CI=true)."""
    from tests.ros1.rosnet import rosnet

    with rosnet(tmp_path) as net:
        yield net


@pytest.fixture(autouse=True)
def isolated_logging() -> Iterator[None]:
    """A ``main()`` run in-process may configure the root logger: undo it after each test.

    Its handler writes to the test's captured stderr, which is closed once the test ends; left
    in place it would turn every later log line of the session into a logging error.
    """
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        yield
    finally:
        for handler in root.handlers:
            if handler not in handlers:
                root.removeHandler(handler)
        root.setLevel(level)
