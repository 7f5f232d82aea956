"""Priority sources: set directly, computed from environment events, or heard on a topic.

``PrioritySource`` turns events into a channel's priority through a priority function (eq. 1);
``PriorityTopic`` takes it from ``std_msgs/Float64`` messages on ``[topic]/dbm/priority``, so
any ROS tool (``ros2 topic pub``, ``rostopic pub``) or a mission node of the user's sets it,
over every transport.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

from dbml.core.errors import TransportError
from dbml.core.priority import collision_priority, time_to_collision_s
from dbml.core.spec import check_number, check_priority
from dbml.protocol import names
from dbml.protocol.schema import PRIORITY, ParamError
from dbml.transports.base import Handle, Sample, Transport
from dbml.transports.overflow import ThrottledLog
from dbml.transports.worker import PeriodicWorker

__all__ = [
    "BAD_PRIORITY_LOG_S",
    "PRIORITY_INTERVAL_S",
    "PrioritySource",
    "PriorityTopic",
    "collision_priority_source",
]

log = logging.getLogger("dbml.priority")

PRIORITY_INTERVAL_S = 0.05
"""The shortest time between two priorities a channel takes from its topic. Each one is a
parameter write that every process hears and that makes the optimizer allocate again, so a
node publishing at kHz must not make one per message; 20 a second still follows a joystick."""
BAD_PRIORITY_LOG_S = 10.0
"""A channel's bad priorities from its topic are logged at most once per this many seconds
(with how many were ignored): a node may publish a bad value at kHz."""
_IDLE_S = 3600.0
"""How long the flood's worker waits with nothing held (``wake`` cuts it short)."""


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


class PriorityTopic:
    """A channel's priority from ``std_msgs/Float64`` messages on ``[topic]/dbm/priority``.

    The transport supplies only the message's serialisation (``Transport.float64``); the value
    is checked with the wire schema (a bad one is logged, ``BAD_PRIORITY_LOG_S`` apart) and
    written as ``[topic]/dbm/priority``. One flood rule, on every transport: at most one write
    per ``interval_s``. A value heard sooner is held (a newer one replaces it) and written when
    the interval ends, by a worker thread of its own: the middleware's callback thread never
    waits. ``clock`` (the transport's by default) decides when an interval ends;
    ``worker=False`` starts no thread: only ``tick()`` writes a held value (a test whose manual
    clock a thread waking on real time would race).
    """

    def __init__(
        self,
        transport: Transport,
        topic: str,
        *,
        interval_s: float = PRIORITY_INTERVAL_S,
        clock: Callable[[], float] | None = None,
        worker: bool = True,
    ) -> None:
        self.topic = names.check_channel(topic)
        self.interval_s = check_number(interval_s, field="interval_s", minimum=0)
        self._name = names.priority(topic)
        self._params = transport.params
        self._codec = transport.float64
        self._clock = transport.now if clock is None else clock
        self._bad = ThrottledLog(BAD_PRIORITY_LOG_S, log=log)
        self._lock = threading.Lock()
        self._next_s = -math.inf
        """When the next write may be made."""
        self._held: float | None = None
        """The newest value heard too soon, for the end of the interval."""
        self._closed = False
        self._run_worker = worker
        self._worker: PeriodicWorker | None = None
        source = f"{topic}{names.PRIORITY_SUFFIX}"
        transport.set_topic_type(source, self._codec.msg_type)
        self._subscription: Handle = transport.subscribe(source, self._on_sample)

    def _on_sample(self, sample: Sample) -> None:
        """A message on the priority topic (the middleware's thread): checked, then offered."""
        try:
            heard = self._codec.decode(sample.payload)
        except TransportError as err:
            self._bad.warning(
                self._name, "%s: ignoring an undecodable priority: %s", self._name, err
            )
            return
        try:
            value = float(PRIORITY.check(heard, name=self._name))
        except ParamError as err:
            self._bad.warning(self._name, "ignoring a priority: %s", err)
            return
        self.offer(value)

    def offer(self, value: float) -> None:
        """A valid priority: written now, or held until the interval since the last one ends."""
        with self._lock:
            if self._closed:
                return
            now = self._clock()
            due = now >= self._next_s
            if due:
                self._next_s = now + self.interval_s
                self._held = None
                worker = None
            else:
                self._held = value
                worker = self._worker_locked()
        if due:
            self._write(value)
        elif worker is not None:
            worker.wake()

    def tick(self) -> bool:
        """Write the value held, if its interval is over; True if one was written.

        The worker's step; public so a test with a manual clock drives it.
        """
        with self._lock:
            now = self._clock()
            if self._held is None or now < self._next_s:
                return False
            value, self._held = self._held, None
            self._next_s = now + self.interval_s
        self._write(value)
        return True

    def _write(self, value: float) -> None:
        if self._params.get(self._name) != value:  # the same again is no change to announce
            self._params.set(self._name, value)

    def _wait_s(self) -> float:
        """How long the worker may sleep: until the held value is due, else long."""
        with self._lock:
            if self._held is None:
                return _IDLE_S
            return max(0.0, self._next_s - self._clock())

    def _worker_locked(self) -> PeriodicWorker | None:
        """The flood's worker, started the first time a value is held (None: not run)."""
        if self._worker is None and self._run_worker:
            self._worker = PeriodicWorker(
                self.tick,
                interval_s=self._wait_s,
                name=f"dbml-priority {self.topic}",
                log=log,
                clock=self._clock,
            ).start()
        return self._worker

    @property
    def alive(self) -> bool:
        """False once the worker thread died."""
        return self._worker is None or self._worker.alive

    def close(self) -> None:
        """Stop hearing the topic; a value still held is dropped."""
        with self._lock:
            self._closed = True
            self._held = None
            worker, self._worker = self._worker, None
        self._subscription.close()
        if worker is not None:
            worker.stop()
