"""Rate control: a limiter that drops what exceeds a rate, and a loop pacer (the paper's DBMRate).

The limiter drops what exceeds the rate; the pacer sleeps to absolute deadlines, so a sensor loop
runs at the rate without drift and does not even capture what would be dropped.
"""

from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ["Rate", "RateLimiter"]


class RateLimiter:
    """``allow(now)`` is True when a message may go out at ``rate_hz``.

    A message is due every period; a source faster than the rate gets exactly the rate on
    average, and after a pause at most one extra message goes out early. A new rate applies
    from the last message on.
    """

    def __init__(self, rate_hz: float) -> None:
        self._period = 1.0 / rate_hz
        self._due = -float("inf")

    @property
    def rate_hz(self) -> float:
        """The rate in force."""
        return 1.0 / self._period

    def set_rate(self, rate_hz: float) -> None:
        """Apply a new rate from the last message on: the next is due one new period after it.

        So a faster allocation takes effect at once instead of after the old, slower period.
        """
        period = 1.0 / rate_hz
        if period != self._period:
            self._due += period - self._period  # -inf (nothing sent yet) stays -inf
            self._period = period

    def allow(self, now: float) -> bool:
        """Whether a message may go out at ``now``; if so it counts as sent."""
        if now < self._due:
            return False
        first = self._due == -float("inf")
        self._due = now + self._period if first else max(self._due + self._period, now)
        return True


class Rate:
    """``sleep()`` blocks until the next tick of a loop running at ``rate_hz()``.

    The deadline is one period after the previous tick, with the period of the rate in force
    while waiting: a new allocation applies within ``poll_s``, even in the middle of a long
    period. Falling behind by more than a period restarts the schedule instead of bursting.
    """

    def __init__(
        self,
        rate_hz: Callable[[], float],
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        poll_s: float = 0.05,
    ) -> None:
        self._rate_hz = rate_hz
        self._clock = clock
        self._sleep = sleep
        self._poll_s = poll_s
        self._last: float | None = None

    def sleep(self) -> None:
        """Block until the loop's next tick."""
        now = self._clock()
        if self._last is None:  # the loop's first tick is now
            self._last = now
            return
        while True:
            period = 1.0 / self._rate_hz()
            deadline = self._last + period
            now = self._clock()
            if now >= deadline:
                break
            self._sleep(min(deadline - now, self._poll_s))
        self._last = deadline if now - deadline < period else now

    def reset(self) -> None:
        """Start the schedule again at the next ``sleep()``."""
        self._last = None
