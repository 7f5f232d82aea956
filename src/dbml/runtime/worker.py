"""One periodic worker thread, for every node part that acts on a period (and on a poke).

The optimizer (every period and at once on a trigger), the estimator (every 0.1 s) and the
reception reporter (every 0.1 s) share it: a tick that raises is logged and the next one retries,
so a bad input can never end the thread while the process stays alive. Should the thread end all
the same (a ``SystemExit`` in a tick, say), it logs why and ``alive`` turns False: the node's
command then exits non-zero, so a supervisor restarts it instead of a process that looks alive
and does nothing.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

__all__ = ["PeriodicWorker"]


class PeriodicWorker:
    """Call ``tick()`` on a daemon thread every ``interval_s`` and soon after ``wake()``.

    ``interval_s`` is a number, or read before each wait. Bursts of wakes within ``coalesce_s``
    run one tick. ``immediate`` runs the first tick at start instead of one interval later.
    """

    def __init__(
        self,
        tick: Callable[[], object],
        *,
        interval_s: float | Callable[[], float],
        name: str,
        log: logging.Logger,
        coalesce_s: float = 0.0,
        immediate: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._tick = tick
        self._interval_s = interval_s
        self._name = name
        self._log = log
        self._coalesce_s = coalesce_s
        self._immediate = immediate
        self._clock = clock
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    FALLBACK_INTERVAL_S = 1.0
    """The wait used when reading the interval fails."""

    def _interval(self) -> float:
        try:
            return self._interval_s() if callable(self._interval_s) else self._interval_s
        except Exception:
            self._log.exception("%s: reading the interval failed", self._name)
            return self.FALLBACK_INTERVAL_S

    @property
    def alive(self) -> bool:
        """False once the thread has ended without ``stop()`` (it died)."""
        thread = self._thread
        return self._stop.is_set() or thread is None or thread.is_alive()

    def wake(self) -> None:
        """Run a tick as soon as possible."""
        self._wake.set()

    def start(self) -> PeriodicWorker:
        """Start the thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException:  # the thread ends here: say why, and ``alive`` tells the node
            self._log.critical("%s: the thread died", self._name, exc_info=True)

    def _loop(self) -> None:
        next_at = self._clock() + (0.0 if self._immediate else self._interval())
        while not self._stop.is_set():
            woken = self._wake.wait(timeout=max(0.0, next_at - self._clock()))
            if self._stop.is_set():
                break
            if woken and self._coalesce_s > 0:
                self._stop.wait(self._coalesce_s)
            self._wake.clear()
            try:
                self._tick()
            except Exception:  # keep the thread alive: the next tick retries
                self._log.exception("%s: tick failed", self._name)
            next_at = self._clock() + self._interval()

    def stop(self, *, timeout_s: float = 5.0) -> None:
        """Stop the thread and wait for the tick in progress (bounded)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout_s)
