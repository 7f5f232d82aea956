"""One list of callbacks, shared by every transport's subscriptions and watchers.

Callbacks may be added and removed from any thread, including from inside a callback. ``fire``
copies the list under its lock and calls the copy outside it, so a callback may take other locks
or call back into the transport without a deadlock; a callback that raises is logged and the
others still run, so one faulty watcher cannot silence the rest.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Generic, ParamSpec

from dbml.transports.base import Closer, Handle

__all__ = ["CallbackList"]

log = logging.getLogger("dbml.transports")

_P = ParamSpec("_P")


class _Entry(Generic[_P]):
    """One registration; ``closed`` stops a call already copied by a ``fire`` in progress."""

    __slots__ = ("closed", "fn")

    def __init__(self, fn: Callable[_P, object]) -> None:
        self.fn = fn
        self.closed = False


class CallbackList(Generic[_P]):
    """Callbacks taking ``_P``: ``add`` returns a handle that removes, ``fire`` calls them all."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: list[_Entry[_P]] = []

    def add(self, fn: Callable[_P, object]) -> Handle:
        """Register ``fn``; closing the handle removes it, and it is not called after that."""
        entry = _Entry(fn)
        with self._lock:
            self._entries.append(entry)

        def remove() -> None:
            entry.closed = True
            with self._lock:
                if entry in self._entries:
                    self._entries.remove(entry)

        return Closer(remove)

    def __bool__(self) -> bool:
        """Whether any callback is registered (a publisher's subscriber match)."""
        with self._lock:
            return bool(self._entries)

    def fire(self, *args: _P.args, **kwargs: _P.kwargs) -> None:
        """Call every callback, in registration order, outside the lock; log any that raises."""
        with self._lock:
            entries = list(self._entries)
        for entry in entries:
            if entry.closed:
                continue
            try:
                entry.fn(*args, **kwargs)
            except Exception:
                log.exception("callback %r failed", entry.fn)
