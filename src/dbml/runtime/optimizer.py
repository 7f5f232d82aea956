"""The optimizer node (the paper's DBMOptimizer and default optimizer node).

It reads channels, priorities, sizes and the budget from the parameter store and the live graph,
allocates, and pushes each publisher its rate through ``[topic]/dbm/frequency/current_value``:

- every ``/dbm/optimization_rate_in_seconds`` (which doubles as the publishers' heartbeat), and
- at once when a priority, a size, a bound, the budget or the graph changes, coalescing bursts.

Only channels with a subscriber to ``[topic]/optimized`` on another host are managed; the others
run at their maximum. Decreases are pushed first and acknowledged before increases go out, so the
budget is not exceeded while rates change. Infeasibility is logged and written to ``/dbm/status``
and ``/dbm/status_message``, with rates that still fit the budget.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from dbml.core.allocation import Allocation, Status, Strategy, allocate
from dbml.core.config import DbmSettings
from dbml.core.errors import DbmlError
from dbml.core.spec import ChannelSpec, LinkSpec, Problem
from dbml.runtime import names
from dbml.runtime.graph import is_managed, published_topics, publisher_hosts
from dbml.transports.base import Handle, ParamValue, Transport, param_number

__all__ = ["ChannelState", "OptimizerNode", "Round"]

log = logging.getLogger("dbml.optimizer")

_TRIGGERS = frozenset({"frequency/min", "frequency/max", "message_size_in_bytes", "priority"})
_DEFAULTS: dict[str, ParamValue] = {
    names.UTILIZATION: 1.0,
    names.PERIOD: 1.0,
    names.STRATEGY: Strategy.PAPER.value,
}
_GLOBAL_TRIGGERS = frozenset({names.BANDWIDTH, names.UTILIZATION, names.PERIOD, names.STRATEGY})


@dataclass(frozen=True, slots=True)
class ChannelState:
    """A live channel as the optimizer sees it."""

    topic: str
    host: str
    min_rate_hz: float
    max_rate_hz: float
    size_bytes: float | None
    priority: float
    managed: bool


@dataclass(frozen=True, slots=True)
class Round:
    """The outcome of one optimisation: the rate pushed to every live channel."""

    channels: tuple[ChannelState, ...]
    rates_hz: dict[str, float]
    status: Status
    message: str
    budget_mbit: float | None
    """What was allocatable: the estimate, else bandwidth times utilization."""
    allocation: Allocation | None


class OptimizerNode:
    """Allocate and push rates; ``start()`` runs it in a thread, ``optimize()`` runs one round.

    ``budget_mbit`` overrides ``/dbm/max_bandwidth_in_mbit`` (and its utilization) when it returns
    a number: the hook a bandwidth estimator uses; its value is the usable budget. With
    ``write_defaults`` the defaults of unset parameters (utilization 1, period 1 s) are written, so
    ``rosparam get`` shows every one; only for stores whose reads are complete at start (ROS's).
    """

    def __init__(
        self,
        transport: Transport,
        *,
        settings: DbmSettings | None = None,
        links: Iterable[LinkSpec] = (),
        ack_timeout_s: float = 0.25,
        coalesce_s: float = 0.002,
        budget_mbit: Callable[[], float | None] | None = None,
        write_defaults: bool = False,
    ) -> None:
        self._transport = transport
        self._links = tuple(links)
        self._ack_timeout_s = ack_timeout_s
        self._coalesce_s = coalesce_s
        self._budget_override = budget_mbit
        self._pushed: dict[str, float] = {}
        self._managed: dict[str, bool] = {}
        self._status: tuple[str, str] | None = None
        self._acks = threading.Condition()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_round: Round | None = None
        if settings is not None:
            params = transport.params
            params.set(names.BANDWIDTH, settings.max_bandwidth_mbit)
            params.set(names.UTILIZATION, settings.utilization)
            params.set(names.PERIOD, settings.optimization_period_s)
            params.set(names.STRATEGY, settings.strategy.value)
        elif write_defaults:
            for name, default in _DEFAULTS.items():
                if transport.params.get(name) is None:
                    transport.params.set(name, default)
        self._handles: list[Handle] = [
            transport.params.watch(self._on_param),
            transport.graph.watch(self.poke),
        ]

    # -- triggers -----------------------------------------------------------------------------

    def poke(self) -> None:
        """Ask for a re-optimisation as soon as possible (bursts coalesce into one)."""
        self._wake.set()

    def _on_param(self, name: str, _value: ParamValue) -> None:
        if name in _GLOBAL_TRIGGERS:
            self.poke()
            return
        split = names.topic_of(name)
        if split is None:
            return
        _, field = split
        if field in _TRIGGERS:
            self.poke()
        elif field == "frequency/applied_value":
            with self._acks:
                self._acks.notify_all()

    # -- reading the world --------------------------------------------------------------------

    def period_s(self) -> float:
        period = param_number(self._transport.params.get(names.PERIOD))
        return period if period is not None and period > 0 else 1.0

    def strategy(self) -> Strategy:
        raw = self._transport.params.get(names.STRATEGY)
        try:
            return Strategy(raw) if isinstance(raw, str) else Strategy.PAPER
        except ValueError:
            log.error("%s=%r is not a strategy; using paper", names.STRATEGY, raw)
            return Strategy.PAPER

    def _budget(self) -> tuple[float, float] | None:
        """(Mbit/s, utilization) to allocate: an estimate is already the usable budget."""
        if self._budget_override is not None:
            estimate = self._budget_override()
            if estimate is not None:
                return estimate, 1.0
        value = param_number(self._transport.params.get(names.BANDWIDTH))
        if value is None or value <= 0:
            return None
        return value, param_number(self._transport.params.get(names.UTILIZATION)) or 1.0

    def budget_mbit(self) -> float | None:
        """What may be allocated: the estimate, else bandwidth times utilization."""
        budget = self._budget()
        return None if budget is None else budget[0] * budget[1]

    def channels(self) -> tuple[ChannelState, ...]:
        entries = self._transport.graph.entries()
        params = self._transport.params.snapshot()
        states = []
        for topic in sorted(published_topics(entries)):
            low = param_number(params.get(names.min_rate(topic)))
            high = param_number(params.get(names.max_rate(topic)))
            if low is None or high is None or not 0 < low <= high:
                continue  # a publisher that has not declared valid bounds yet
            size = param_number(params.get(names.size(topic)))
            priority = param_number(params.get(names.priority(topic))) or 0.0
            states.append(
                ChannelState(
                    topic=topic,
                    host=min(publisher_hosts(entries, topic)),
                    min_rate_hz=low,
                    max_rate_hz=high,
                    size_bytes=size if size is not None and size > 0 else None,
                    priority=min(1.0, max(0.0, priority)),
                    managed=is_managed(entries, topic),
                )
            )
        return tuple(states)

    # -- one round ----------------------------------------------------------------------------

    def _allocate(
        self, managed: list[ChannelState], budget: tuple[float, float] | None
    ) -> tuple[dict[str, float], Status, str, Allocation | None]:
        if not managed:
            return {}, Status.OPTIMAL, "no managed channels", None
        if budget is None:
            rates = {c.topic: c.min_rate_hz for c in managed}
            return rates, Status.INFEASIBLE, f"no budget: set {names.BANDWIDTH}", None
        sized = [c for c in managed if c.size_bytes is not None]
        # Channels that have not sent a message yet have no size: they stay at their minimum.
        rates = {c.topic: c.min_rate_hz for c in managed if c.size_bytes is None}
        if not sized:
            return rates, Status.OPTIMAL, "waiting for the first message sizes", None
        strategy = self.strategy()
        topics = {c.topic for c in sized}
        links = tuple(
            LinkSpec(link.name, link.capacity_mbit, kept)
            for link in self._links
            if (kept := tuple(t for t in link.topics if t in topics))
        )
        if links and strategy is not Strategy.LP:
            log.error("links are configured but strategy is %s; links ignored", strategy.value)
            links = ()
        problem = Problem(
            channels=tuple(
                ChannelSpec(c.topic, c.min_rate_hz, c.max_rate_hz, c.size_bytes or 1.0, c.priority)
                for c in sized
            ),
            bandwidth_mbit=budget[0],
            utilization=budget[1],
            links=links,
        )
        allocation = allocate(problem, strategy=strategy)
        rates.update(allocation.rates_by_topic())
        return rates, allocation.status, allocation.message, allocation

    def optimize(self) -> Round:
        """Read, allocate and push once."""
        channels = self.channels()
        budget = self._budget()
        managed = [c for c in channels if c.managed]
        try:
            rates, status, message, allocation = self._allocate(managed, budget)
        except DbmlError as err:
            # e.g. a utilization parameter out of range: keep every managed channel at its min.
            rates = {c.topic: c.min_rate_hz for c in managed}
            status, message, allocation = Status.INFEASIBLE, str(err), None
        for channel in channels:
            if not channel.managed:
                rates[channel.topic] = channel.max_rate_hz
        self._report_managed(channels)
        self._push(rates)
        self._report_status(status, message)
        usable = None if budget is None else budget[0] * budget[1]
        result = Round(channels, rates, status, message, usable, allocation)
        self.last_round = result
        return result

    def _push(self, rates: dict[str, float]) -> None:
        params = self._transport.params

        def running(topic: str) -> float | None:
            """What the publisher acknowledged running, else what we last pushed."""
            applied = param_number(params.get(names.applied(topic)))
            return applied if applied is not None else self._pushed.get(topic)

        before = {t: running(t) for t in rates}
        decreases = {t: r for t, r in rates.items() if (b := before[t]) is None or r < b}
        for topic, rate in decreases.items():
            params.set(names.current_value(topic), rate)
        if decreases and any((b := before[t]) is not None and r > b for t, r in rates.items()):
            self._await_acks(decreases)
        for topic, rate in rates.items():
            if topic not in decreases:
                params.set(names.current_value(topic), rate)  # also the periodic heartbeat
        self._pushed = {t: rates[t] for t in rates}

    def _await_acks(self, decreases: dict[str, float]) -> None:
        """Wait until publishers apply the decreases (bounded), so increases come after them."""
        params = self._transport.params

        def applied() -> bool:
            return all(params.get(names.applied(t)) == r for t, r in decreases.items())

        with self._acks:
            if not self._acks.wait_for(applied, timeout=self._ack_timeout_s):
                late = sorted(t for t, r in decreases.items() if params.get(names.applied(t)) != r)
                log.warning("no acknowledgement of a decrease from %s; raising others anyway", late)

    def _report_managed(self, channels: tuple[ChannelState, ...]) -> None:
        for channel in channels:
            if self._managed.get(channel.topic) != channel.managed:
                self._managed[channel.topic] = channel.managed
                self._transport.params.set(names.managed(channel.topic), channel.managed)

    def _report_status(self, status: Status, message: str) -> None:
        params = self._transport.params
        if self._status != (status.value, message):
            self._status = (status.value, message)
            params.set(names.STATUS, status.value)
            params.set(names.STATUS_MESSAGE, message)
            if status is Status.INFEASIBLE:
                log.warning("infeasible: %s", message)
            else:
                log.info("%s", message)

    # -- the loop -----------------------------------------------------------------------------

    def run(self) -> None:
        """Optimise every period and on every trigger until ``stop()``."""
        now = self._transport.now
        next_round = now()
        while not self._stop.is_set():
            triggered = self._wake.wait(timeout=max(0.0, next_round - now()))
            if self._stop.is_set():
                break
            if triggered:
                self._stop.wait(self._coalesce_s)
            self._wake.clear()
            try:
                self.optimize()
            except Exception:  # keep the node alive; the next trigger retries
                log.exception("optimisation round failed")
            next_round = now() + self.period_s()

    def start(self) -> OptimizerNode:
        self._thread = threading.Thread(target=self.run, name="dbml-optimizer", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for handle in self._handles:
            handle.close()
        self._handles.clear()
