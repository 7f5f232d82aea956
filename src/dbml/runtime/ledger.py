"""What each managed channel may be sending now, and which of a round's increases fit beside it.

A round's new rates reach the publishers at different times, so while they change the wire
carries some old rates and some new ones. Waiting for every decrease's acknowledgement before
any increase goes keeps the sum within the budget, but makes every increase (and the round's
heartbeat) wait for the slowest publisher of the fleet. The ledger instead counts what each
channel may still send, in bytes a second, and lets an increase go as soon as it fits:

- a channel whose decrease was pushed counts at its rate before it until the publisher
  acknowledges the new one, and for a drain after that: the frame it sent just before applying
  the decrease may still be queued on the link when the acknowledgement arrives. The drain is
  the time that frame takes at the budget's rate (the caller says it);
- a decrease not acknowledged within ``ack_timeout_s`` of its push counts as applied (the
  publisher may be gone; one that only missed the push hears it again a period later); one
  acknowledged drains in full, however late;
- an increase counts at its new rate from the moment it is pushed;
- an increase goes when the sum over every limit it belongs to stays within that limit
  (the budget, a link's capacity), in the order given (the most important first); one that does
  not fit waits for the next acknowledgement, drain or timeout, or, where the caller allows it,
  goes part of the way once the room made reaches a floor (the caller's: half of its rise), so
  a channel raised at the cost of many others moves when most of them have applied their cuts,
  not when the slowest has.

Pure: the clock is passed in.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

__all__ = ["FIT_TOLERANCE", "Limit", "RateLedger"]

FIT_TOLERANCE = 1e-9
"""Relative slack on a limit: an allocation that spends exactly the budget fits it."""


@dataclass(frozen=True, slots=True)
class Limit:
    """Bytes a second that the channels in ``topics`` may send together."""

    topics: frozenset[str]
    bytes_per_s: float


@dataclass(slots=True)
class _Decrease:
    before_bytes_per_s: float
    pushed_s: float
    drain_s: float
    settles_s: float = math.inf
    """When the channel counts at its new rate: its acknowledgement's arrival plus the drain."""


class RateLedger:
    """The decreases not yet applied, and the admission of increases beside them."""

    def __init__(self, *, ack_timeout_s: float) -> None:
        self._ack_timeout_s = ack_timeout_s
        self._pending: dict[str, _Decrease] = {}

    @property
    def pending(self) -> frozenset[str]:
        """The channels still counted at their rate before a decrease."""
        return frozenset(self._pending)

    def decrease(
        self, topic: str, *, before_bytes_per_s: float, drain_s: float, now: float
    ) -> None:
        """A decrease of ``topic`` was pushed at ``now``: count it at ``before`` until it settles.

        A second decrease before the first settled keeps the higher rate before.
        """
        old = self._pending.get(topic)
        before = (
            before_bytes_per_s if old is None else max(before_bytes_per_s, old.before_bytes_per_s)
        )
        self._pending[topic] = _Decrease(before, now, drain_s)

    def acknowledged(self, topic: str, now: float) -> None:
        """The publisher of ``topic`` said it applies the decrease: it settles after its drain."""
        pending = self._pending.get(topic)
        if pending is not None and math.isinf(pending.settles_s):
            pending.settles_s = now + pending.drain_s

    def settle(self, now: float) -> list[str]:
        """Forget the decreases settled by ``now``; return those that timed out, by topic."""
        late = []
        for topic, pending in list(self._pending.items()):
            if now >= self._settles_s(pending):
                del self._pending[topic]
                if math.isinf(pending.settles_s):
                    late.append(topic)
        return sorted(late)

    def _settles_s(self, pending: _Decrease) -> float:
        """Its drain's end once acknowledged, else its acknowledgement's deadline."""
        if math.isinf(pending.settles_s):
            return pending.pushed_s + self._ack_timeout_s
        return pending.settles_s

    def next_change_s(self) -> float | None:
        """The next time a decrease settles or times out without a new event (None: none)."""
        return min(map(self._settles_s, self._pending.values()), default=None)

    def forget(self, live: Iterable[str]) -> None:
        """Keep only the channels in ``live`` (the others are gone)."""
        kept = set(live)
        for topic in set(self._pending) - kept:
            del self._pending[topic]

    def clear(self) -> None:
        """Forget every decrease (a restart pushes every rate again)."""
        self._pending.clear()

    def committed(self, topic: str, current_bytes_per_s: float) -> float:
        """What ``topic`` may be sending: ``current`` (its pushed rate), or its rate before."""
        pending = self._pending.get(topic)
        if pending is None:
            return current_bytes_per_s
        return max(current_bytes_per_s, pending.before_bytes_per_s)

    def admit(
        self,
        increases: Mapping[str, float],
        current: Mapping[str, float],
        limits: Sequence[Limit],
        *,
        floors: Mapping[str, float] | None = None,
    ) -> dict[str, float]:
        """The increases (topic: new bytes a second, in order) that go now, in that order.

        ``current``: every channel's pushed bytes a second (a channel missing sends nothing).
        An increase goes in full when it fits; else, where ``floors`` names it, as far as it
        fits if that reaches its floor (a step on the way, so a rise need not wait for every
        decrease it needs). Each counts from then on, so a later one fits beside it or not at
        all. The value is the bytes a second each goes to.
        """
        floors = {} if floors is None else floors
        load = {t: self.committed(t, b) for t, b in current.items()}
        for topic in self._pending.keys() - load.keys():
            load[topic] = self._pending[topic].before_bytes_per_s
        totals = [sum(load.get(t, 0.0) for t in limit.topics) for limit in limits]
        admitted: dict[str, float] = {}
        for topic, wanted in increases.items():
            running = load.get(topic, 0.0)
            inside = [i for i, limit in enumerate(limits) if topic in limit.topics]
            extra = wanted - running
            if extra <= 0:
                admitted[topic] = wanted
                continue
            slack = min(
                (limits[i].bytes_per_s * (1.0 + FIT_TOLERANCE) - totals[i] for i in inside),
                default=math.inf,
            )
            room = min((limits[i].bytes_per_s - totals[i] for i in inside), default=math.inf)
            if extra <= slack:
                goes = wanted
            elif topic in floors and room > 0 and running + room >= floors[topic]:
                goes = running + room
            else:
                continue
            admitted[topic] = goes
            load[topic] = goes
            for i in inside:
                totals[i] += goes - running
        return admitted
