"""Scenario roles as OS processes, driven over stdin and read over stdout as JSON lines.

Both ``dbml demo teleop`` (on loopback) and ``dbml testbed teleop`` (inside network namespaces)
start one process per role, wait for ``{"type": "ready"}``, send ``start <t0>``, and read the
roles' reports. This is that plumbing, once: every line lands in one queue, ``None`` marks a
process's end, and ``close()`` ends every process it started, by PID (ask, terminate, kill).

The role side is :func:`serve_role`: announce readiness, wait for the start time, run, and end on
``stop``, stdin EOF or a signal (:func:`stop_on_signals`). A process that takes commands of its
own (a benchmark's workers) reads them with :func:`read_commands`.

A child that another interpreter than ``sys.executable`` runs (Debian's ``rosmaster``, the other
environment's Python) gets :func:`foreign_interpreter_env`: none of the ROS 2 wheels' bootstrap.

Each thread here is a ``BackgroundThread``: should one die, it is said (critical) and counted,
so the process's ``Lifetime`` (or its role's run) ends non-zero.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from dbml.core.errors import DbmlError
from dbml.transports.worker import BackgroundThread

__all__ = [
    "Emit",
    "Message",
    "RoleProcesses",
    "emit_json",
    "end_process",
    "foreign_interpreter_env",
    "free_port",
    "read_commands",
    "serve_role",
    "stop_on_signals",
    "wait_ready",
]

log = logging.getLogger("dbml.harness")

Emit = Callable[[dict[str, Any]], None]
"""A role's report sink: one JSON-able message."""
Message = tuple[str, dict[str, Any] | None]
"""A role's name and one of its reports; None when the role ended."""
_EMIT_LOCK = threading.Lock()
"""One report is one line, also when several threads of a role report at once."""
_TAIL_CHARS = 2000
"""How much of a role's stderr ``log_tail`` keeps."""
_ROS_WHEELS_GUARD = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
"""Set by the ROS 2 wheels' ``.pth`` bootstrap once it has re-executed with its library path."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (for a rendezvous or a master of a run's own)."""
    with socket.socket() as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


def foreign_interpreter_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """``base`` (default ``os.environ``) for a child that another interpreter than ours runs.

    The ROS 2 wheels' ``.pth`` bootstrap re-executes every interpreter of their environment with
    ``LD_LIBRARY_PATH`` extended and a guard variable set, and children inherit both. Another
    interpreter (Debian's ``/usr/bin/python3`` running ``rosmaster``, the ROS 1 venv's) would load
    ROS 2's libraries, and its own environment's bootstrap, seeing the guard, would not run. So
    the guard goes, and so do the directories the bootstrap adds (an environment's ``lib``, the
    wheels' ``ros_*.libs``); the user's own stay (the variable goes if nothing is left), and so
    does every other variable.
    """
    env = dict(os.environ if base is None else base)
    env.pop(_ROS_WHEELS_GUARD, None)
    kept = [
        entry
        for entry in env.pop("LD_LIBRARY_PATH", "").split(os.pathsep)
        if entry and not _wheels_library_dir(Path(entry))
    ]
    if kept:
        env["LD_LIBRARY_PATH"] = os.pathsep.join(kept)
    return env


def _wheels_library_dir(path: Path) -> bool:
    """Whether the wheels' bootstrap adds ``path``: its ``sys.prefix/lib``, or a ``ros_*.libs``."""
    if path.name.startswith("ros_") and path.name.endswith(".libs"):
        return True
    if path.name != "lib":
        return False
    prefix = path.parent  # ours, or another virtual environment's (a child of one of them)
    return prefix.resolve() == Path(sys.prefix).resolve() or (prefix / "pyvenv.cfg").is_file()


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


@contextlib.contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM, so loops end cleanly and transports get closed."""
    stop = threading.Event()
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda *_: stop.set())
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class RoleProcesses:
    """The role processes, with their stdout read line by line into one queue."""

    def __init__(self) -> None:
        self.messages: queue.Queue[Message] = queue.Queue()
        self.children: dict[str, subprocess.Popen[str]] = {}
        self._logs: dict[str, IO[str]] = {}
        self._tails: dict[str, str] = {}
        self._readers: list[BackgroundThread] = []
        self._stop_signals: dict[str, int] = {}

    def spawn(
        self,
        role: str,
        argv: Sequence[str],
        *,
        env: Mapping[str, str] | None = None,
        stop_signal: int | None = None,
    ) -> None:
        """Start ``argv`` as ``role``, its stdout read into ``messages``, its stderr logged.

        ``stop_signal``: a process that reads no ``stop`` line (``dbml optimizer``) gets this
        signal when the roles are closed, instead of the grace time of one that does.
        """
        if stop_signal is not None:
            self._stop_signals[role] = stop_signal
        stderr = tempfile.TemporaryFile("w+")  # noqa: SIM115 - closed in close()
        self._logs[role] = stderr
        child = subprocess.Popen(
            list(argv),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            env=None if env is None else dict(env),
        )
        self.children[role] = child
        reader = BackgroundThread(lambda: self._read(role, child), name=f"read-{role}", log=log)
        self._readers.append(reader.start())

    def _read(self, role: str, child: subprocess.Popen[str]) -> None:
        assert child.stdout is not None
        try:
            for line in child.stdout:
                with contextlib.suppress(ValueError):
                    message = json.loads(line)
                    if isinstance(message, dict):  # a report; anything else is not one
                        self.messages.put((role, message))
        finally:  # EOF, or its output cannot be read: either way the role is gone for us
            self.messages.put((role, None))

    def send(self, line: str, *, to: str | None = None) -> None:
        """One line to every running role's stdin, or to role ``to``'s only."""
        for role, child in self.children.items():
            if to not in (None, role):
                continue
            if child.poll() is None and child.stdin is not None:
                with contextlib.suppress(BrokenPipeError, OSError):
                    child.stdin.write(line + "\n")
                    child.stdin.flush()

    def start(self, t0: float) -> None:
        """Tell every role the wall-clock time of step 1."""
        self.send(f"start {t0!r}")

    def log_tail(self, role: str) -> str:
        """The end of what ``role`` wrote on stderr (also after ``close``)."""
        if role in self._tails:
            return self._tails[role]
        stderr = self._logs[role]
        stderr.seek(0)
        return stderr.read()[-_TAIL_CHARS:]

    def exit_code(self, role: str, *, timeout_s: float = 0.0) -> int | None:
        """``role``'s exit code, waiting up to ``timeout_s`` for its end; None while it runs."""
        try:
            return self.children[role].wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def close(self, *, save_logs: Path | None = None) -> dict[str, int]:
        """Ask, then terminate, then kill: every process started here, by PID.

        Each process's exit code, by role: negative for one ended by a signal after the grace
        time, positive for one that failed on its own (a dead thread's role exits 1).
        ``save_logs``: a directory where each role's whole stderr is kept as ``<role>.log``.
        """
        self.send("stop")
        for role, sig in self._stop_signals.items():
            child = self.children[role]
            if child.poll() is None:
                child.send_signal(sig)
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
            reader.join(2.0)  # EOF follows the exit
        for child in self.children.values():
            if child.stdout is not None:
                child.stdout.close()
        for role, stderr in self._logs.items():
            if save_logs is not None and not stderr.closed:
                stderr.seek(0)
                (save_logs / f"{role}.log").write_text(stderr.read())
            if role not in self._tails:
                self._tails[role] = self.log_tail(role)
            stderr.close()
        return {role: child.returncode for role, child in self.children.items()}


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
    line = json.dumps(message) + "\n"
    with _EMIT_LOCK:
        sys.stdout.write(line)
        sys.stdout.flush()


def read_commands(stop: threading.Event) -> queue.Queue[str]:
    """Lines of stdin, read by a thread into the queue returned; ``stop`` or EOF sets ``stop``.

    For a process that takes commands besides ``stop``: EOF means its parent went away, so it
    ends then too, as a role does. Should the thread die (stdin failing), ``stop`` is set as
    well, and the death is said and counted (for the process's ``Lifetime``, which exits 1).
    """
    commands: queue.Queue[str] = queue.Queue()

    def read() -> None:
        try:
            for line in sys.stdin:
                if line.startswith("stop"):
                    break
                commands.put(line.strip())
        finally:
            stop.set()

    BackgroundThread(read, name="commands", log=log).start()
    return commands


_SHOWN_CHARS = 80
"""How much of a malformed control line an error quotes."""


def _start_time(line: str) -> float:
    """``t0`` of a ``start <t0>`` line; ``DbmlError`` naming the line if it is not one."""
    try:
        t0 = float(line.partition(" ")[2])
    except ValueError:
        t0 = math.nan
    if not math.isfinite(t0):
        raise DbmlError(f"control line {line.strip()[:_SHOWN_CHARS]!r} is not 'start <t0>'")
    return t0


def serve_role(role: str, stop: threading.Event, run: Callable[[float], None]) -> None:
    """Announce ``ready``, wait for ``start <t0>`` on stdin, then ``run(t0)``.

    ``stop`` is set by ``stop`` or EOF on stdin (and by the caller's signal handlers), so a role
    whose parent went away ends too. The thread reading stdin sets ``stop`` however it ends: a
    malformed line, or stdin failing, ends the role too, and then ``DbmlError`` says why, so the
    process exits non-zero instead of waiting for a start that never comes. Whatever ends that
    thread is handed to this one (never left to race ``stop`` as an uncounted death).
    """
    emit_json({"type": "ready", "role": role})
    start_at: list[float] = []
    started = threading.Event()
    failed: list[BaseException] = []

    def control() -> None:
        try:
            for line in sys.stdin:
                if line.startswith("stop"):
                    break
                if line.startswith("start ") and not started.is_set():  # the first one counts
                    start_at.append(_start_time(line))
                    started.set()
        except BaseException as err:  # said by serve_role, on the main thread: it exits non-zero
            failed.append(err)
        finally:
            stop.set()  # stdin closed, told to stop, or the thread failed

    BackgroundThread(control, name="control", log=log).start()
    while not started.is_set() and not stop.is_set():
        started.wait(0.1)
    if not stop.is_set():
        run(start_at[0])
    if failed:
        raise DbmlError(f"role {role}: its control thread failed: {failed[0]}") from failed[0]
