"""The child's side of the supervisor: reports on stdout, control lines on stdin.

A child reports with :func:`emit_json` (one JSON object per line, from any thread) and reads its
control lines with one :class:`Control`: ``start <t0>`` (step 1's wall-clock time), ``stop``
(or EOF: its parent went away) and any other line, a command of its own. :func:`serve_role` is a
role's whole protocol: announce ``ready``, wait for ``start <t0>``, run, end on ``stop``, EOF or
a signal (:func:`stop_on_signals`).

A child run as a thread of the supervisor's process gets its lines and its report sink from the
supervisor (``ChildIO``) instead of stdin and stdout; the protocol is the same.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from dbml.core.errors import DbmlError
from dbml.transports.worker import BackgroundThread

__all__ = [
    "Control",
    "Emit",
    "RoleError",
    "emit_json",
    "serve_role",
    "stop_on_signals",
]

log = logging.getLogger("dbml.harness")

Emit = Callable[[dict[str, Any]], None]
"""A child's report sink: one JSON-able message."""
_EMIT_LOCK = threading.Lock()
"""One report is one line, also when several threads of a child report at once."""
_SHOWN_CHARS = 80
"""How much of a malformed control line an error quotes."""
_START_POLL_S = 0.1
"""How often a role waiting for its start looks whether it was stopped instead."""


class RoleError(DbmlError):
    """A role's run failed once it was ready (a dbml thread died, its control failed)."""


def emit_json(message: dict[str, Any]) -> None:
    """A child's report: one JSON line on stdout."""
    line = json.dumps(message) + "\n"
    with _EMIT_LOCK:
        sys.stdout.write(line)
        sys.stdout.flush()


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


def _start_time(line: str) -> float:
    """``t0`` of a ``start <t0>`` line; ``DbmlError`` naming the line if it is not one."""
    try:
        t0 = float(line.partition(" ")[2])
    except ValueError:
        t0 = math.nan
    if not math.isfinite(t0):
        raise DbmlError(f"control line {line.strip()[:_SHOWN_CHARS]!r} is not 'start <t0>'")
    return t0


class Control:
    """The one reader of a child's control lines; ``stop``, EOF or a failure set ``stop``.

    The first ``start <t0>`` line gives ``wait_start`` its time (a malformed one is a failure);
    later ones are ignored; ``stop`` ends the reading; any other line goes to ``commands``.

    ``hand_over``: a failure (a malformed start line, stdin failing) is kept for the caller's
    thread (``wait_start`` and ``check`` raise it as ``RoleError``), never a death raced
    against ``stop``. Otherwise the reading thread dies of it, said and counted (the process's
    ``Lifetime`` then exits 1).
    """

    def __init__(
        self,
        stop: threading.Event,
        *,
        lines: Iterable[str] | None = None,
        hand_over: bool = False,
        name: str = "control",
    ) -> None:
        self.stop = stop
        self.commands: queue.Queue[str] = queue.Queue()
        """Lines that are neither ``start`` nor ``stop``, stripped."""
        self._lines = lines
        self._hand_over = hand_over
        self._name = name
        self._started = threading.Event()
        self._t0: float | None = None
        self.failure: BaseException | None = None
        """What ended the reading, when it failed and ``hand_over`` is set."""

    def start(self) -> Control:
        """Start reading, on a thread of its own."""
        reader = BackgroundThread(self._read, name=self._name, log=log).start()
        if not self._hand_over:  # ``stop`` once a death is counted, so a Lifetime sees it
            BackgroundThread(
                lambda: self._stop_after(reader), name=f"{self._name}-end", log=log
            ).start()
        return self

    def _read(self) -> None:
        try:
            for line in sys.stdin if self._lines is None else self._lines:
                if line.startswith("stop"):
                    break
                if line.startswith("start "):
                    if not self._started.is_set():  # the first one counts
                        self._t0 = _start_time(line)
                        self._started.set()
                    continue
                self.commands.put(line.strip())
        except BaseException as err:
            if not self._hand_over:
                raise  # said and counted by its thread; ``_stop_after`` sets ``stop`` then
            self.failure = err
        self.stop.set()  # told to stop, EOF, or the reading failed (handed over)

    def _stop_after(self, reader: BackgroundThread) -> None:
        """Set ``stop`` once ``reader`` ended, however (its death counted by then)."""
        while reader.running:
            reader.join(_START_POLL_S)
        self.stop.set()

    def wait_start(self, *, owner: str = "") -> float | None:
        """The first start line's time; None when stopped first. ``RoleError`` on a failure."""
        while not self._started.is_set() and not self.stop.is_set():
            self._started.wait(_START_POLL_S)
        self.check(owner=owner)
        return self._t0 if self._started.is_set() and not self.stop.is_set() else None

    def check(self, *, owner: str = "") -> None:
        """``RoleError`` saying why (``owner``: whose control), if the reading failed."""
        failure = self.failure
        if failure is not None:
            whose = f"{owner}: " if owner else ""
            raise RoleError(f"{whose}its control thread failed: {failure}") from failure


def serve_role(
    role: str,
    stop: threading.Event,
    run: Callable[[float], None],
    *,
    lines: Iterable[str] | None = None,
    emit: Emit = emit_json,
) -> None:
    """Announce ``ready``, wait for ``start <t0>`` on ``lines`` (stdin), then ``run(t0)``.

    ``stop`` is set by ``stop`` or EOF (and by the caller's signal handlers), so a role whose
    parent went away ends too. A malformed line, or the lines failing, ends the role too: then
    ``RoleError`` says why, so the process exits non-zero instead of waiting for a start that
    never comes.
    """
    emit({"type": "ready", "role": role})
    control = Control(stop, lines=lines, hand_over=True).start()
    t0 = control.wait_start(owner=f"role {role}")
    if t0 is not None:
        run(t0)
    control.check(owner=f"role {role}")
