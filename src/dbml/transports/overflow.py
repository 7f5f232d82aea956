"""What a bounded structure fed by the network says when it is full: once per flood, with a count.

Every structure filled by what peers send (sessions met, graph entries, parameter names) holds
at most a named bound; past it, new items are refused (or the oldest evicted) and memory stays
what the bound allows. A flood must not flood the log in turn: ``Overflow`` logs the first item
refused, then nothing until the flood is over (the structure fell to half its bound, so one
hovering at its bound does not log per item), and then how many were refused meanwhile.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

__all__ = ["MAX_LOGGED_KEYS", "LogOnce", "Overflow", "ThrottledLog"]

MAX_LOGGED_KEYS = 1_000
"""Distinct bad keys a ``LogOnce`` remembers; past it, it says so once and logs no more."""


class Overflow:
    """The refusals of one bounded structure, told once per flood.

    ``what`` names the structure's items (``"sessions met"``), ``bound`` is its size; with
    ``evicts`` the structure makes room by evicting an old item instead of refusing the new
    one, and says so. Thread-safe; it logs outside its lock, and its callers may hold theirs.
    """

    def __init__(self, what: str, bound: int, *, log: logging.Logger, evicts: bool = False) -> None:
        self.what = what
        self.bound = bound
        self._log = log
        self._action, self._done = (
            ("evicting the oldest", "evicted") if evicts else ("refusing new ones", "refused")
        )
        self._lock = threading.Lock()
        self._flooding = False
        self._in_flood = 0
        self.total = 0
        """Items refused (or evicted) over the structure's life."""

    @property
    def flooding(self) -> bool:
        """Whether the structure has refused items since it last had room."""
        with self._lock:
            return self._flooding

    def refuse(self, count: int = 1) -> None:
        """Count ``count`` items refused (or evicted); the first of a flood is logged."""
        with self._lock:
            self.total += count
            self._in_flood += count
            first, self._flooding = not self._flooding, True
        if first:
            self._log.warning(
                "%s: %d held, the most kept; %s (told once until half of them are gone)",
                self.what,
                self.bound,
                self._action,
            )

    def room(self, size: int) -> None:
        """The structure holds ``size`` now: at half its bound or less, a flood is over."""
        if size > self.bound // 2 or not self._flooding:  # the usual case, without the lock
            return
        with self._lock:
            if not self._flooding:
                return
            self._flooding = False
            count, self._in_flood = self._in_flood, 0
        self._log.warning("%s: room again; %d %s meanwhile", self.what, count, self._done)


class LogOnce:
    """Logs each distinct bad key once: the network may repeat a bad key or value forever.

    At most ``bound`` keys are remembered; the next one is told as "no more are logged", once.
    """

    def __init__(self, log: logging.Logger, *, bound: int = MAX_LOGGED_KEYS) -> None:
        self._log = log
        self._bound = bound
        self._seen: set[str] = set()
        self._full = False
        self._lock = threading.Lock()

    def warning(self, key: str, message: str, *args: object) -> None:
        """Log ``message % args`` the first time ``key`` is seen."""
        with self._lock:
            if key in self._seen or self._full:
                return
            full = self._full = len(self._seen) >= self._bound
            if not full:
                self._seen.add(key)
        if full:
            self._log.warning("%d distinct bad keys logged: no more are logged", self._bound)
        else:
            self._log.warning(message, *args)


class ThrottledLog:
    """Logs a repeated problem per key at most once per ``interval_s``, with how many were ignored.

    A node may publish a bad value at kilohertz rates; each one is still counted. At most
    ``bound`` keys are remembered (the oldest is forgotten first).
    """

    def __init__(
        self,
        interval_s: float,
        *,
        log: logging.Logger,
        clock: Callable[[], float] = time.monotonic,
        bound: int = MAX_LOGGED_KEYS,
    ) -> None:
        self._interval_s = interval_s
        self._log = log
        self._clock = clock
        self._bound = bound
        self._lock = threading.Lock()
        self._state: dict[str, tuple[float, int]] = {}
        """By key: when it was last logged, and what was ignored since."""

    def warning(self, key: str, message: str, *args: object) -> None:
        """Log ``message % args`` for ``key`` unless it was logged within the interval."""
        now = self._clock()
        with self._lock:
            last_s, ignored = self._state.pop(key, (None, 0))
            ignored += 1
            if last_s is not None and now - last_s < self._interval_s:
                self._state[key] = (last_s, ignored)
                return
            while len(self._state) >= self._bound:
                del self._state[next(iter(self._state))]
            self._state[key] = (now, 0)
        self._log.warning(
            f"{message} (%d value(s) ignored; logged at most every %g s)",
            *args,
            ignored,
            self._interval_s,
        )
