"""Priority sources: a channel's raw priority set directly, or computed from environment events."""

from __future__ import annotations

from collections.abc import Callable

from dbml.core.priority import collision_priority, time_to_collision_s
from dbml.core.spec import check_priority
from dbml.protocol import names
from dbml.transports.base import Transport

__all__ = ["PrioritySource", "collision_priority_source"]


class PrioritySource:
    """Turns events into ``[topic]/dbm/priority`` through a priority function (eq. 1).

    Writes only when the priority changes, so a sensor callback can call ``update`` freely; each
    write makes the optimizer re-allocate at once.
    """

    def __init__(self, transport: Transport, topic: str, function: Callable[..., float]) -> None:
        self.topic = names.check_channel(topic)
        self._transport = transport
        self._function = function
        self._last: float | None = None

    def set(self, priority: float) -> float:
        """Set the priority directly (validated as the core validates it)."""
        value = check_priority(priority, owner=f"channel {self.topic!r}")
        if value != self._last:
            self._last = value
            self._transport.params.set(names.priority(self.topic), value)
        return value

    def update(self, *events: float) -> float:
        """Compute the priority from ``events`` and publish it if it changed."""
        return self.set(self._function(*events))


def collision_priority_source(transport: Transport, topic: str) -> PrioritySource:
    """The paper's camera priority: ``update(distance_m, speed_m_per_s)`` -> eq. 6-7."""
    return PrioritySource(
        transport,
        topic,
        lambda distance_m, speed_m_per_s: collision_priority(
            time_to_collision_s(distance_m, speed_m_per_s)
        ),
    )
