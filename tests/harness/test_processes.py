import logging
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from dbml.harness.processes import (
    Message,
    RoleProcesses,
    read_commands,
    stop_on_signals,
    wait_ready,
)
from dbml.transports.worker import death_count
from tests.conftest import wait_for

ECHO = """
import queue
from dbml.harness.processes import emit_json, read_commands, stop_on_signals
with stop_on_signals() as stop:
    commands = read_commands(stop)
    emit_json({"type": "ready"})
    while not stop.is_set():
        try:
            emit_json({"type": "echo", "line": commands.get(timeout=0.05)})
        except queue.Empty:
            pass
emit_json({"type": "stopped"})
"""
"""A worker that takes commands: echoes each line, ends on ``stop`` or EOF."""
DEAF = """
from dbml.harness.processes import emit_json, stop_on_signals
with stop_on_signals() as stop:
    emit_json({"type": "ready"})
    stop.wait(60)
emit_json({"type": "stopped"})
"""
"""A process that reads no stdin (as ``dbml optimizer``): only a signal ends it early."""
GARBLED = """
import sys
sys.stderr.write("garbled: about to fail\\n")
sys.stderr.flush()
sys.stdout.buffer.write(b"\\xff\\xfe not UTF-8\\n")
sys.stdout.flush()
sys.stdin.readline()  # until told to stop
sys.exit(3)
"""
"""A process whose output cannot be read (not UTF-8), exiting 3 when told to stop."""
TIMEOUT_S = 30.0


def take(messages: queue.Queue[Message], role: str, kind: str) -> Any:
    """The next ``kind`` message of ``role`` (others of any role are dropped)."""
    deadline = time.monotonic() + TIMEOUT_S
    while True:
        got, message = messages.get(timeout=max(0.1, deadline - time.monotonic()))
        if got == role and message is not None and message["type"] == kind:
            return message


def test_stop_on_signals_sets_the_event_and_restores_the_handlers() -> None:
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with stop_on_signals() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(5.0)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_commands_reach_one_role_or_every_role_and_stop_ends_them() -> None:
    roles = RoleProcesses()
    try:
        for role in ("a", "b"):
            roles.spawn(role, [sys.executable, "-c", ECHO])
        assert wait_ready(roles.messages, {"a", "b"}, timeout_s=TIMEOUT_S) is None
        roles.send("only a", to="a")
        roles.send("both")
        echoes: dict[str, list[str]] = {"a": [], "b": []}
        while echoes["a"][-1:] != ["both"] or echoes["b"][-1:] != ["both"]:
            role, message = roles.messages.get(timeout=TIMEOUT_S)
            if message is not None and message["type"] == "echo":
                echoes[role].append(message["line"])
        assert echoes == {"a": ["only a", "both"], "b": ["both"]}
    finally:
        roles.close()
    assert [child.returncode for child in roles.children.values()] == [0, 0]


def test_a_process_that_reads_no_stdin_gets_its_stop_signal_without_the_grace_time() -> None:
    roles = RoleProcesses()
    try:
        roles.spawn("deaf", [sys.executable, "-c", DEAF], stop_signal=signal.SIGTERM)
        assert wait_ready(roles.messages, {"deaf"}, timeout_s=TIMEOUT_S) is None
        start = time.monotonic()
    finally:
        roles.close()
    assert time.monotonic() - start < 4.0  # the grace time of a role that reads stdin is 5 s
    assert roles.children["deaf"].returncode == 0  # its handler ended it, not SIGTERM's default
    assert take(roles.messages, "deaf", "stopped") == {"type": "stopped"}


def test_a_reader_that_dies_ends_its_role_and_is_counted(caplog: pytest.LogCaptureFixture) -> None:
    """The runner sees the role end, and its own ``Lifetime`` sees a thread of its died."""
    roles = RoleProcesses()
    deaths = death_count()
    try:
        with caplog.at_level(logging.CRITICAL, logger="dbml"):
            roles.spawn("garbled", [sys.executable, "-c", GARBLED])
            assert roles.messages.get(timeout=TIMEOUT_S) == ("garbled", None)
            wait_for(lambda: death_count() == deaths + 1, what="the reader's death counted")
        assert roles.exit_code("garbled") is None  # it still runs
    finally:
        codes = roles.close()
    assert codes == {"garbled": 3}
    assert roles.exit_code("garbled") == 3
    assert "garbled: about to fail" in roles.log_tail("garbled")  # kept after close
    assert "read-garbled: the thread died" in caplog.text
    assert "UnicodeDecodeError" in caplog.text


class _FailingStdin:
    """stdin that fails at once."""

    def __iter__(self) -> Iterator[str]:
        raise OSError("stdin is gone")


def test_a_dead_command_reader_sets_stop_and_is_counted(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(sys, "stdin", _FailingStdin())
    stop = threading.Event()
    deaths = death_count()
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        read_commands(stop)
        assert stop.wait(TIMEOUT_S)
        wait_for(lambda: death_count() == deaths + 1, what="the reader's death counted")
    assert "commands: the thread died" in caplog.text
    assert "OSError: stdin is gone" in caplog.text
