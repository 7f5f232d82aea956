"""Testbed fixtures: skip without privileges locally, fail in CI where they must be present."""

from __future__ import annotations

import fcntl
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbml.testbed import privilege_problem
from tests.conftest import require

TESTBED_LOCK = Path("/tmp/dbml-testbed.lock")
"""Held for a testbed test's whole run: two runs on one machine would share its CPU and time
each other's frames wrongly (``flock /tmp/dbml-testbed.lock dbml testbed ...`` takes it too)."""


@pytest.fixture(scope="session")
def netns_privilege() -> None:
    """Stop a namespace test early when this process cannot build namespaces."""
    require(privilege_problem(), what="be able to build network namespaces")


@pytest.fixture(autouse=True)
def testbed_alone() -> Iterator[None]:
    """One testbed test at a time on this machine, whichever process runs it."""
    with TESTBED_LOCK.open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
