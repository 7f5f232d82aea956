"""Python child processes for the ROS 2 tests: bounded reads, ended by their PID."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import pytest

from dbml.harness.ros2env import fastdds_shm_files
from dbml.harness.supervisor import ProcessChild, Supervisor

CHILD_TIMEOUT_S = 30.0
"""The most a child may take to start, answer or end."""


def first_line(process: ProcessChild, *, timeout_s: float = CHILD_TIMEOUT_S) -> str:
    """The next line ``process`` writes, waited for at most ``timeout_s``."""
    line = process.next(timeout_s=timeout_s)
    if line is None or line.ended:
        pytest.fail(f"no line from pid {process.pid} after {timeout_s} s: {process.log_tail()}")
    return line.text.strip()


@contextmanager
def python_child(
    code: str, *args: str, env: Mapping[str, str] | None = None
) -> Iterator[ProcessChild]:
    """A Python child running ``code``; ended after (stdin closed, then signals, by its PID)."""
    with Supervisor() as children:
        yield children.start("child", [sys.executable, "-c", code, *args], env=env)


def held_by_live_processes(files: list[Path]) -> bool:
    """Whether each of ``files`` still there is a live process's (a name another one took over)."""
    left = {path for path in files if path.exists()}
    live = [int(name) for name in os.listdir("/proc") if name.isdigit()]
    return left <= set(fastdds_shm_files(live))
