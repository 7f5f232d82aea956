"""What the supervisor's children wrote on stdout: their lines, in one bounded mailbox.

Each line is a :class:`Line` (with the JSON object it holds, if it holds one); the last of a
child's is one with ``ended`` set. The :class:`Mailbox` keeps them in arrival order, at most
``per_child`` unread lines of each child (a child that writes more loses its oldest, said once).
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

__all__ = ["Line", "Mailbox", "read_line"]

log = logging.getLogger("dbml.harness")


@dataclass(frozen=True, slots=True)
class Line:
    """One line a child wrote on stdout, or the end of its output (``ended``)."""

    child: str
    text: str
    """The line without its newline (empty at the end)."""
    report: dict[str, Any] | None = None
    """The JSON object the line holds; None for any other line."""
    ended: bool = False
    """The child's output ended: it exited, or its output can no longer be read."""

    @property
    def kind(self) -> str | None:
        """The report's ``type`` (``ready``, ``done``, ...), if the line is a report."""
        kind = None if self.report is None else self.report.get("type")
        return kind if isinstance(kind, str) else None


def read_line(child: str, text: str) -> Line:
    """A line as read: its report if it holds a JSON object."""
    text = text.rstrip("\n")
    report: Any = None
    with contextlib.suppress(ValueError):
        report = json.loads(text)
    return Line(child, text, report if isinstance(report, dict) else None)


class Mailbox:
    """Every child's lines, in arrival order, bounded per child; read selectively.

    ``take`` gives the oldest line that matches, waiting for one; lines that do not match stay
    for a later call, so one reader can wait for one child's report while others queue.
    """

    def __init__(self, per_child: int) -> None:
        self._per_child = per_child
        self._cond = threading.Condition()
        self._lines: dict[str, collections.deque[tuple[int, Line]]] = {}
        self._seq = 0
        self._overflowed: set[str] = set()

    def put(self, line: Line) -> None:
        """One more line of its child (its oldest unread one goes when the child is full)."""
        with self._cond:
            lines = self._lines.setdefault(line.child, collections.deque(maxlen=self._per_child))
            if len(lines) == self._per_child and line.child not in self._overflowed:
                self._overflowed.add(line.child)
                log.warning(
                    "%s: more than %d unread lines, dropping the oldest",
                    line.child,
                    self._per_child,
                )
            self._seq += 1
            lines.append((self._seq, line))
            self._cond.notify_all()

    def _first_locked(self, where: Callable[[Line], bool]) -> tuple[str, int] | None:
        """The child and index of the oldest line that matches ``where``."""
        best: tuple[int, str, int] | None = None
        for child, lines in self._lines.items():
            for index, (seq, line) in enumerate(lines):
                if best is not None and seq > best[0]:
                    break
                if where(line):
                    best = (seq, child, index)
                    break
        return None if best is None else (best[1], best[2])

    def take(self, where: Callable[[Line], bool], timeout_s: float) -> Line | None:
        """The oldest line that matches ``where``, waiting up to ``timeout_s``; None if none."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                found = self._first_locked(where)
                if found is not None:
                    child, index = found
                    lines = self._lines[child]
                    _, line = lines[index]
                    del lines[index]
                    return line
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def clear(self, child: str) -> None:
        """Forget ``child``'s unread lines."""
        with self._cond:
            self._lines.pop(child, None)
