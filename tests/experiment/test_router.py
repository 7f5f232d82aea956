"""A run's router: ended by ``stop`` on stdin, and exit code 1 when its reader dies."""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator

import pytest

from dbml.experiment import entry, router
from dbml.transports.worker import death_count


class _Session:
    """The router's zenoh session, closed once."""

    def __init__(self) -> None:
        self.closed = 0

    def close(self) -> None:
        self.closed += 1


class _Stdin:
    """stdin giving ``lines``, then failing with ``error`` if given (else EOF)."""

    def __init__(self, *lines: str, error: Exception | None = None) -> None:
        self.lines = lines
        self.error = error

    def __iter__(self) -> Iterator[str]:
        yield from self.lines
        if self.error is not None:
            raise self.error


@pytest.fixture
def session(monkeypatch: pytest.MonkeyPatch) -> _Session:
    """No real router: what the entry does around it is under test."""
    opened = _Session()
    monkeypatch.setattr(router, "open_meshed_router", lambda **_: opened)
    monkeypatch.setattr(router, "POLL_S", 0.01)
    return opened


def test_stop_on_stdin_ends_the_router_with_exit_code_0(
    monkeypatch: pytest.MonkeyPatch, session: _Session
) -> None:
    monkeypatch.setattr(sys, "stdin", _Stdin("hello\n", "stop\n"))
    assert entry.main(["router", "--listen", "tcp/127.0.0.1:0"]) == 0
    assert session.closed == 1


def test_a_dead_stdin_thread_ends_the_router_with_exit_code_1(
    monkeypatch: pytest.MonkeyPatch, session: _Session, caplog: pytest.LogCaptureFixture
) -> None:
    """A router that can no longer be told to stop must not run on unseen."""
    monkeypatch.setattr(sys, "stdin", _Stdin("hello\n", error=OSError("stdin is gone")))
    deaths = death_count()
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        assert entry.main(["router", "--listen", "tcp/127.0.0.1:0"]) == 1
    assert death_count() == deaths + 1
    assert session.closed == 1
    assert "stdin: the thread died" in caplog.text
    assert "OSError: stdin is gone" in caplog.text
