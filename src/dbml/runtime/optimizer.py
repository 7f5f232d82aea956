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
from dataclasses import dataclass, replace

from dbml.core.allocation import Allocation, Status, Strategy, allocate
from dbml.core.config import DbmSettings
from dbml.core.errors import DbmlError
from dbml.core.spec import LinkSpec, Problem
from dbml.runtime import names
from dbml.runtime.graph import is_managed, published_topics
from dbml.runtime.params import (
    ChannelParams,
    DbmParams,
    ParamView,
    channel_params,
    write_settings,
)
from dbml.runtime.worker import PeriodicWorker
from dbml.transports.base import Handle, ParamValue, Transport

__all__ = ["ChannelState", "OptimizerNode", "Round"]

log = logging.getLogger("dbml.optimizer")

_TRIGGERS = frozenset({names.MIN_FIELD, names.MAX_FIELD, names.SIZE_FIELD, names.PRIORITY_FIELD})
"""Channel parameters whose change re-allocates at once."""
_GLOBAL_TRIGGERS = frozenset({names.BANDWIDTH, names.UTILIZATION, names.PERIOD, names.STRATEGY})
_DEFAULTS: dict[str, ParamValue] = {
    names.UTILIZATION: DbmParams().utilization,
    names.PERIOD: DbmParams().period_s,
    names.STRATEGY: DbmParams().strategy.value,
}
"""What ``write_defaults`` writes: ``DbmParams``'s own defaults."""
ACK_TIMEOUT_S = 0.25
"""How long increases wait for publishers to acknowledge the decreases pushed before them."""
COALESCE_S = 0.002
"""Triggers within this time of the first run one round."""


@dataclass(frozen=True, slots=True)
class ChannelState:
    """A live channel as the optimizer sees it: its parameters and whether it is managed."""

    params: ChannelParams
    managed: bool

    @property
    def topic(self) -> str:
        """The channel's topic."""
        return self.params.topic


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

    ``budget_mbit`` is the hook a bandwidth estimator uses: when it returns a number, that is the
    estimate, the usable budget in place of bandwidth times utilization. With ``write_defaults``
    the defaults of unset parameters (utilization 1, period 1 s) are written, so ``rosparam get``
    shows every one; only for stores whose reads are complete at start (ROS's).
    """

    def __init__(
        self,
        transport: Transport,
        *,
        settings: DbmSettings | None = None,
        links: Iterable[LinkSpec] = (),
        ack_timeout_s: float = ACK_TIMEOUT_S,
        coalesce_s: float = COALESCE_S,
        budget_mbit: Callable[[], float | None] | None = None,
        write_defaults: bool = False,
    ) -> None:
        self._transport = transport
        self._links = tuple(links)
        self._ack_timeout_s = ack_timeout_s
        self._estimate = budget_mbit
        self._pushed: dict[str, float] = {}
        self._managed: dict[str, bool] = {}
        self._status: tuple[str, str] | None = None
        self._acks = threading.Condition()
        self.last_round: Round | None = None
        params = transport.params
        if settings is not None:
            write_settings(params, settings)
        elif write_defaults:
            for name, default in _DEFAULTS.items():
                if params.get(name) is None:
                    params.set(name, default)
        self._view = ParamView.of(params)
        self._worker = PeriodicWorker(
            self._round,
            interval_s=lambda: self._view.dbm().period_s,
            name="dbml-optimizer",
            log=log,
            coalesce_s=coalesce_s,
            immediate=True,
            clock=transport.now,
        )
        self._handles: list[Handle] = [
            self._view.watch(self._on_param),
            transport.graph.watch(self.poke),
        ]

    def _round(self) -> None:
        self.optimize()  # looked up per round, so a wrapped ``optimize`` is the one that runs

    # -- triggers -----------------------------------------------------------------------------

    def poke(self) -> None:
        """Ask for a re-optimisation as soon as possible (bursts coalesce into one)."""
        self._worker.wake()

    def _on_param(self, name: str, _value: ParamValue) -> None:
        """A valid value arrived (the view has it already): react to what it changes."""
        if name in _GLOBAL_TRIGGERS:
            self.poke()
            return
        split = names.topic_of(name)
        if split is None:
            return
        if split[1] in _TRIGGERS:
            self.poke()
        elif split[1] == names.APPLIED_FIELD:
            with self._acks:
                self._acks.notify_all()

    # -- reading the world --------------------------------------------------------------------

    def dbm(self) -> DbmParams:
        """The ``/dbm/...`` parameters in force, with this node's own estimate when it runs one.

        An estimate in the store is for readers such as the monitor: the budget follows only the
        estimator this node was given, never a value any peer can write.
        """
        estimate = None if self._estimate is None else self._estimate()
        return replace(self._view.dbm(), estimate_mbit=estimate)

    def period_s(self) -> float:
        """The optimisation period in force."""
        return self._view.dbm().period_s

    def strategy(self) -> Strategy:
        """The allocation strategy in force."""
        return self._view.dbm().strategy

    def budget_mbit(self) -> float | None:
        """What may be allocated: the estimate, else bandwidth times utilization."""
        return self.dbm().budget_mbit

    def channels(self) -> tuple[ChannelState, ...]:
        """Every live channel whose publisher declared valid bounds, by topic."""
        entries = self._transport.graph.entries()
        values = self._view.values()  # one copy for the round, not one per channel
        states = []
        for topic in sorted(published_topics(entries)):
            params = channel_params(values, topic)
            if params.bounded:  # else a publisher that has not declared valid bounds yet
                states.append(ChannelState(params, is_managed(entries, topic)))
        return tuple(states)

    # -- one round ----------------------------------------------------------------------------

    def _allocate(
        self, managed: list[ChannelParams], dbm: DbmParams
    ) -> tuple[dict[str, float], Status, str, Allocation | None]:
        if not managed:
            return {}, Status.OPTIMAL, "no managed channels", None
        floors = {c.topic: c.floor_hz for c in managed}
        budget = dbm.link_and_utilization()
        if budget is None:
            return floors, Status.INFEASIBLE, f"no budget: set {names.BANDWIDTH}", None
        specs = [spec for c in managed if (spec := c.spec()) is not None]
        # Channels that have not sent a message yet have no size: they stay at their minimum.
        rates = {t: r for t, r in floors.items() if t not in {s.topic for s in specs}}
        if not specs:
            return rates, Status.OPTIMAL, "waiting for the first message sizes", None
        topics = {s.topic for s in specs}
        links = tuple(
            LinkSpec(link.name, link.capacity_mbit, kept)
            for link in self._links
            if (kept := tuple(t for t in link.topics if t in topics))
        )
        if links and dbm.strategy is not Strategy.LP:
            log.error("links are configured but strategy is %s; links ignored", dbm.strategy.value)
            links = ()
        problem = Problem(
            tuple(specs), bandwidth_mbit=budget[0], utilization=budget[1], links=links
        )
        allocation = allocate(problem, strategy=dbm.strategy)
        rates.update(allocation.rates_by_topic())
        return rates, allocation.status, allocation.message, allocation

    def optimize(self) -> Round:
        """Read, allocate and push once."""
        channels = self.channels()
        dbm = self.dbm()
        managed = [c.params for c in channels if c.managed]
        try:
            rates, status, message, allocation = self._allocate(managed, dbm)
        except DbmlError as err:
            # A bad combination of good values: keep every managed channel at its minimum.
            rates = {c.topic: c.floor_hz for c in managed}
            status, message, allocation = Status.INFEASIBLE, str(err), None
        for channel in channels:
            if not channel.managed and channel.params.max_rate_hz is not None:
                rates[channel.topic] = channel.params.max_rate_hz
        problems = self._view.problems()
        if problems:
            message = f"{message}; ignored: {'; '.join(problems)}"
        self._report_managed(channels)
        self._push(rates)
        self._report_status(status, message)
        result = Round(channels, rates, status, message, dbm.budget_mbit, allocation)
        self.last_round = result
        return result

    def _push(self, rates: dict[str, float]) -> None:
        params = self._transport.params

        def running(topic: str) -> float | None:
            """What the publisher acknowledged running, else what we last pushed."""
            applied = self._applied_hz(topic)
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
        self._pushed = dict(rates)

    def _applied_hz(self, topic: str) -> float | None:
        """The rate the publisher acknowledged (validated by the view)."""
        value = self._view.get(names.applied(topic))
        return value if isinstance(value, float) else None

    def _await_acks(self, decreases: dict[str, float]) -> None:
        """Wait until publishers apply the decreases (bounded), so increases come after them."""

        def late() -> list[str]:
            return sorted(t for t, r in decreases.items() if self._applied_hz(t) != r)

        with self._acks:
            if not self._acks.wait_for(lambda: not late(), timeout=self._ack_timeout_s):
                log.warning(
                    "no acknowledgement of a decrease from %s; raising others anyway", late()
                )

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

    def start(self) -> OptimizerNode:
        """Optimise now, then every period and on every trigger, until ``stop()``."""
        self._worker.start()
        return self

    def stop(self) -> None:
        """Stop the loop and stop following the store and the graph."""
        self._worker.stop()
        for handle in self._handles:
            handle.close()
        self._handles.clear()
