"""The managed publisher (the paper's DBMPublisher).

Every message goes to ``[topic]`` for local consumers (only when someone subscribes there) and,
throttled to the allocated rate, to ``[topic]/optimized`` for remote ones. The allocated rate is
pushed by the optimizer through ``[topic]/dbm/frequency/current_value``; the publisher applies it,
acknowledges it in ``[topic]/dbm/frequency/applied_value`` and never polls. A new channel runs at
its minimum until allocated; hearing no allocation for ``failsafe_periods`` optimisation periods
sends it back to its minimum (fail-safe), and the next allocation takes over again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from dbml.core.errors import SpecError
from dbml.core.spec import ChannelSpec
from dbml.runtime import names
from dbml.runtime.metadata import pack_meta
from dbml.runtime.rate import Rate, RateLimiter
from dbml.transports.base import (
    Handle,
    ParamValue,
    Role,
    Transport,
    Variant,
    check_topic,
    param_number,
)

__all__ = ["ManagedPublisher"]

log = logging.getLogger("dbml.publisher")

SIZE_CHANGE = 0.10
"""Relative change of message size that is worth telling the optimizer about."""


class ManagedPublisher:
    """Publish on ``topic`` at the rate the optimizer allocates, between ``min_rate_hz`` and
    ``max_rate_hz``.

    ``publish(payload)`` drops what exceeds the rate; ``rate.sleep()`` paces a sensor loop so it
    does not even capture what would be dropped. Call ``publish`` from one thread; allocations
    arrive on the transport's thread. The per-message path reads only cached values: the rate
    in force and the fail-safe deadline are recomputed when an allocation or the period arrives.
    """

    def __init__(
        self,
        transport: Transport,
        topic: str,
        *,
        min_rate_hz: float,
        max_rate_hz: float,
        priority: float | None = None,
        failsafe_periods: float = 3.0,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        check_topic(topic)
        # Validates the bounds with the same rules and messages as the allocation core.
        ChannelSpec(topic, min_rate_hz, max_rate_hz, 1.0, 0.0 if priority is None else priority)
        if failsafe_periods <= 0:
            raise SpecError(f"failsafe_periods={failsafe_periods!r} must be > 0")
        self.topic = topic
        self.min_rate_hz = float(min_rate_hz)
        self.max_rate_hz = float(max_rate_hz)
        self._transport = transport
        self._now = transport.now
        self._failsafe_periods = failsafe_periods
        self._wall_clock_ns = wall_clock_ns
        self._lock = threading.Lock()
        self._full_seq = 0
        self._optimized_seq = 0
        self._size_bytes = -1
        self._allocated_hz: float | None = None
        self._rate_hz = self.min_rate_hz  # in force: the allocation, else the minimum
        self._last_heard = transport.now()
        self._period_s = param_number(transport.params.get(names.PERIOD)) or 1.0
        self._deadline = self._last_heard + failsafe_periods * self._period_s
        self._failsafe = False
        self._limiter = RateLimiter(self.min_rate_hz)
        self.rate = Rate(self.current_rate_hz, clock=transport.now)

        params = transport.params
        self._handles: list[Handle] = [params.watch(self._on_param)]
        params.set(names.min_rate(topic), self.min_rate_hz)
        params.set(names.max_rate(topic), self.max_rate_hz)
        if priority is not None:  # otherwise keep what was set (the optimizer reads none as 0)
            params.set(names.priority(topic), float(priority))
        self._full = transport.declare_publisher(topic, Variant.FULL)
        self._optimized = transport.declare_publisher(topic, Variant.OPTIMIZED)
        self._handles.append(transport.graph.announce(Role.PUBLISHER, topic, Variant.FULL))

    # -- allocation ---------------------------------------------------------------------------

    def _on_param(self, name: str, value: ParamValue) -> None:
        if name == names.PERIOD:
            period = param_number(value)
            if period is not None and period > 0:
                with self._lock:
                    self._period_s = period
                    self._deadline = self._last_heard + self._failsafe_periods * period
            return
        if name != names.current_value(self.topic):
            return
        rate = param_number(value)
        if rate is None or rate <= 0:
            return
        with self._lock:
            self._last_heard = self._transport.now()
            self._deadline = self._last_heard + self._failsafe_periods * self._period_s
            if self._failsafe:
                log.warning("%s: allocation heard again; running at %.3f Hz", self.topic, rate)
                self._failsafe = False
            changed = rate != self._allocated_hz
            self._allocated_hz = rate
            self._rate_hz = rate
            self._limiter.set_rate(rate)
        if changed:
            self._transport.params.set(names.applied(self.topic), rate)

    def _enter_failsafe(self, now: float) -> None:
        with self._lock:
            if self._failsafe or now <= self._deadline:
                return
            self._failsafe = True
            log.warning(
                "%s: no allocation heard for %.1f s (%g periods); fail-safe: minimum %.3f Hz",
                self.topic,
                now - self._last_heard,
                self._failsafe_periods,
                self.min_rate_hz,
            )
            self._allocated_hz = None
            self._rate_hz = self.min_rate_hz
            self._limiter.set_rate(self.min_rate_hz)

    def current_rate_hz(self) -> float:
        """The rate in force: the allocation, or the minimum before one and in fail-safe."""
        if self._now() > self._deadline:
            self._enter_failsafe(self._now())
        return self._rate_hz

    @property
    def failsafe(self) -> bool:
        self.current_rate_hz()
        return self._failsafe

    # -- publishing ---------------------------------------------------------------------------

    def _track_size(self, size: int) -> None:
        # The serialised message, as sent; metadata and protocol headers are the overhead that
        # /dbm/max_bandwidth_utilization < 1 reserves room for.
        known = self._size_bytes
        if known < 0 or abs(size - known) > SIZE_CHANGE * known:
            self._size_bytes = size
            self._transport.params.set(names.size(self.topic), size)

    def publish(self, payload: bytes) -> bool:
        """Send ``payload``; True if it went to ``[topic]/optimized`` (within the rate).

        Each variant numbers its own messages, so a receiver's sequence gaps are losses, never
        the throttling.
        """
        now = self._now()
        if now > self._deadline:
            self._enter_failsafe(now)
        if len(payload) != self._size_bytes:
            self._track_size(len(payload))
        sent_ns = self._wall_clock_ns()
        if self._full.has_subscribers:
            self._full_seq += 1
            self._full.put(payload, pack_meta(self._full_seq, sent_ns, self._rate_hz))
        if not self._limiter.allow(now):
            return False
        self._optimized_seq += 1
        self._optimized.put(payload, pack_meta(self._optimized_seq, sent_ns, self._rate_hz))
        return True

    def close(self) -> None:
        for handle in self._handles:
            handle.close()
        self._handles.clear()
        self._full.close()
        self._optimized.close()
