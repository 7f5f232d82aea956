"""Allocation and fail-safe: which rate a managed publisher runs at, from what it heard when.

The optimizer pushes a rate (``[topic]/dbm/frequency/current_value``) when it changes and a
heartbeat (``/dbm/round``) every period; either one renews the allocation for
``failsafe_periods`` periods. Past that deadline nobody is known to be minding the budget, so
the channel runs at its declared minimum until an allocation or heartbeat is heard again. A
new channel has no allocation yet: it waits for the first, sending nothing (the optimizer can
only make room once it knows the size, so the wait counts from when the size is known). A
heartbeat during that wait renews it: the optimizer runs, and a fleet joining at once may take
it several periods to admit, which is no reason to send unbudgeted frames. Only a wait in
silence ends in the fail-safe, at the minimum.

Pure state: no clock of its own (every call takes ``now``), no lock, no I/O. The publisher
serialises calls under its lock and does the logging and the acknowledgements outside it.
"""

from __future__ import annotations

import math

__all__ = ["FAILSAFE_PERIODS", "FailSafe"]

FAILSAFE_PERIODS = 3.0
"""Optimisation periods without an allocation before a publisher falls back to its minimum."""
DEFAULT_PERIOD_S = 1.0
"""The optimisation period assumed until ``/dbm/optimization_rate_in_seconds`` says otherwise."""


class FailSafe:
    """The allocation in force for one channel, and its deadline.

    ``rate_hz(now)`` is the one definition of the rate in force: the allocation while it is
    fresh, else the minimum (before the first allocation and in fail-safe alike).
    ``waiting(now)`` says whether the channel is still within its wait for a first allocation,
    when nothing may cross the network for it.
    """

    __slots__ = (
        "_failsafe_periods",
        "_lapse_noted",
        "_last_heard",
        "_period_s",
        "_wait_noted",
        "_wait_since",
        "allocated_hz",
        "deadline",
        "max_rate_hz",
        "min_rate_hz",
    )

    def __init__(
        self,
        *,
        min_rate_hz: float,
        max_rate_hz: float,
        now: float,
        failsafe_periods: float = FAILSAFE_PERIODS,
        period_s: float = DEFAULT_PERIOD_S,
    ) -> None:
        self.min_rate_hz = min_rate_hz
        self.max_rate_hz = max_rate_hz
        self._failsafe_periods = failsafe_periods
        self._period_s = period_s
        self.allocated_hz: float | None = None
        """The last allocation heard, clamped to the maximum (None: none yet)."""
        self._last_heard = now
        self.deadline = math.inf
        """The allocation (or the wait for the first one) stands until then."""
        self._lapse_noted = False
        self._wait_since = now
        """When the wait for a first allocation began (the size known, else creation)."""
        self._wait_noted = False
        self._renew(now)

    @property
    def failsafe_periods(self) -> float:
        """Periods of silence after which the minimum applies."""
        return self._failsafe_periods

    def _renew(self, now: float) -> None:
        self._last_heard = now
        self.deadline = now + self._failsafe_periods * self._period_s

    def rate_hz(self, now: float) -> float:
        """The rate in force at ``now``: the fresh allocation, else the minimum."""
        allocated = self.allocated_hz
        if allocated is not None and now <= self.deadline:
            return allocated
        return self.min_rate_hz

    def in_force(self) -> tuple[float, float] | None:
        """The allocation and the time up to which ``rate_hz`` answers it (None: none yet).

        For a hot path that compares one number per message instead of asking every time.
        """
        allocated = self.allocated_hz
        return None if allocated is None else (allocated, self.deadline)

    def waiting(self, now: float) -> bool:
        """Whether no allocation came yet and the wait for the first one is not over."""
        return self.allocated_hz is None and now <= self.deadline

    def lapsed(self, now: float) -> bool:
        """Whether nothing was heard for ``failsafe_periods`` periods (fail-safe)."""
        return now > self.deadline

    @property
    def lapse_noted(self) -> bool:
        """Whether a fail-safe was noted (``note_lapse``) and no allocation heard since."""
        return self._lapse_noted

    def allocate(self, rate_hz: float, now: float) -> float:
        """An allocation of ``rate_hz`` arrived at ``now``: the rate now in force.

        The publisher is the authority on its bounds: a rate above the maximum is clamped.
        """
        allocated = self.allocated_hz = min(rate_hz, self.max_rate_hz)
        self._heard(now)
        return allocated

    def heartbeat(self, now: float) -> float | None:
        """The optimizer's heartbeat at ``now``: the allocation it does not push again stands.

        Returns that allocation (None: there is none, and a heartbeat alone allocates nothing,
        but it renews the wait for the first one: the optimizer is alive).
        """
        allocated = self.allocated_hz
        if allocated is not None or not self._lapse_noted:
            self._heard(now)
        return allocated

    def _heard(self, now: float) -> None:
        self._renew(now)
        self._lapse_noted = False
        if self.allocated_hz is not None:
            self._wait_noted = False

    @property
    def period_s(self) -> float:
        """The optimizer's period, as last heard."""
        return self._period_s

    def set_period(self, period_s: float) -> None:
        """A new optimisation period: the deadline counts from the last word in it."""
        self._period_s = period_s
        self.deadline = self._last_heard + self._failsafe_periods * period_s

    def size_known(self, now: float) -> None:
        """The optimizer now knows the size: the wait for a first allocation counts from here.

        Once the fail-safe was noted the channel stays at its minimum until an allocation.
        """
        if self.allocated_hz is None and not self._lapse_noted:
            self._wait_since = now
            self._renew(now)

    def note_long_wait(self, now: float) -> float | None:
        """Seconds waited, the first time a wait renewed by heartbeats outlasts the deadline.

        The optimizer runs but has not admitted the channel (it tracks too many channels, or
        has not heard the size yet): said once, so the silence is not a mystery.
        """
        if not self.waiting(now) or self._wait_noted:
            return None
        waited_s = now - self._wait_since
        if waited_s <= self._failsafe_periods * self._period_s:
            return None
        self._wait_noted = True
        return waited_s

    def note_lapse(self, now: float) -> float | None:
        """Seconds since the last word, the first time ``now`` is found in fail-safe; else None.

        So the fail-safe is reported once; ``lapse_noted`` then says an allocation ends it.
        """
        if now <= self.deadline or self._lapse_noted:
            return None
        self._lapse_noted = True
        return now - self._last_heard
