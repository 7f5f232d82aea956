"""Scenario roles as OS processes, driven over stdin and read over stdout as JSON lines.

Both ``dbml demo teleop`` (on loopback) and ``dbml testbed teleop`` (inside network namespaces)
start one process per role, wait for ``{"type": "ready"}``, send ``start <t0>``, and read the
roles' reports. This is that plumbing, once: every line lands in one queue, ``None`` marks a
process's end, and ``close()`` ends every process it started, by PID (ask, terminate, kill).

The role side is :func:`serve_role`: announce readiness, wait for the start time, run, and end on
``stop``, stdin EOF or a signal.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import IO, Any

__all__ = [
    "Emit",
    "Message",
    "RoleProcesses",
    "emit_json",
    "end_process",
    "free_port",
    "serve_role",
    "wait_ready",
]

Emit = Callable[[dict[str, Any]], None]
"""A role's report sink: one JSON-able message."""
Message = tuple[str, dict[str, Any] | None]
"""A role's name and one of its reports; None when the role ended."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (for a rendezvous or a master of a run's own)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


def end_process(
    process: subprocess.Popen[Any], *, sig: int = signal.SIGTERM, timeout_s: float = 5.0
) -> int:
    """End a process we started: ``sig``, then SIGKILL after ``timeout_s``; its exit code."""
    if process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=timeout_s)
    return process.returncode


class RoleProcesses:
    """The role processes, with their stdout read line by line into one queue."""

    def __init__(self) -> None:
        self.messages: queue.Queue[Message] = queue.Queue()
        self.children: dict[str, subprocess.Popen[str]] = {}
        self._logs: dict[str, IO[str]] = {}
        self._readers: list[threading.Thread] = []

    def spawn(
        self, role: str, argv: Sequence[str], *, env: Mapping[str, str] | None = None
    ) -> None:
        """Start ``argv`` as ``role``, its stdout read into ``messages``, its stderr logged."""
        log = tempfile.TemporaryFile("w+")  # noqa: SIM115 - closed in close()
        self._logs[role] = log
        child = subprocess.Popen(
            list(argv),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=None if env is None else dict(env),
        )
        self.children[role] = child
        reader = threading.Thread(target=self._read, args=(role, child), daemon=True)
        reader.start()
        self._readers.append(reader)

    def _read(self, role: str, child: subprocess.Popen[str]) -> None:
        assert child.stdout is not None
        for line in child.stdout:
            with contextlib.suppress(ValueError):
                self.messages.put((role, json.loads(line)))
        self.messages.put((role, None))  # EOF: the process ended

    def send(self, line: str) -> None:
        """One line to every running role's stdin."""
        for child in self.children.values():
            if child.poll() is None and child.stdin is not None:
                with contextlib.suppress(BrokenPipeError, OSError):
                    child.stdin.write(line + "\n")
                    child.stdin.flush()

    def start(self, t0: float) -> None:
        """Tell every role the wall-clock time of step 1."""
        self.send(f"start {t0!r}")

    def log_tail(self, role: str) -> str:
        """The end of what ``role`` wrote on stderr."""
        log = self._logs[role]
        log.seek(0)
        return log.read()[-2000:]

    def close(self) -> None:
        """Ask, then terminate, then kill: every process started here, by PID."""
        self.send("stop")
        deadline = time.monotonic() + 5.0
        for child in self.children.values():
            try:
                child.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.terminate()
        for child in self.children.values():
            try:
                child.wait(timeout=3.0)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait(timeout=3.0)
            if child.stdin is not None:
                with contextlib.suppress(OSError):
                    child.stdin.close()
        for reader in self._readers:
            reader.join(timeout=2.0)  # EOF follows the exit
        for child in self.children.values():
            if child.stdout is not None:
                child.stdout.close()
        for log in self._logs.values():
            log.close()


def wait_ready(messages: queue.Queue[Message], roles: set[str], *, timeout_s: float) -> str | None:
    """Wait until every role reported ``ready``; the role that ended first, if one did.

    Raises ``queue.Empty`` when the time runs out.
    """
    ready: set[str] = set()
    deadline = time.monotonic() + timeout_s
    while ready != roles:
        role, message = messages.get(timeout=max(0.1, deadline - time.monotonic()))
        if message is None:
            return role
        if message.get("type") == "ready":
            ready.add(role)
    return None


def emit_json(message: dict[str, Any]) -> None:
    """A role's report: one JSON line on stdout."""
    sys.stdout.write(json.dumps(message) + "\n")
    sys.stdout.flush()


def serve_role(role: str, stop: threading.Event, run: Callable[[float], None]) -> None:
    """Announce ``ready``, wait for ``start <t0>`` on stdin, then ``run(t0)``.

    ``stop`` is set by ``stop`` or EOF on stdin (and by the caller's signal handlers), so a role
    whose parent went away ends too.
    """
    emit_json({"type": "ready", "role": role})
    start_at: list[float] = []
    started = threading.Event()

    def control() -> None:
        for line in sys.stdin:
            if line.startswith("stop"):
                break
            if line.startswith("start "):
                start_at.append(float(line.split()[1]))
                started.set()
        stop.set()  # stdin closed or told to stop

    threading.Thread(target=control, name="control", daemon=True).start()
    while not started.is_set() and not stop.is_set():
        started.wait(0.1)
    if not stop.is_set():
        run(start_at[0])
