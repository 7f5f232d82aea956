"""Python child processes for the ROS 2 tests: bounded reads, ended by their PID."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import pytest

from dbml.harness.processes import end_process
from dbml.harness.ros2env import fastdds_shm_files

CHILD_TIMEOUT_S = 30.0
"""The most a child may take to start, answer or end."""


def first_line(process: subprocess.Popen[str], *, timeout_s: float = CHILD_TIMEOUT_S) -> str:
    """The first line ``process`` writes, read by a thread so that waiting for it is bounded."""
    lines: queue.Queue[str] = queue.Queue()
    assert process.stdout is not None
    stdout = process.stdout
    threading.Thread(target=lambda: lines.put(stdout.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout_s).strip()
    except queue.Empty:
        pytest.fail(f"no line from pid {process.pid} after {timeout_s} s")


@contextmanager
def python_child(
    code: str, *args: str, env: Mapping[str, str] | None = None
) -> Iterator[subprocess.Popen[str]]:
    """A Python child running ``code``; ended after (stdin closed, then signals, by its PID)."""
    process = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=None if env is None else dict(env),
    )
    try:
        yield process
    finally:
        if process.stdin is not None:
            process.stdin.close()
        end_process(process, timeout_s=CHILD_TIMEOUT_S)
        if process.stdout is not None:
            process.stdout.close()


def held_by_live_processes(files: list[Path]) -> bool:
    """Whether each of ``files`` still there is a live process's (a name another one took over)."""
    left = {path for path in files if path.exists()}
    live = [int(name) for name in os.listdir("/proc") if name.isdigit()]
    return left <= set(fastdds_shm_files(live))
