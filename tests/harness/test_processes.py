import os
import queue
import signal
import sys
import time
from typing import Any

from dbml.harness.processes import Message, RoleProcesses, stop_on_signals, wait_ready

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
