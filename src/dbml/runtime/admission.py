"""Which rate increases a round may push now: those the room on the wire already covers.

A round that lowers some channels and raises others pushes the decreases first. An increase may
go as soon as the budget has room for it, counting every channel at the higher of what it was
told and what it acknowledged running: a decrease not yet acknowledged still counts at its old
rate, an increase pushed counts at its new one. So the round does not wait for its slowest
publisher's acknowledgement before raising anyone: each acknowledgement frees its share, and
the increases it covers go out. A new channel rises from zero as soon as there is room for it.

Pure: the optimizer feeds it rates and acknowledgements and pushes what it answers.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

__all__ = ["Admission"]


@dataclass
class Admission:
    """The increases of one round, pushed as the room on the wire allows.

    ``load_bytes_per_s`` is every managed channel's rate times its size, counted at the higher
    of its old and new rate while its change is in flight; ``budget_bytes_per_s`` is what may be
    allocated. ``increases`` maps a topic to ``(from_hz, to_hz, size_bytes)``.
    """

    budget_bytes_per_s: float
    load_bytes_per_s: float
    increases: dict[str, tuple[float, float, float]]
    pushed: set[str] = field(default_factory=set)

    @classmethod
    def start(
        cls,
        *,
        budget_bytes_per_s: float,
        running_hz: Mapping[str, float],
        new_hz: Mapping[str, float],
        sizes_bytes: Mapping[str, float],
    ) -> Admission:
        """A round's increases, with every managed channel at what it runs at now.

        ``running_hz``: what the managed channels run at (0 for a new channel); ``new_hz``: the
        round's rates. Only channels with a size count.
        """
        load = 0.0
        increases: dict[str, tuple[float, float, float]] = {}
        for topic, size in sizes_bytes.items():
            before = running_hz.get(topic, 0.0)
            after = new_hz.get(topic, before)
            load += before * size  # a decrease counts at its old rate until acknowledged
            if after > before:
                increases[topic] = (before, after, size)
        return cls(budget_bytes_per_s, load, increases)

    def acknowledged(self, topic: str, *, before_hz: float, after_hz: float, size: float) -> None:
        """A decrease from ``before_hz`` to ``after_hz`` is in force: its share is free."""
        if after_hz < before_hz:
            self.load_bytes_per_s -= (before_hz - after_hz) * size

    def covered(self) -> list[str]:
        """The increases the room covers now, smallest first; each counts as pushed."""
        room = self.budget_bytes_per_s - self.load_bytes_per_s
        ready = []
        waiting = [
            (t, (after - before) * size) for t, (before, after, size) in self.increases.items()
        ]
        for topic, extra in sorted(waiting, key=lambda item: (item[1], item[0])):
            if topic in self.pushed:
                continue
            if extra > room:
                break
            room -= extra
            self.load_bytes_per_s += extra
            self.pushed.add(topic)
            ready.append(topic)
        return ready

    def rest(self) -> list[str]:
        """The increases not pushed yet (pushed anyway when the wait for acknowledgements ends)."""
        return sorted(set(self.increases) - self.pushed)
