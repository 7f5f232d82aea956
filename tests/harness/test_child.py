"""A role's control thread: whatever ends it ends the role, non-zero when it failed."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Iterator

import pytest

from dbml.core.errors import DbmlError
from dbml.harness.child import serve_role

TIMEOUT_S = 30.0
"""How long a test waits for a role that should end at once."""

ROLE = """
import threading
from dbml.harness.child import serve_role
serve_role("r1", threading.Event(), lambda t0: print("ran", t0))
"""
"""A role process that runs nothing but the control protocol."""


class Stdin:
    """Gives ``lines``, then ends (EOF) once ``eof`` is set; or fails with ``error`` there."""

    def __init__(self, *lines: str, error: BaseException | None = None) -> None:
        self.lines = lines
        self.error = error
        self.eof = threading.Event()

    def __iter__(self) -> Iterator[str]:
        yield from self.lines
        assert self.eof.wait(TIMEOUT_S), "the test never ended stdin"
        if self.error is not None:
            raise self.error


def serve(monkeypatch: pytest.MonkeyPatch, stdin: Stdin, stop: threading.Event) -> list[float]:
    """Run ``serve_role`` on ``stdin``; the start times its ``run`` was given.

    The run ends stdin, then waits for ``stop``, as a role runs until told to end.
    """
    monkeypatch.setattr(sys, "stdin", stdin)
    ran: list[float] = []

    def run(t0: float) -> None:
        ran.append(t0)
        stdin.eof.set()
        assert stop.wait(TIMEOUT_S), "nothing set stop"

    serve_role("r1", stop, run)
    return ran


def test_a_start_line_runs_the_role_and_eof_ends_it(monkeypatch: pytest.MonkeyPatch) -> None:
    stop = threading.Event()
    assert serve(monkeypatch, Stdin("start 12.5\n", "start 13\n"), stop) == [12.5]
    assert stop.is_set()


@pytest.mark.parametrize("line", ["start soon", "start ", "start 1 2", "start nan", "start inf"])
def test_a_malformed_start_line_ends_the_role_with_an_error(
    monkeypatch: pytest.MonkeyPatch, line: str
) -> None:
    stop = threading.Event()
    shown = repr(line.strip())
    with pytest.raises(DbmlError, match=rf"role r1: .*control line {shown} is not 'start <t0>'"):
        serve(monkeypatch, Stdin(f"{line}\n", "start 1.0\n"), stop)
    assert stop.is_set()


def test_a_control_thread_failing_during_the_run_stops_it_and_raises(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    stop = threading.Event()
    stdin = Stdin("start 1.0\n", error=OSError("stdin is gone"))
    with pytest.raises(DbmlError, match="role r1: its control thread failed: stdin is gone"):
        serve(monkeypatch, stdin, stop)
    assert stop.is_set()


def test_a_control_thread_ended_by_system_exit_still_fails_the_role(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Not an ``Exception``: still handed to the role's thread, never lost."""
    stop = threading.Event()
    stdin = Stdin("start 1.0\n", error=SystemExit("stdin is gone"))
    with pytest.raises(DbmlError, match="role r1: its control thread failed: stdin is gone"):
        serve(monkeypatch, stdin, stop)
    assert stop.is_set()


def test_a_role_process_given_a_malformed_line_exits_non_zero() -> None:
    """The control thread must not die leaving the role waiting for a start forever."""
    result = subprocess.run(
        [sys.executable, "-c", ROLE],
        input="start soon\n",
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert result.returncode != 0
    assert "control line 'start soon' is not 'start <t0>'" in result.stderr
    assert "ran" not in result.stdout
