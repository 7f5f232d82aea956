"""The supervisor: start children, read their lines, talk to them, end them by PID."""

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbml.core.errors import DbmlError
from dbml.harness.child import Control, stop_on_signals
from dbml.harness.mailbox import Line
from dbml.harness.supervisor import ChildExitedError, ChildIO, ProcessChild, Supervisor
from dbml.transports.worker import death_count
from tests.conftest import wait_for

ECHO = """
import queue, threading
from dbml.harness.child import Control, emit_json, stop_on_signals
with stop_on_signals() as stop:
    control = Control(stop).start()
    emit_json({"type": "ready"})
    while not stop.is_set():
        try:
            emit_json({"type": "echo", "line": control.commands.get(timeout=0.05)})
        except queue.Empty:
            pass
emit_json({"type": "stopped"})
"""
"""A worker that takes commands: echoes each line, ends on ``stop`` or EOF."""
DEAF = """
from dbml.harness.child import emit_json, stop_on_signals
with stop_on_signals() as stop:
    emit_json({"type": "ready"})
    stop.wait(60)
emit_json({"type": "stopped"})
"""
"""A process that reads no stdin (as ``dbml optimizer``): only a signal ends it early."""
STUBBORN = """
import signal, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("ready", flush=True)
while True:
    time.sleep(1)
"""
"""A process that ignores ``stop`` and SIGTERM: only SIGKILL ends it."""
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


def report(children: Supervisor, child: str, kind: str) -> Line:
    """The next ``kind`` report of ``child`` (its other lines stay)."""
    line = children.take(lambda ln: ln.child == child and ln.kind == kind, timeout_s=TIMEOUT_S)
    assert line is not None, f"no {kind} from {child}"
    return line


def test_stop_on_signals_sets_the_event_and_restores_the_handlers() -> None:
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with stop_on_signals() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(5.0)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


def test_commands_reach_one_child_or_every_child_and_stop_ends_them() -> None:
    with Supervisor() as children:
        for name in ("a", "b"):
            children.start(name, [sys.executable, "-c", ECHO])
        assert children.wait_ready({"a", "b"}, timeout_s=TIMEOUT_S) is None
        children.send("only a", to="a")
        children.send("both")
        echoes: dict[str, list[str]] = {"a": [], "b": []}
        while echoes["a"][-1:] != ["both"] or echoes["b"][-1:] != ["both"]:
            line = children.take(lambda ln: ln.kind == "echo", timeout_s=TIMEOUT_S)
            assert line is not None
            assert line.report is not None
            echoes[line.child].append(line.report["line"])
        assert echoes == {"a": ["only a", "both"], "b": ["both"]}
        codes = children.close()
    assert codes == {"a": 0, "b": 0}
    assert report(children, "a", "stopped").report == {"type": "stopped"}


def test_a_process_that_reads_no_stdin_gets_its_stop_signal_without_the_grace_time() -> None:
    children = Supervisor()
    try:
        children.start("deaf", [sys.executable, "-c", DEAF], stop_signal=signal.SIGTERM)
        assert children.wait_ready({"deaf"}, timeout_s=TIMEOUT_S) is None
        start = time.monotonic()
    finally:
        codes = children.close()
    assert time.monotonic() - start < 4.0  # the grace time of a child that reads stdin is 5 s
    assert codes == {"deaf": 0}  # its handler ended it, not SIGTERM's default
    assert report(children, "deaf", "stopped").report == {"type": "stopped"}


def test_a_child_that_ignores_stop_and_sigterm_is_killed_by_its_pid() -> None:
    with Supervisor() as children:
        child = children.start("stubborn", [sys.executable, "-c", STUBBORN])
        line = children.next(child="stubborn", timeout_s=TIMEOUT_S)
        assert line is not None
        assert (line.text, line.report) == ("ready", None)
        code = children.end("stubborn", ask_s=0.2)
    assert code == -signal.SIGKILL
    assert child.poll() == -signal.SIGKILL


def test_a_reader_that_dies_ends_its_child_and_is_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The runner sees the child end, and its own ``Lifetime`` sees a thread of its died."""
    children = Supervisor()
    deaths = death_count()
    try:
        with caplog.at_level(logging.CRITICAL, logger="dbml"):
            child = children.start("garbled", [sys.executable, "-c", GARBLED])
            assert children.next(timeout_s=TIMEOUT_S) == Line("garbled", "", ended=True)
            wait_for(lambda: death_count() == deaths + 1, what="the reader's death counted")
        assert child.poll() is None  # it still runs
    finally:
        codes = children.close()
    assert codes == {"garbled": 3}
    assert child.poll() == 3
    assert "garbled: about to fail" in child.log_tail()  # kept after close
    assert "read-garbled: the thread died" in caplog.text
    assert "UnicodeDecodeError" in caplog.text


def test_everything_is_ended_when_the_caller_fails(tmp_path: Path) -> None:
    started: list[ProcessChild] = []

    def fail_with_a_child() -> None:
        with Supervisor(logs=tmp_path) as children:
            started.append(children.start("deaf", [sys.executable, "-c", DEAF], stdin=False))
            assert children.wait_ready(["deaf"], timeout_s=TIMEOUT_S) is None
            raise RuntimeError("the caller failed")

    with pytest.raises(RuntimeError, match="the caller failed"):
        fail_with_a_child()
    (child,) = started
    assert child.poll() == 0  # asked by SIGTERM (no stdin), its handler ended it
    assert (tmp_path / "deaf.log").is_file()  # kept where asked


def test_stderr_goes_to_a_log_file_read_while_it_runs_and_kept_where_asked(
    tmp_path: Path,
) -> None:
    code = "import sys; sys.stderr.write('said on stderr\\n'); sys.stderr.flush(); input()"
    with Supervisor(logs=tmp_path) as children:
        child = children.start("talker", [sys.executable, "-c", code])
        children.wait_until(lambda: "said on stderr" in child.log(), timeout_s=TIMEOUT_S)
        assert child.log_path == tmp_path / "talker.log"
    assert (tmp_path / "talker.log").read_text() == "said on stderr\n"
    assert child.log() == "said on stderr\n"


def test_waiting_fails_as_soon_as_a_watched_child_ends() -> None:
    code = "import sys; sys.stderr.write('gave up\\n'); sys.exit(4)"
    with Supervisor() as children:
        children.start("quitter", [sys.executable, "-c", code])
        with pytest.raises(ChildExitedError, match=r"^quitter exited \(code 4\): gave up$"):
            children.wait_until(lambda: False, timeout_s=TIMEOUT_S, watch=["quitter"])
        with pytest.raises(TimeoutError, match="waiting for nothing"):
            children.wait_until(lambda: False, timeout_s=0.1, what="nothing")


def test_a_name_is_started_once_and_argv_is_a_list() -> None:
    with Supervisor() as children:
        children.start("one", [sys.executable, "-c", "pass"])
        with pytest.raises(DbmlError, match="child 'one' was started already"):
            children.start("one", [sys.executable, "-c", "pass"])
        with pytest.raises(DbmlError, match="must be a list of arguments"):
            children.start("two", "python -c pass")
        with pytest.raises(DbmlError, match="child name '/r1/camera' must be a file name"):
            children.start("/r1/camera", [sys.executable, "-c", "pass"])


def test_a_child_in_a_namespace_runs_through_ip_netns_exec(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    started: list[list[str]] = []

    class StartedError(Exception):
        pass

    def popen(argv: list[str], **_: object) -> None:
        started.append(argv)
        raise StartedError

    monkeypatch.setattr("subprocess.Popen", popen)
    with Supervisor() as children, pytest.raises(StartedError):
        children.start("inside", ["python3", "-c", "pass"], netns="dbml-abc123-r1")
    assert started == [["ip", "netns", "exec", "dbml-abc123-r1", "python3", "-c", "pass"]]


def test_unread_lines_are_bounded_per_child_and_others_kept(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with (
        caplog.at_level(logging.WARNING, logger="dbml.harness"),
        Supervisor(lines_per_child=10) as children,
    ):
        chatty = children.start("chatty", [sys.executable, "-c", "for i in range(50): print(i)"])
        children.start("quiet", [sys.executable, "-c", "print('hello'); input()"])
        # Every line read, its end too (the warning comes at the first dropped line, before).
        wait_for(
            lambda: chatty.reader is not None and not chatty.reader.running, timeout_s=TIMEOUT_S
        )
        assert "chatty: more than 10 unread lines" in caplog.text
        line = children.next(child="quiet", timeout_s=TIMEOUT_S)
        assert line is not None
        assert line.text == "hello"
        kept = children.take_all(lambda ln: ln.child == "chatty")
    assert [line.text for line in kept[:-1]] == [str(i) for i in range(41, 50)]
    assert kept[-1].ended  # the end is a line too: the newest 10 are 41-49 and it


def test_a_thread_child_reads_its_lines_reports_and_ends_as_a_process_does() -> None:
    def body(io: ChildIO) -> int:
        stop = threading.Event()
        control = Control(stop, lines=io.lines).start()
        io.emit({"type": "ready"})
        stop.wait(TIMEOUT_S)
        io.emit({"type": "got", "line": control.commands.get_nowait()})
        return 5

    with Supervisor() as children:
        child = children.start_thread("worker", body)
        assert children.wait_ready(["worker"], timeout_s=TIMEOUT_S) is None
        children.send("hello", to="worker")
        codes = children.close()
    assert codes == {"worker": 5}
    assert child.poll() == 5
    assert report(children, "worker", "got").report == {"type": "got", "line": "hello"}


def test_a_thread_child_that_raises_exits_1_with_its_traceback() -> None:
    def body(io: ChildIO) -> int:
        raise RuntimeError("no transport")

    with Supervisor() as children:
        child = children.start_thread("broken", body)
        assert children.wait_ready(["broken"], timeout_s=TIMEOUT_S) == "broken"
        assert child.wait(TIMEOUT_S) == 1
    assert "RuntimeError: no transport" in child.log_tail()


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
        Control(stop, name="commands").start()
        assert stop.wait(TIMEOUT_S)
        wait_for(lambda: death_count() == deaths + 1, what="the reader's death counted")
    assert "commands: the thread died" in caplog.text
    assert "OSError: stdin is gone" in caplog.text
