"""dbml's background threads: each one says when it dies, so its process can exit non-zero.

A middleware callback must never block, so slow work (sending, polling, following the graph)
runs on threads of dbml's own. A thread that ends by an exception would leave a process that
looks alive and does nothing: every thread made here logs why it died (critical), turns its
``alive`` False and is counted by ``death_count()``, for the node's command to exit non-zero
(a supervisor then restarts it).

- ``PeriodicWorker``: ``tick()`` every interval and soon after ``wake()`` (a tick that raises
  is logged and the next one retries).
- ``OrderedSender``: items sent one at a time, in order, from a bounded queue, so ``put``
  never blocks its caller; ``flush`` waits (bounded) for what is queued.
- ``BackgroundThread``: any other loop (a server's ``serve_forever``).

Here, under transports, because transports need them and must not import the runtime; the
runtime re-exports ``PeriodicWorker`` from ``dbml.runtime.worker``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

from dbml.transports.overflow import Overflow

__all__ = [
    "DEFAULT_SENDER_CAPACITY",
    "FLUSH_TIMEOUT_S",
    "STOP_TIMEOUT_S",
    "BackgroundThread",
    "OrderedSender",
    "PeriodicWorker",
    "death_count",
]

T = TypeVar("T")

DEFAULT_SENDER_CAPACITY = 4096
"""The most items an ``OrderedSender`` holds unsent. A process's parameters coalesce to one
item per name, so this is room for the writes of about a thousand channels (an optimizer over
ROS 1 writes one per channel per round) plus batches queued through a long stall; an item is
a write or a round's allocation, KiB, so a stalled network costs megabytes, not the process."""
FLUSH_TIMEOUT_S = 4.0
"""How long closing a parameter store waits for its ``OrderedSender``'s queued writes: a send
that times out (a ROS 1 master call gives up after 2 s) and the next one."""
STOP_TIMEOUT_S = 5.0
"""How long stopping a thread waits for the work in progress (a tick, a send)."""

_deaths_lock = threading.Lock()
_death_count = 0


def _died(name: str, log: logging.Logger) -> None:
    """Say why the calling thread ends (the log names every death), and count it."""
    global _death_count  # noqa: PLW0603  # one count per process: any death fails its run
    log.critical("%s: the thread died", name, exc_info=True)
    with _deaths_lock:
        _death_count += 1


def death_count() -> int:
    """How many dbml threads of this process died so far: a run compares it with its start's."""
    with _deaths_lock:
        return _death_count


class BackgroundThread:
    """Run ``target()`` on a daemon thread; an exception out of it is a death, said and counted.

    ``target`` returning is a normal end (a ``serve_forever`` after ``shutdown()``).
    """

    def __init__(self, target: Callable[[], object], *, name: str, log: logging.Logger) -> None:
        self._target = target
        self._name = name
        self._log = log
        self._died = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        try:
            self._target()
        except BaseException:  # the thread ends here: say why, and ``alive`` tells the owner
            _died(self._name, self._log)
            self._died = True

    @property
    def alive(self) -> bool:
        """False once ``target`` raised (the thread died)."""
        return not self._died

    def start(self) -> BackgroundThread:
        """Start the thread (once)."""
        self._thread.start()
        return self

    def join(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Wait (bounded) for the thread to end; at once from the thread itself."""
        if self._thread.ident is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout_s)

    @property
    def running(self) -> bool:
        """Whether the thread runs now (started, not ended): a bounded ``join`` may leave it."""
        return self._thread.is_alive()

    def is_current(self) -> bool:
        """Whether the caller is this thread (``target`` calling back into its owner).

        Known from construction: no window in which the thread runs but is not known yet.
        """
        return self._thread is threading.current_thread()


class PeriodicWorker:
    """Call ``tick()`` on a daemon thread every ``interval_s`` and soon after ``wake()``.

    ``interval_s`` is a number, or read before each wait. Bursts of wakes within ``coalesce_s``
    run one tick. ``immediate`` runs the first tick at start instead of one interval later.
    A tick that raises is logged and the next one retries, so a bad input never ends the
    thread; should it end all the same (a ``SystemExit`` in a tick), ``alive`` turns False.
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
            thread = threading.Thread(target=self._run, name=self._name, daemon=True)
            thread.start()
            self._thread = thread  # once started: ``alive`` reads a made, unstarted one as dead
        return self

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException:  # the thread ends here: say why, and ``alive`` tells the node
            _died(self._name, self._log)

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

    def stop(self, *, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """Stop the thread and wait for the tick in progress (bounded)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout_s)


class OrderedSender(Generic[T]):
    """Hand items to ``send`` on a thread of its own, in order: ``put`` never blocks.

    A middleware callback may be the one that puts, and the network may stall: items wait in a
    queue of at most ``capacity``.
    An item put under a ``slot`` replaces the one of that slot still queued, and goes to the
    back (a parameter's newest write supersedes the older ones). When the queue is full the
    oldest item is dropped: the newest state is what matters, and memory stays bounded. The
    drops are told once per stall with a count (an ``Overflow``), by the sender's thread once
    its send in flight returns: ``put``'s callers may hold locks of theirs, so it logs nothing.

    ``send`` raising ``Exception`` loses that item (logged with ``describe(item)``); the
    thread goes on with the next. ``on_exit`` runs on the thread when it ends after ``close``
    (to release what ``send`` holds per thread, such as a connection).
    """

    def __init__(
        self,
        send: Callable[[T], None],
        *,
        name: str,
        log: logging.Logger,
        capacity: int = DEFAULT_SENDER_CAPACITY,
        describe: Callable[[T], str] = repr,
        on_exit: Callable[[], object] | None = None,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity={capacity!r} must be at least 1")
        self._send = send
        self._name = name
        self._log = log
        self._capacity = capacity
        self._describe = describe
        self._on_exit = on_exit
        self._changed = threading.Condition()
        self._queue: OrderedDict[Hashable, T] = OrderedDict()
        self._in_flight: list[T] = []
        self._closing = False
        self.dropped = 0
        """How many items were dropped because the queue was full (over the sender's life)."""
        self._untold = 0
        """Drops not handed to ``_full`` yet: the thread does, outside every lock."""
        self._full = Overflow(f"{name}: unsent items", capacity, log=log, evicts=True)
        self._thread = BackgroundThread(self._loop, name=name, log=log).start()

    @property
    def alive(self) -> bool:
        """False once the thread died (it does not on a failed send)."""
        return self._thread.alive

    def put(self, item: T, *, slot: Hashable | None = None) -> T | None:
        """Queue ``item`` (replacing the one queued under ``slot``); returns at once.

        Returns the item dropped to make room (the oldest, when the queue was full; ``item``
        itself once closing), so its owner can forget it was pending. It never logs: its caller
        may hold a lock (the sender's thread tells of drops).
        """
        dropped: T | None = None
        with self._changed:
            if self._closing:
                return item
            key: Hashable = object() if slot is None else slot
            if key in self._queue:
                del self._queue[key]
            elif len(self._queue) >= self._capacity:
                _, dropped = self._queue.popitem(last=False)
                self.dropped += 1
                self._untold += 1
            self._queue[key] = item
            self._changed.notify_all()
        return dropped

    def pending(self) -> list[T]:
        """What is not sent yet, oldest first: the item being sent, then the queue."""
        with self._changed:
            return [*self._in_flight, *self._queue.values()]

    def _loop(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: bool(self._queue) or self._closing)
                untold, self._untold = self._untold, 0
                if not self._queue:
                    break  # closing, and everything was sent
                _, item = self._queue.popitem(last=False)
                self._in_flight = [item]
                size = len(self._queue)
            self._tell(untold, size)
            try:
                self._send(item)
            except Exception as err:  # a closed session or a network error: keep sending
                self._log.warning("%s: %s not sent: %s", self._name, self._describe(item), err)
            finally:
                with self._changed:
                    self._in_flight = []
                    self._changed.notify_all()
        self._tell(untold, 0)
        if self._on_exit is not None:
            self._on_exit()

    def _tell(self, dropped: int, size: int) -> None:
        """Hand drops to ``_full`` and say how full the queue is (on the thread, no lock held)."""
        if dropped:
            self._full.refuse(dropped)
        self._full.room(size)

    def flush(self, timeout_s: float) -> bool:
        """Wait until every queued item was handed to ``send``; False after ``timeout_s``."""
        with self._changed:
            return self._changed.wait_for(
                lambda: not self._queue and not self._in_flight, timeout=timeout_s
            )

    def close(self, timeout_s: float) -> bool:
        """Send what is queued (waiting at most ``timeout_s``), then end the thread.

        False if items were left unsent; later ``put`` calls are ignored.
        """
        flushed = self.flush(timeout_s)
        with self._changed:
            self._closing = True
            self._queue.clear()
            self._changed.notify_all()
        if flushed:
            self._thread.join()
        return flushed
