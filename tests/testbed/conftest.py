"""Testbed fixtures: skip without privileges locally, fail in CI where they must be present."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbml.harness.ros2env import flock_holders
from dbml.testbed import privilege_problem
from tests.conftest import require

TESTBED_LOCK = Path("/tmp/dbml-testbed.lock")
"""Held for a testbed test's whole run: two runs on one machine would share its CPU and time
each other's frames wrongly (``flock /tmp/dbml-testbed.lock dbml testbed ...`` takes it too).
Under ``flock /tmp/dbml-testbed.lock pytest ...`` the lock is an ancestor's: taken already."""


@pytest.fixture(scope="session")
def netns_privilege() -> None:
    """Stop a namespace test early when this process cannot build namespaces."""
    require(privilege_problem(), what="be able to build network namespaces")


@pytest.fixture(autouse=True)
def testbed_alone() -> Iterator[None]:
    """One testbed test at a time on this machine, whichever process runs it."""
    if _held_by_an_ancestor(TESTBED_LOCK):
        yield  # locking again would wait for ourselves
        return
    with TESTBED_LOCK.open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _held_by_an_ancestor(path: Path) -> bool:
    """Whether a process this one descends from holds ``path``'s flock."""
    if not path.exists():
        return False
    holders = flock_holders(path)
    pid = os.getppid()
    while pid > 1:
        if pid in holders:
            return True
        try:
            stat = Path(f"/proc/{pid}/stat").read_text(encoding="utf-8")
        except OSError:
            return False
        pid = int(stat.rsplit(")", 1)[1].split()[1])  # the field after the state: the parent
    return False
