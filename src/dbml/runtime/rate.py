"""Rate control: a limiter, a loop pacer (the paper's DBMRate) and a camera's byte window.

The limiter drops what exceeds a rate; the pacer paces a loop at it. Both count credit: frames
earned at the rate in force over time, the integral of the rate. A message (or a loop tick)
spends one frame. So what goes out in any window is at most what the rates in force over that
window allowed, plus the frames banked at its start, however often the rate changes: a rate that
is high for an instant earns an instant's worth, not a whole period's (a scheme that only
remembers the last message's time would let every brief increase send at once). Where a change
is seen late (at the next call), the time since the last look counts at the lower of the old and
the new rate, so a late-seen decrease never earns at the old rate. The byte window holds a
camera's frames to the bytes the allocation counted them at.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable

__all__ = [
    "PACER_LATE_S",
    "PACER_LATE_SHARE",
    "REALIGN_RATIO",
    "SAME_RATE",
    "ByteWindow",
    "Rate",
    "RateLimiter",
    "caught_up_periods",
    "same_rate",
]

_EPSILON_FRAMES = 1e-9
"""Rounding slack, so a message exactly one period later is never refused."""
_PACER_BEHIND_FRAMES = 2.0
"""The most credit a loop holds: a whole period late."""
PACER_LATE_SHARE = 0.25
"""A tick later than this share of a period, and than ``PACER_LATE_S``, restarts the schedule."""
PACER_LATE_S = 0.05
"""A tick later than this, and than ``PACER_LATE_SHARE`` of a period, restarts the schedule."""
WINDOW_S = 1.0
"""The window the budget is promised over (what a passive counter of the wire measures)."""
SAME_RATE = 1e-9
"""Rates this close (relative) are one: a solver's rounding (1.000000000000011 Hz for a floor
of 1) is no change to push, nor one for a loop to realign its phase to."""
REALIGN_RATIO = 1.25
"""A pacer that keeps its phase moves to its grid when the rate changes by this factor or more."""
MAX_WINDOW_FRAMES = 4096
"""The most frames a ``ByteWindow`` remembers (its memory bound; far above any camera's rate)."""


def caught_up_periods(rate_hz: float) -> float:
    """How late a tick of a loop at ``rate_hz`` may be, in periods, and still be caught up.

    The later of ``PACER_LATE_SHARE`` of a period and ``PACER_LATE_S``, at most a period.
    """
    return min(max(PACER_LATE_SHARE, PACER_LATE_S * rate_hz), 1.0)


def same_rate(a_hz: float, b_hz: float) -> bool:
    """Whether two rates are one: equal but for an allocation's float noise (``SAME_RATE``)."""
    return math.isclose(a_hz, b_hz, rel_tol=SAME_RATE, abs_tol=0.0)


def _realigns(tick_hz: float, hz: float) -> bool:
    """Whether a loop that ticked at ``tick_hz`` moves to its grid at ``hz``."""
    return tick_hz <= 0 or max(hz / tick_hz, tick_hz / hz) >= REALIGN_RATIO


class _Credit:
    """Frames earned at the rate in force since the last look, capped at ``cap_frames``."""

    def __init__(self, rate_hz: float, *, cap_frames: float) -> None:
        self.rate_hz = rate_hz
        self._cap = cap_frames
        self.frames = 1.0  # the first message goes at once
        self.seen: float | None = None
        """When credit was last earned up to."""

    def look(self, now: float, rate_hz: float | None = None) -> None:
        """Earn up to ``now``; a new rate counts from the last look at the lower of the two."""
        earning = self.rate_hz if rate_hz is None else min(self.rate_hz, rate_hz)
        self._earn(now, earning)
        if rate_hz is not None:
            self.rate_hz = rate_hz

    def _earn(self, now: float, earning_hz: float) -> None:
        """Add what ``earning_hz`` earned since the last look (the one rule of credit)."""
        seen = self.seen
        if seen is None or now > seen:
            if seen is not None:
                self.frames = min(self.frames + (now - seen) * earning_hz, self._cap)
            self.seen = now

    def spend(self) -> bool:
        if self.frames < 1.0 - _EPSILON_FRAMES:
            return False
        self.frames = max(self.frames - 1.0, 0.0)
        return True

    def take(self, now: float) -> bool:
        """``look(now)`` then ``spend()``: the hot path of every managed publish."""
        self._earn(now, self.rate_hz)
        return self.spend()

    def wait_s(self) -> float:
        """Seconds until one frame is earned at the rate in force (infinite at 0 Hz)."""
        missing = 1.0 - self.frames
        if missing <= 0.0:
            return 0.0
        return missing / self.rate_hz if self.rate_hz > 0 else math.inf


class RateLimiter:
    """``allow(now)`` is True when a message may go out at the rate in force.

    A source faster than the rate gets exactly the rate on average; after a pause at most one
    extra message goes out early (two frames of credit at most).
    """

    BANKED_FRAMES = 2.0
    """The most credit kept: a source that called late may catch up one message, no more."""

    def __init__(self, rate_hz: float) -> None:
        self._credit = _Credit(rate_hz, cap_frames=self.BANKED_FRAMES)

    @property
    def rate_hz(self) -> float:
        """The rate in force."""
        return self._credit.rate_hz

    def set_rate(self, rate_hz: float, now: float) -> None:
        """Apply ``rate_hz`` from ``now``; what was earned until ``now`` is kept.

        So a faster allocation takes effect at once (the part of a period already waited
        counts), and a brief one earns only its share. What was banked stays across a
        decrease: it is a paced loop's margin against its late wake-ups (without it a 1-Hz
        loop's on-time tick after a late one was refused, and the stream went 2 s without a
        frame), and it is within the limiter's bound (``BANKED_FRAMES``), decrease or not.
        """
        self._credit.look(now, rate_hz)

    def restart(self, rate_hz: float, now: float, *, owed_frames: float = 0.0) -> None:
        """Apply ``rate_hz`` from ``now`` with at most one frame of credit, less ``owed_frames``.

        After a pause that must not be banked (an outage): what was earned up to one frame is
        kept, so restarting often never starves a channel, and frames already sent that the
        pause's time does not cover are owed (the credit goes below zero).
        """
        credit = self._credit
        credit.look(now, rate_hz)
        credit.frames = min(credit.frames, 1.0) - owed_frames

    def allow(self, now: float) -> bool:
        """Whether a message may go out at ``now``; if so it counts as sent."""
        return self._credit.take(now)

    def wait_s(self, now: float) -> float:
        """Seconds from ``now`` until a message may go at the rate in force (0: at once)."""
        self._credit.look(now)
        return self._credit.wait_s()


class Rate:
    """``sleep()`` blocks until the next tick of a loop running at ``rate_hz()``.

    The loop earns one tick per period of the rate in force, read every ``poll_s`` while
    waiting, so a new allocation applies within ``poll_s`` even in the middle of a long period.
    Ticks keep absolute deadlines: neither loop work nor a late wake-up (a sleep returns after
    its time, later on a busy machine) adds to the period, so the loop runs at the rate itself
    (each tick's wake-up delay lost, 1.6 ms at 16 Hz on a loaded testbed, cost 2.5 % of the
    rate). A tick later than ``caught_up_periods`` (the longer of a quarter of a period and
    50 ms) is a stall, not a late wake-up: it restarts the schedule, and its time is lost. A
    caught-up tick follows the late one sooner than a period, and on a link the stream nearly
    fills it waits behind it: R1's 84,000-B frames at 5.48 Hz on a 4-Mbit uplink (176 ms to
    cross, 3.6 % of the uplink idle), stopped 150 ms, sent a tick 141 ms late and the next 42 ms
    after it, which waited 126 ms behind the first, and the backlog took 3 s to drain.

    ``keep_phase``: after the rate changes by ``REALIGN_RATIO`` or more, the first tick at the
    new rate goes at the point of the loop's own grid (``first tick + k / rate``) nearest to
    when the credit allows it (up to half a period earlier or later), and the loop stays on
    that grid: it keeps its phase instead of taking the moment of the change as its new one.
    An optimizer pushes a new allocation to every publisher at once; without this, every loop
    slowed by one push starts its slow schedule from that push, and a fleet's large frames
    leave together once a period (measured: three 1 Hz robots of eight within 30 ms of each
    other, 125 ms apart before the push; their 84 KB frames overflowed the shared link's
    queue). It costs less than a period's wait once per such change. That tick never comes
    sooner after the last one than the faster of the two rates' periods: a raised camera's
    84 KB frame 223 ms after the one before (at 1.93 Hz, then 2.69) went onto a link at 95 %
    of its rate and past tbf's queue. A smaller change (an estimator's probe moves the rates a
    few percent every update) keeps the schedule the credit makes, which carries a loop's
    place in its period over to the new rate: realigning at each one put the next tick at a
    new point of a new grid each time, and a 2.8 Hz camera probed every 200 ms went 0.7 s
    without a frame.
    """

    def __init__(
        self,
        rate_hz: Callable[[], float],
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        poll_s: float = 0.05,
        keep_phase: bool = False,
    ) -> None:
        self._rate_hz = rate_hz
        self._clock = clock
        self._sleep = sleep
        self._poll_s = poll_s
        self._keep_phase = keep_phase
        self._credit: _Credit | None = None
        self._anchor = 0.0
        """The loop's first tick: its phase, kept across rate changes with ``keep_phase``."""
        self._tick_hz = 0.0
        """The rate of the last tick: a different one in force is a change."""
        self._last_tick = 0.0
        """When the loop last ticked: the first tick at a new rate is timed from it."""

    def sleep(self) -> None:
        """Block until the loop's next tick."""
        if self._credit is None:  # the loop's first tick is now
            hz = self._rate_hz()
            self._credit = _Credit(hz, cap_frames=_PACER_BEHIND_FRAMES)
            self._anchor = self._clock()
            self._credit.look(self._anchor)
            self._credit.spend()
            self._tick_hz, self._last_tick = hz, self._anchor
            return
        credit = self._credit
        pending: tuple[float, float] | None = None  # a new rate and its tick on the grid
        while True:
            now, hz = self._clock(), self._rate_hz()
            credit.look(now, hz)
            if credit.frames >= 1.0 + caught_up_periods(hz) - _EPSILON_FRAMES:
                credit.frames = 1.0  # a stall, not a late wake-up: this tick now, then on schedule
            if self._keep_phase and hz > 0 and _realigns(self._tick_hz, hz):
                # A new rate: tick at the point of the loop's own grid nearest to when the
                # credit allows (at most half a period either side), then stay on the grid.
                if pending is None or pending[0] != hz:
                    # Never sooner after the last tick than the faster rate's period: a tick
                    # early for both rates is a frame more than the link was carrying.
                    soonest = max(now, self._last_tick + 1 / max(hz, self._tick_hz))
                    pending = (hz, self._grid_point(now + credit.wait_s(), hz, soonest))
                grid = pending[1]
                if now < grid:
                    self._sleep(min(grid - now, self._poll_s))
                    continue
                credit.frames, credit.seen = 0.0, grid
                self._tick_hz, self._last_tick = hz, grid
                return
            if pending is not None:
                # The rate went back near the last tick's before the grid's point: what the
                # wait earned is no catch-up, the credit's schedule goes on from one frame.
                credit.frames, pending = min(credit.frames, 1.0), None
            if credit.spend():
                self._tick_hz, self._last_tick = hz, now
                return
            self._sleep(min(credit.wait_s(), self._poll_s))

    def _grid_point(self, due: float, hz: float, soonest: float) -> float:
        """The point of the loop's grid at ``hz`` (first tick + k / hz) nearest to ``due``.

        Or, if that one is before ``soonest``, the first one at or after it.
        """
        k = max(
            round((due - self._anchor) * hz),
            math.ceil((soonest - self._anchor) * hz - _EPSILON_FRAMES),
        )
        return self._anchor + k / hz

    def reset(self) -> None:
        """Start the schedule again at the next ``sleep()``."""
        self._credit = None


class ByteWindow:
    """A camera's frames within the bytes the allocation counted them at, over any 1-s window.

    The optimizer allocates a camera's rate on its rung's bytes as the ladder said them. A scene
    that gets busier sends larger frames until the ladder is measured again and the next round
    follows, and a rate that fills the budget then overspends it by as much. Each frame the rate
    lets through is offered here with its bytes, the bytes it was counted at and the rate in
    force; it goes only if the frames that went in the last ``window_s``, with it, are within
    the channel's share of the promise: what its allocations (rate times counted bytes) earned
    over the window, and the limiter's ``RateLimiter.BANKED_FRAMES`` at the largest count of
    the window's frames (a late frame and its catch-up put the rate's frames and two in one
    window; a window that opens just before a frame of a higher count, before a cut or a lower
    rung, holds a frame more of it than its rate earned in the window). So a frame over its
    count costs a later frame, never the budget; frames at their count are never refused; and
    frames refused, or offered close together, do not widen the window.
    """

    def __init__(self, *, window_s: float = WINDOW_S, max_frames: int = MAX_WINDOW_FRAMES) -> None:
        self._window_s = window_s
        self._frames: collections.deque[tuple[float, int, int]] = collections.deque()
        """(time, bytes sent: 0 if refused, counted bytes) of each frame offered in the window."""
        self._max_frames = max_frames
        self._sent = 0
        self._allocations: collections.deque[tuple[float, float]] = collections.deque()
        """(since, bytes/s) of each allocation in force over the window, oldest first; the
        oldest counts as in force over the whole window before the next (a first frame's
        allocation was the channel's before it)."""
        self._seen: float | None = None
        """When a frame was last offered: a lower allocation seen now counts from then."""
        self.refused = 0
        """Frames refused so far (a count for a monitor or a test)."""

    def admit(self, now: float, size_bytes: int, counted_bytes: int, *, rate_hz: float) -> bool:
        """Whether a frame of ``size_bytes``, counted at ``counted_bytes``, goes at ``now``."""
        frames = self._frames
        while frames and (frames[0][0] <= now - self._window_s or len(frames) >= self._max_frames):
            self._sent -= frames.popleft()[1]
        self._allocate(now, rate_hz * counted_bytes)
        self._seen = now
        largest = max((counted for _, _, counted in frames), default=counted_bytes)
        banked = RateLimiter.BANKED_FRAMES * max(largest, counted_bytes)
        fits = self._sent + size_bytes <= banked + self._earned(now)
        sent = size_bytes if fits else 0
        frames.append((now, sent, counted_bytes))
        self._sent += sent
        if not fits:
            self.refused += 1
        return fits

    def left(self, now: float) -> None:
        """The frame last admitted left at ``now`` (its send returned): it counts from then.

        A frame is judged when it is offered, before its send, and counted from when its send
        returned, so a window of the times frames left (what a counter of the wire sees) never
        holds more than one of this window does. Counted from its offer instead, a 16-Hz
        camera's 24-KB frames beside a testbed's processes put a 17th frame in one 1-s window by
        send time (402,108 B of a 400,114-B bound, 1 of 25 runs).
        """
        frames = self._frames
        if frames:
            at, sent, counted = frames[-1]
            frames[-1] = (max(at, now), sent, counted)

    def _allocate(self, now: float, bytes_per_s: float) -> None:
        """Record the allocation in force at ``now``; forget those wholly before the window.

        A change is seen at the next frame; the time since the last one counts at the lower of
        the two (as the limiter's credit does), so a cut seen late earns nothing at the old rate.
        """
        allocations = self._allocations
        if not allocations or allocations[-1][1] != bytes_per_s:
            since = now
            if allocations and self._seen is not None and bytes_per_s < allocations[-1][1]:
                since = self._seen
            while allocations and allocations[-1][0] >= since:
                allocations.pop()  # superseded from its start
            allocations.append((since, bytes_per_s))
        start = now - self._window_s
        while len(allocations) > 1 and (
            allocations[1][0] <= start or len(allocations) > self._max_frames
        ):
            allocations.popleft()

    def _earned(self, now: float) -> float:
        """The bytes the allocations in force over the window ending at ``now`` earned."""
        allocations = self._allocations
        start = now - self._window_s
        earned = 0.0
        for i, (since, bytes_per_s) in enumerate(allocations):
            begin = start if i == 0 else max(since, start)
            end = allocations[i + 1][0] if i + 1 < len(allocations) else now
            earned += bytes_per_s * max(end - begin, 0.0)
        return earned
