"""One supervisor for every child a run starts: start it, read it, talk to it, end it by PID.

The demo, the testbed, the benchmarks and the tests start processes (and, over the memory
transport, roles as threads) through a :class:`Supervisor`:

- ``start(name, argv, env=, cwd=, netns=)`` starts a process (inside a network namespace with
  ``netns``); ``start_thread(name, body)`` runs ``body`` as a child of this process, with the
  same interface (lines sent to it, reports from it, an exit code).
- Every line a child writes on stdout lands, as a :class:`Line` (with the JSON object it holds,
  if any), in one mailbox; a last line with ``ended`` set marks the end of its output. ``next``
  and ``take`` read it, ``wait_ready`` and ``wait_until`` wait on conditions with timeouts.
- A child's stderr goes to ``<logs>/<name>.log`` (``logs`` given: kept; else a temporary folder
  removed on ``close``, each log's tail kept in memory): never a full pipe.
- ``send`` writes a line to a child's stdin; ``end`` and ``close`` end children by their PID:
  ask (a ``stop`` line, or the child's ``stop_signal``), then SIGTERM, then SIGKILL.
- Used as a context manager, every child is ended on the way out, also on an exception.

The threads reading the children's output are ``BackgroundThread`` workers: should one die (a
child writing what is not UTF-8), the death is said and counted, and its child's output ends.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import shutil
import signal
import subprocess
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Protocol

from dbml.core.errors import DbmlError
from dbml.harness.child import Emit
from dbml.harness.mailbox import Line, Mailbox, read_line
from dbml.transports.worker import BackgroundThread

__all__ = [
    "ASK_S",
    "TERMINATE_S",
    "ChildExitedError",
    "ChildIO",
    "ProcessChild",
    "Supervisor",
    "ThreadChild",
]

log = logging.getLogger("dbml.harness")

ASK_S = 5.0
"""How long a child asked to end (``stop`` or its signal) may take before SIGTERM."""
TERMINATE_S = 3.0
"""How long a child may take after SIGTERM before SIGKILL (and again after SIGKILL)."""
TAIL_CHARS = 2000
"""How much of a child's stderr ``log_tail`` gives."""
LINES_PER_CHILD = 10_000
"""Unread lines kept per child; a child that writes more loses its oldest (said once)."""
_POLL_S = 0.05
"""How often ``wait_until`` looks at its condition."""
_JOIN_S = 2.0
"""How long closing waits for a reader once its process ended (EOF follows the exit)."""
_KEPT_CHARS = 1_000_000
"""How much of a child's stderr stays readable after ``close`` removed its log file."""


class ChildExitedError(DbmlError):
    """A child ended while it was being waited for."""

    def __init__(self, name: str, code: int | None, tail: str) -> None:
        lines = " | ".join(tail.strip().splitlines()[-3:])
        super().__init__(f"{name} exited (code {code}){': ' + lines if lines else ''}")
        self.name = name
        self.code = code
        self.tail = tail


class _LogFile:
    """A child's stderr: a file opened for appending (shared with the child, read by path)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.file: IO[bytes] = path.open("ab")
        self._kept: str | None = None

    def read(self) -> str:
        if self._kept is not None:
            return self._kept
        try:
            return self.path.read_text(errors="replace")
        except OSError:
            return ""

    def close(self, *, keep_text: bool) -> None:
        if keep_text:
            self._kept = self.read()[-_KEPT_CHARS:]
        self.file.close()


class ProcessChild:
    """One process of a supervisor: its PID, its stdin, its stderr log; ended by its PID."""

    def __init__(
        self,
        name: str,
        popen: subprocess.Popen[str],
        logfile: _LogFile,
        mailbox: Mailbox,
        *,
        stop_signal: int | None,
    ) -> None:
        self._name = name
        self._mailbox = mailbox
        self.popen = popen
        """The process (its ``pid``, ``returncode``), for what this class does not offer."""
        self._log = logfile
        self.stop_signal = stop_signal
        self._stdin_lock = threading.Lock()
        self.reader: BackgroundThread | None = None

    @property
    def name(self) -> str:
        """Its name in the supervisor."""
        return self._name

    @property
    def pid(self) -> int:
        """Its process id."""
        return self.popen.pid

    @property
    def log_path(self) -> Path:
        """Where its stderr goes (gone after ``close`` unless the supervisor keeps logs)."""
        return self._log.path

    def poll(self) -> int | None:
        """Its exit code, None while it runs."""
        return self.popen.poll()

    def wait(self, timeout_s: float) -> int | None:
        """Its exit code, waiting up to ``timeout_s``; None while it runs."""
        try:
            return self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def send(self, line: str) -> None:
        """One line to its stdin (nothing once it ended)."""
        stdin = self.popen.stdin
        if stdin is None or self.popen.poll() is not None:
            return
        with self._stdin_lock, contextlib.suppress(OSError, ValueError):
            stdin.write(line + "\n")
            stdin.flush()

    def close_stdin(self) -> None:
        """End its stdin (EOF: a role takes it as its parent gone)."""
        stdin = self.popen.stdin
        if stdin is not None:
            with self._stdin_lock, contextlib.suppress(OSError, ValueError):
                stdin.close()

    def next(self, *, timeout_s: float) -> Line | None:
        """Its oldest unread line, or None when ``timeout_s`` passed first."""
        return self._mailbox.take(lambda line: line.child == self._name, timeout_s)

    def kill(self) -> None:
        """SIGKILL, now (a crash, as a test makes one)."""
        self.send_signal(signal.SIGKILL)

    def send_signal(self, sig: int, *, group: bool = False) -> None:
        """``sig`` to the process (``group``: to its process group, as a terminal sends Ctrl-C)."""
        if self.popen.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            if group:
                os.killpg(self.popen.pid, sig)
            else:
                self.popen.send_signal(sig)

    def ask(self) -> None:
        """Ask it to end: ``stop`` on its stdin, then EOF, or its ``stop_signal``."""
        self.send("stop")
        self.close_stdin()
        if self.stop_signal is not None:
            self.send_signal(self.stop_signal)

    def force(self, *, timeout_s: float = TERMINATE_S) -> int:
        """SIGTERM, then SIGKILL after ``timeout_s``: its exit code."""
        if self.popen.poll() is None:
            self.popen.terminate()
            if self.wait(timeout_s) is None:
                self.popen.kill()
                self.popen.wait(timeout=timeout_s)
        return int(self.popen.returncode)

    def log(self) -> str:
        """Everything it wrote on stderr so far."""
        return self._log.read()

    def log_tail(self, chars: int = TAIL_CHARS) -> str:
        """The end of its stderr."""
        return self.log()[-chars:]


class ChildIO(Protocol):
    """What a thread child gets: its control lines and its report sink."""

    @property
    def lines(self) -> Iterable[str]:
        """The lines sent to it; ends (EOF) when it is asked to end."""
        ...

    @property
    def emit(self) -> Emit:
        """One report (a JSON object), into the supervisor's mailbox."""
        ...


class _Lines:
    """A thread child's stdin: the lines sent, until EOF."""

    def __init__(self) -> None:
        self._queue: queue.Queue[str | None] = queue.Queue()

    def put(self, line: str | None) -> None:
        self._queue.put(line)

    def __iter__(self) -> Iterator[str]:
        while (line := self._queue.get()) is not None:
            yield line + "\n"


@dataclass(frozen=True, slots=True)
class _ThreadIO:
    lines: _Lines
    emit: Emit


class ThreadChild:
    """A child run as a thread of this process: ``body(io)`` returns its exit code."""

    def __init__(self, name: str, body: Callable[[ChildIO], int | None], mailbox: Mailbox):
        self._name = name
        self._lines = _Lines()
        self._code: int | None = None
        self._error = ""
        self._ended = threading.Event()

        def emit(report: dict[str, Any]) -> None:
            mailbox.put(Line(name, json.dumps(report), report))

        def run() -> None:
            code = 1
            try:
                code = body(_ThreadIO(self._lines, emit)) or 0
            except Exception:
                self._error = traceback.format_exc()
            finally:
                self._code = code
                self._ended.set()
                mailbox.put(Line(name, "", ended=True))

        self._thread = BackgroundThread(run, name=f"child-{name}", log=log).start()

    @property
    def name(self) -> str:
        """Its name in the supervisor."""
        return self._name

    def poll(self) -> int | None:
        """Its exit code, None while it runs."""
        return self._code if self._ended.is_set() else None

    def wait(self, timeout_s: float) -> int | None:
        """Its exit code, waiting up to ``timeout_s``; None while it runs."""
        self._ended.wait(timeout_s)
        return self.poll()

    def send(self, line: str) -> None:
        """One line to its control lines (nothing once it ended)."""
        if not self._ended.is_set():
            self._lines.put(line)

    def ask(self) -> None:
        """``stop``, then EOF."""
        self._lines.put("stop")
        self._lines.put(None)

    def log(self) -> str:
        """The traceback it ended with (empty if it returned)."""
        return self._error

    def log_tail(self, chars: int = TAIL_CHARS) -> str:
        """The end of ``log()``."""
        return self._error[-chars:]


class Supervisor:
    """The children of one run, their output in one mailbox; a context manager."""

    def __init__(self, *, logs: Path | None = None, lines_per_child: int = LINES_PER_CHILD):
        self._mailbox = Mailbox(lines_per_child)
        self._children: dict[str, ProcessChild | ThreadChild] = {}
        self._keep_logs = logs is not None
        self._scratch: str | None = None
        if logs is None:
            self._scratch = tempfile.mkdtemp(prefix="dbml-children-")
            self._logs = Path(self._scratch)
        else:
            logs.mkdir(parents=True, exist_ok=True)
            self._logs = logs
        self._files: dict[str, _LogFile] = {}
        self._closed = False

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self.close()

    # -- starting -------------------------------------------------------------------------------

    def _claim(self, name: str) -> None:
        if not name or "/" in name or name in {".", ".."}:
            raise DbmlError(f"child name {name!r} must be a file name (its log's)")
        if self._closed:
            raise DbmlError(f"child {name!r}: the supervisor is closed")
        if name in self._children:
            raise DbmlError(f"child {name!r} was started already")

    def start(
        self,
        name: str,
        argv: Sequence[str],
        *,
        env: Mapping[str, str] | None = None,
        cwd: Path | str | None = None,
        netns: str | None = None,
        stop_signal: int | None = None,
        stdin: bool = True,
        read_stdout: bool = True,
        new_session: bool = False,
        pass_fds: Sequence[int] = (),
    ) -> ProcessChild:
        """Start ``argv`` as child ``name`` (inside network namespace ``netns``, if given).

        ``stop_signal``: how it is asked to end besides ``stop`` on stdin (a process that reads
        no stdin, as ``dbml optimizer``). ``stdin`` False: it reads from /dev/null (and can only
        be asked by a signal: SIGTERM unless ``stop_signal`` says another). ``read_stdout``
        False: its stdout goes to its log with its stderr. ``new_session``: its own process
        group (``send_signal(group=True)`` reaches it and its children, as a terminal's Ctrl-C).
        """
        self._claim(name)
        if isinstance(argv, str):
            raise DbmlError(f"argv={argv!r} must be a list of arguments, not a string")
        command = ["ip", "netns", "exec", netns, *argv] if netns is not None else list(argv)
        logfile = self._files[name] = _LogFile(self._logs / f"{name}.log")
        if not stdin and stop_signal is None:
            stop_signal = signal.SIGTERM
        popen = subprocess.Popen(
            command,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE if read_stdout else logfile.file,
            stderr=logfile.file,
            text=True,
            env=None if env is None else dict(env),
            cwd=cwd,
            start_new_session=new_session,
            pass_fds=tuple(pass_fds),
        )
        child = ProcessChild(name, popen, logfile, self._mailbox, stop_signal=stop_signal)
        self._children[name] = child
        if read_stdout:  # else it writes no line: only its exit code tells its end
            child.reader = BackgroundThread(
                lambda: self._read(child), name=f"read-{name}", log=log
            ).start()
        return child

    def _read(self, child: ProcessChild) -> None:
        stdout = child.popen.stdout
        assert stdout is not None
        try:
            for text in stdout:
                self._mailbox.put(read_line(child.name, text))
        finally:  # EOF, or its output cannot be read: either way it is gone for us
            self._mailbox.put(Line(child.name, "", ended=True))

    def start_thread(self, name: str, body: Callable[[ChildIO], int | None]) -> ThreadChild:
        """Run ``body`` as child ``name`` on a thread: lines, reports and exit code as a process.

        ``body`` returns its exit code (None: 0); an exception out of it is exit code 1, its
        traceback the child's log.
        """
        self._claim(name)
        child = ThreadChild(name, body, self._mailbox)
        self._children[name] = child
        return child

    # -- reading --------------------------------------------------------------------------------

    @property
    def children(self) -> Mapping[str, ProcessChild | ThreadChild]:
        """Every child started, in start order."""
        return self._children

    def __getitem__(self, name: str) -> ProcessChild | ThreadChild:
        return self._children[name]

    def process(self, name: str) -> ProcessChild:
        """Child ``name``, which must be a process."""
        child = self._children[name]
        if not isinstance(child, ProcessChild):
            raise DbmlError(f"child {name!r} is a thread, not a process")
        return child

    def pids(self) -> list[int]:
        """The PIDs of the processes started here."""
        return [c.pid for c in self._children.values() if isinstance(c, ProcessChild)]

    def take(self, where: Callable[[Line], bool], *, timeout_s: float) -> Line | None:
        """The oldest unread line that matches ``where`` (waiting up to ``timeout_s``), or None.

        Lines that do not match stay for a later call.
        """
        return self._mailbox.take(where, timeout_s)

    def take_all(self, where: Callable[[Line], bool]) -> list[Line]:
        """Every unread line that matches ``where`` now, oldest first (without waiting)."""
        taken: list[Line] = []
        while (line := self.take(where, timeout_s=0.0)) is not None:
            taken.append(line)
        return taken

    def next(self, *, child: str | None = None, timeout_s: float) -> Line | None:
        """The oldest unread line (of ``child``), or None when ``timeout_s`` passed first."""
        return self.take(lambda line: child in (None, line.child), timeout_s=timeout_s)

    def reports(self, child: str, *, timeout_s: float) -> Iterator[dict[str, Any]]:
        """``child``'s reports as they come, until its output ends or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            line = self.next(child=child, timeout_s=left)
            if line is None or line.ended:
                return
            if line.report is not None:
                yield line.report

    def drop(self, child: str) -> None:
        """Forget ``child``'s unread lines: what is read next it wrote from now on."""
        self._mailbox.clear(child)

    def wait_ready(self, names: Iterable[str], *, timeout_s: float) -> str | None:
        """Wait until each of ``names`` reported ``ready``; the first that ended instead.

        Their other lines meanwhile are dropped. ``TimeoutError`` when the time runs out.
        """
        waiting = set(names)
        deadline = time.monotonic() + timeout_s
        while waiting:
            line = self.take(
                lambda line: line.child in waiting, timeout_s=deadline - time.monotonic()
            )
            if line is None:
                raise TimeoutError(
                    f"not ready within {timeout_s:g} s: {', '.join(sorted(waiting))}"
                )
            if line.ended:
                return line.child
            if line.kind == "ready":
                waiting.discard(line.child)
        return None

    def wait_until(
        self,
        predicate: Callable[[], bool],
        *,
        timeout_s: float,
        watch: Iterable[str] = (),
        what: str = "",
    ) -> None:
        """Wait until ``predicate()`` holds.

        ``ChildExitedError`` when one of ``watch`` ends first, ``TimeoutError`` naming ``what`` when
        the time runs out.
        """
        watched = [self._children[name] for name in watch]
        deadline = time.monotonic() + timeout_s
        while not predicate():
            for child in watched:
                code = child.poll()
                if code is not None:
                    raise ChildExitedError(child.name, code, child.log_tail())
            if time.monotonic() > deadline:
                raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}")
            time.sleep(_POLL_S)

    # -- talking and ending -----------------------------------------------------------------------

    def send(self, line: str, *, to: str | None = None) -> None:
        """One line to every running child's stdin, or to child ``to``'s only."""
        for name, child in self._children.items():
            if to in (None, name):
                child.send(line)

    def end(self, name: str, *, ask_s: float = ASK_S) -> int:
        """End child ``name`` (ask, then SIGTERM, then SIGKILL, by its PID); its exit code.

        A thread still running after ``ask_s`` is left to end on its own (exit code -1).
        """
        child = self._children[name]
        child.ask()
        code = child.wait(ask_s)
        if code is None and isinstance(child, ProcessChild):
            code = child.force()
        return -1 if code is None else code

    def close(self) -> dict[str, int]:
        """End every child (all asked at once, then SIGTERM, then SIGKILL); exit codes by name.

        Negative: ended by a signal (or a thread still running: -1). Safe to call again.
        """
        self._closed = True
        for child in self._children.values():
            if child.poll() is None:
                child.ask()
        deadline = time.monotonic() + ASK_S
        for child in self._children.values():
            child.wait(max(0.1, deadline - time.monotonic()))
        codes: dict[str, int] = {}
        for name, child in self._children.items():
            code: int | None
            if isinstance(child, ProcessChild):
                code = child.force()
                child.close_stdin()
                if child.reader is not None:
                    child.reader.join(_JOIN_S)
                if child.popen.stdout is not None:
                    with contextlib.suppress(OSError):
                        child.popen.stdout.close()
            else:
                code = child.poll()
            codes[name] = -1 if code is None else code
        for logfile in self._files.values():
            logfile.close(keep_text=not self._keep_logs)
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)
            self._scratch = None
        return codes
