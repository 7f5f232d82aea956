"""A channel's message size as the optimizer should know it: measured, and told only on change.

The publisher is the authority on its own size: the serialised message as sent (metadata and
protocol headers are the overhead that ``/dbm/max_bandwidth_utilization`` < 1 reserves room
for). Telling the optimizer of every few-percent wobble would re-optimise the fleet for
nothing, so only the first size and a change beyond ``SIZE_CHANGE`` are announced; a size
written by anyone else is disputed, and the next message re-asserts the real one.
"""

from __future__ import annotations

__all__ = ["SIZE_CHANGE", "SizeTracker"]

SIZE_CHANGE = 0.10
"""Relative change of message size that is worth telling the optimizer about."""


class SizeTracker:
    """The size last announced (``known_bytes``, -1 before the first) and when to announce anew.

    Not thread-safe on its own: ``observe`` belongs to the publishing thread; ``dispute`` may
    come from another, and only ever forgets the size (the worst a race does is one extra
    announcement).
    """

    __slots__ = ("_change", "known_bytes")

    def __init__(self, *, change: float = SIZE_CHANGE) -> None:
        self._change = change
        self.known_bytes = -1
        """The size announced last; ``publish`` compares a message's length with it first."""

    def observe(self, size_bytes: int) -> bool:
        """Whether ``size_bytes`` is to be announced (the first, or a material change)."""
        known = self.known_bytes
        if known >= 0 and abs(size_bytes - known) <= self._change * known:
            return False
        self.known_bytes = size_bytes
        return True

    def dispute(self, written: object) -> int | None:
        """Someone wrote ``written`` as our size: our real size if it is not that, else None.

        The real size is then forgotten, so the next ``observe`` announces it again: on the
        publishing thread, not as a blocking write on the caller's (often the middleware's).
        """
        known = self.known_bytes
        if written == known or known <= 0:
            return None
        self.known_bytes = -1
        return known
