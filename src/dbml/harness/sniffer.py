"""A passive wire sniffer: what was actually sent, in bytes per sliding window.

The budget is a promise about bytes on the wire, not about the rates the optimizer computes, so
benchmarks and tests that claim it count what a plain zenoh subscriber receives: every sample's
payload size and arrival time, on a key expression such as ``*/*/optimized``. ``worst_window``
slides a window (1 s by default) over every arrival and returns the most bytes any window held.
Where a sample carries dbml's metadata, its send time is kept too (``sent``): windows by send
time tell a publisher's overspend from a receiver that stalled and took a burst late.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from dbml.core.errors import TransportError
from dbml.protocol.metadata import MessageMeta

__all__ = ["WindowStats", "WireSniffer", "window_stats"]

WINDOW_S = 1.0
"""The paper's budget is per second: the default sliding window."""
_NS_PER_S = 1e9


@dataclass(frozen=True, slots=True)
class WindowStats:
    """Sliding-window totals over a recording: the worst and how often a limit was passed."""

    windows: int
    """How many windows were measured (one starting at each arrival that has a full window)."""
    worst_bytes: int
    over_share: float
    """The share of windows above the ``limit_bytes`` given to ``window_stats``."""


def window_stats(
    arrivals: list[tuple[float, int]], *, limit_bytes: float, window_s: float = WINDOW_S
) -> WindowStats:
    """The worst window, and the share of windows over ``limit_bytes``, of ``(t_s, bytes)``.

    A window starts at each arrival and spans ``window_s``; only windows that end before the last
    arrival count, so the tail of a recording does not look quiet.
    """
    if not arrivals:
        return WindowStats(0, 0, 0.0)
    arrivals = sorted(arrivals)
    end_s = arrivals[-1][0]
    worst = total = over = windows = 0
    right = 0
    for left, (start_s, _) in enumerate(arrivals):
        if start_s + window_s > end_s:
            break
        while right < len(arrivals) and arrivals[right][0] < start_s + window_s:
            total += arrivals[right][1]
            right += 1
        windows += 1
        worst = max(worst, total)
        over += total > limit_bytes
        total -= arrivals[left][1]
    return WindowStats(windows, worst, over / windows if windows else 0.0)


class WireSniffer:
    """Record the size and arrival time of every sample on ``key_expr`` (a context manager).

    It only subscribes: it declares nothing the runtime sees as a subscriber of dbml's graph,
    so it does not change what is managed.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._arrivals: list[tuple[float, int]] = []
        self._sent: list[tuple[float, int]] = []
        self._subscriber = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        attachment = sample.attachment
        sent_s = None
        if attachment is not None:
            try:
                sent_s = MessageMeta.decode(attachment.to_bytes()).sent_ns / _NS_PER_S
            except TransportError:
                sent_s = None  # not dbml's: its arrival alone counts
        with self._lock:
            self._arrivals.append((self._clock(), size))
            if sent_s is not None:
                self._sent.append((sent_s, size))

    def sent(self, *, since_s: float = -float("inf")) -> list[tuple[float, int]]:
        """Every ``(sent_s, bytes)`` carrying a send time (wall clock) at or after ``since_s``."""
        with self._lock:
            return [s for s in self._sent if s[0] >= since_s]

    def arrivals(self, *, since_s: float = -float("inf")) -> list[tuple[float, int]]:
        """Every ``(t_s, bytes)`` recorded at or after ``since_s``."""
        with self._lock:
            return [a for a in self._arrivals if a[0] >= since_s]

    def clear(self) -> None:
        """Forget what was recorded (a warm-up, say)."""
        with self._lock:
            self._arrivals.clear()
            self._sent.clear()

    def close(self) -> None:
        """Stop recording."""
        self._subscriber.undeclare()  # type: ignore[no-untyped-call]  # unannotated in stubs

    def __enter__(self) -> WireSniffer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
