"""The optimizer node (the paper's DBMOptimizer and default optimizer node).

It reads channels, priorities, sizes and the budget from the parameter store and the live graph,
allocates, and pushes each publisher its rate through ``[topic]/dbm/frequency/current_value``:

- every ``/dbm/optimization_rate_in_seconds``, and
- at once when a priority, a size, a bound, the budget or the graph changes, coalescing bursts.

A round pushes only what changed: rates, ``managed`` flags, the status, and ``/dbm/round``, the
heartbeat that tells publishers their rate still stands. Then it says what it decided, whole, in
a ``RoundReport`` on ``/dbm/optimizer/round`` (when anyone listens): the live view and ``dbml
monitor`` show that, and never allocate themselves. When some rates go down and others up,
the decreases go first and each increase goes once it fits beside what the others may still be
sending (``dbml.runtime.ledger``: a decrease counts until acknowledged and drained, or
``ACK_TIMEOUT_S`` passed), so the budget is not exceeded while rates change, and no round waits
for the slowest publisher: an increase that does not fit yet goes when an acknowledgement
frees its room.
Each write is one message where the middleware allows (zenoh's batch), one write per name over
ROS 1. A rate is pushed again when its channel's publishers change (a restarted publisher heard
nothing). Only channels with a subscriber to ``[topic]/optimized`` on another host are managed;
the others run at their maximum. Infeasibility is logged and written to ``/dbm/status``
and ``/dbm/status_message``, with rates that still fit the budget.

It tracks at most ``MAX_CHANNELS`` channels, so what it remembers per channel is bounded however
many topics the graph shows; the channels past it are ignored, said in the status message.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import TypeAlias

from dbml.core.allocation import Allocation, Status, Strategy, allocate
from dbml.core.config import DbmSettings
from dbml.core.errors import DbmlError
from dbml.core.ladder import Ladder
from dbml.core.quality import QualityAllocation, QualityStatus, allocate_quality
from dbml.core.spec import LinkSpec, Problem, mbit_to_bytes_per_s, short_repr
from dbml.protocol import keys, names, schema
from dbml.protocol.keys import ROUND_TOPIC
from dbml.protocol.ladders import Encoding, encoding_label, parse_rung_label
from dbml.protocol.messages import MAX_REPORTED_CHANNELS, ChannelRound, RoundReport
from dbml.protocol.schema import Parameter
from dbml.runtime.graph import GraphSummary, summarize
from dbml.runtime.ledger import Limit, RateLedger
from dbml.runtime.params import ChannelParams, DbmParams, ParamView, write_settings
from dbml.runtime.rate import same_rate
from dbml.runtime.worker import PeriodicWorker
from dbml.transports.base import (
    GraphEntry,
    Handle,
    ParamValue,
    Role,
    Transport,
    TransportPriority,
)
from dbml.transports.overflow import Overflow

__all__ = ["MAX_CHANNELS", "REPORT_INTERVAL_S", "ChannelState", "OptimizerNode", "Round"]

log = logging.getLogger("dbml.optimizer")

_TRIGGERS = frozenset(
    {
        schema.MIN_RATE,
        schema.MAX_RATE,
        schema.SIZE,
        schema.PRIORITY,
        schema.BANDWIDTH,
        schema.UTILIZATION,
        schema.PERIOD,
        schema.STRATEGY,
        schema.FRAME_HEADROOM,
        schema.LADDER,
        schema.PREFERENCE,
        schema.MIN_QUALITY,
    }
)
"""Parameters whose change re-allocates at once: a channel's inputs, the budget, the rules."""
_ACKS = frozenset({schema.APPLIED, schema.ENCODING_APPLIED})
"""A publisher's acknowledgements: one may free room for an increase waiting."""
_DEFAULTS: dict[str, ParamValue] = {
    names.UTILIZATION: DbmParams().utilization,
    names.PERIOD: DbmParams().period_s,
    names.STRATEGY: DbmParams().strategy.value,
}
"""What ``write_defaults`` writes: ``DbmParams``'s own defaults."""
ACK_TIMEOUT_S = 0.25
"""How long an unacknowledged decrease counts at its rate before it (increases wait for room)."""
QUEUED_FRAMES = 1.0
"""Frames a decreased publisher may have on the way when its acknowledgement arrives: the
ledger drains them at the budget's rate before their room goes to an increase."""
STEP_SHARE = 0.5
"""A rise that does not fit yet goes part of the way, once, when the room made covers this share
of it (and its minimum): a channel raised at the cost of many others then moves when most of
their cuts are applied, not when the slowest is; the rest follows when it fits."""
BEAT_SPACING = 0.5
"""A triggered round writes the heartbeat only once this share of a period has passed since the
last one; a periodic round always does. The heartbeat goes to every robot, and each robot's
publishers wake for it: a burst of changes (a fleet joining, priorities moving) would otherwise
wake the whole fleet on every round it brings, a cost per change that grows with the fleet. The
publishers' fail-safe waits ``FAILSAFE_PERIODS`` (3) periods; the heartbeats stay at most 1.5
apart."""
COALESCE_S = 0.002
"""Triggers within this time of the first run one round."""
REPORT_INTERVAL_S = 0.1
"""Round reports (telemetry, not control: views and monitors read them, maybe over the radio)
go at most this often; a burst of triggered rounds is reported by its last one but at most one
period later. A report costs about 300 bytes a channel."""
MAX_CHANNELS = MAX_REPORTED_CHANNELS
"""The most channels (published topics) the optimizer tracks: what it remembers per channel
(rates pushed, publishers asked again) and each round's allocation grow with them. A fleet of
160 robots with 4 channels has 640, six times less. Any peer can announce publishers, so past
this the channels tracked already stay, the new ones are ignored (pushed nothing), logged once
per flood with a count (an ``Overflow``: the flood is over once the channels fall to half the
bound) and named by count in ``/dbm/status_message`` every round."""


_Writes: TypeAlias = dict[str | None, dict[str, ParamValue]]
"""Writes by the channel whose names they are (None: global ones): addressed with no parse."""
_Wanted: TypeAlias = tuple[float | None, str | None]
"""A channel's rate and its rung's label (None: no ladder) as pushed or acknowledged."""


def _writes(topic: str, wanted: _Wanted) -> dict[str, ParamValue]:
    rate, label = wanted
    values: dict[str, ParamValue] = {names.current_value(topic): rate}
    if label is not None:
        values[names.encoding(topic)] = label
    return values


def _frame_bytes(channel: ChannelParams, label: str | None) -> float:
    """The bytes a frame of ``channel`` counts at: its rung's, else its size."""
    if label is not None and channel.rungs is not None:
        return _rung_bytes(channel, label)
    return channel.size_bytes or 0.0


def _bytes_per_s(channel: ChannelParams, wanted: _Wanted) -> float:
    """What ``wanted`` (a rate and a rung) sends a second (nothing without a rate)."""
    rate, label = wanted
    return 0.0 if rate is None else rate * _frame_bytes(channel, label)


def _rung_bytes(channel: ChannelParams, label: str) -> float:
    """The bytes a frame of the rung ``label`` names: as counted in it, else by the ladder."""
    encoding, counted = parse_rung_label(label)
    if counted is not None:
        return counted
    for rung in channel.rungs or ():
        if (rung.scale, rung.jpeg_quality) == encoding:
            return rung.size_bytes
    return channel.size_bytes or 0.0


@dataclass(frozen=True, slots=True)
class ChannelState:
    """A live channel as the optimizer sees it: its parameters and whether it is managed."""

    params: ChannelParams
    managed: bool
    publishers: frozenset[str] = frozenset()
    """The channel's publisher declarations: when they change, its rate is pushed again."""
    hosts: frozenset[str] = frozenset()
    """The hosts its publishers run on: its values go in their batches."""

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
    strategy: Strategy = Strategy.PAPER
    number: int = 0
    """The round's counter, as ``/dbm/round`` carries it."""
    encodings: Mapping[str, Encoding] = field(default_factory=dict)
    """The rung pushed to each laddered channel."""
    quality: QualityAllocation | None = None
    """The rate-and-quality allocation, when a managed channel carries a ladder."""

    def report(self) -> RoundReport:
        """The round as the optimizer says it on the wire: every live channel, floors included."""
        allocation = self.allocation or self.quality
        allocated: dict[str, tuple[float, float]] = {}
        if allocation is not None:
            allocated = {
                topic: (float(allocation.normalized_priority[i]), float(allocation.floor_hz[i]))
                for i, topic in enumerate(allocation.topics)
            }
        chosen: dict[str, tuple[float, float]] = {}
        if self.quality is not None:
            quality = self.quality
            chosen = {
                topic: (float(quality.size_bytes[i]), float(quality.quality[i]))
                for i, topic in enumerate(quality.topics)
                if quality.rung[i] >= 0
            }
        budget = None if self.budget_mbit is None else mbit_to_bytes_per_s(self.budget_mbit)
        channels = []
        for state in self.channels:
            params, rate = state.params, self.rates_hz.get(state.topic)
            size, score = chosen.get(state.topic, (params.size_bytes, None))
            encoding = self.encodings.get(state.topic)
            share = None
            if state.managed and budget and rate is not None and size is not None:
                share = rate * size / budget
            normalized, floor = allocated.get(state.topic, (None, None))
            channels.append(
                ChannelRound(
                    topic=state.topic,
                    managed=state.managed,
                    priority=params.priority,
                    min_hz=params.floor_hz,
                    max_hz=params.max_rate_hz or 0.0,
                    size_bytes=size,
                    normalized_priority=normalized,
                    floor_hz=floor,
                    rate_hz=rate,
                    share=share,
                    encoding=None if encoding is None else encoding_label(*encoding),
                    quality=score,
                    sent_hz=params.sent_rate_hz,
                )
            )
        return RoundReport(
            round=self.number,
            status=self.status,
            message=self.message,
            strategy=self.strategy,
            budget_mbit=self.budget_mbit,
            channels=tuple(channels),
        )


@dataclass(frozen=True, slots=True)
class _Waiting:
    """Increases a round could not push yet, and what their admission needs."""

    increases: Mapping[str, _Wanted]
    """In the order they go: the most important first."""
    channels: tuple[ChannelState, ...]
    limits: tuple[Limit, ...]
    stepped: frozenset[str] = frozenset()
    """Those already pushed part of the way: the rest goes only in full."""


@dataclass(frozen=True, slots=True)
class _Outcome:
    """What one round's allocation decided for the managed channels, before it is pushed."""

    status: Status
    message: str
    rates_hz: Mapping[str, float] = field(default_factory=dict)
    """The managed channels' rates; a channel without one is pushed nothing."""
    allocation: Allocation | None = None
    """The allocator's result, when it ran."""
    encodings: Mapping[str, Encoding] = field(default_factory=dict)
    """The laddered channels' rungs."""
    counted_bytes: Mapping[str, float] = field(default_factory=dict)
    """The bytes a frame of each laddered channel may carry: its rung's by the ladder, with the
    budget's room the allocation left shared in proportion (what its camera holds frames to)."""
    quality: QualityAllocation | None = None
    """The rate-and-quality allocation's result, when it ran."""


def _quality_outcome(
    problem: Problem, ladders: Mapping[str, Ladder], price_hint: float | None
) -> _Outcome:
    """A rung and a rate for every channel (``allocate_quality``): the laddered ones' rungs."""
    quality = allocate_quality(problem, ladders, price_hint=price_hint)
    rates = {t: float(r) for t, r in zip(quality.topics, quality.rate_hz, strict=True)}
    encodings: dict[str, Encoding] = {}
    counted: dict[str, float] = {}
    # Rungs are steps, so an allocation may leave part of the budget: a frame may take its share
    # of it (a scene busier than the ladder's word costs frames only when the budget is spent).
    spent = quality.total_bytes_per_s
    room = quality.budget_bytes_per_s / spent if quality.success and spent > 0 else 1.0
    room = max(room, 1.0) if math.isfinite(room) else 1.0
    for i, topic in enumerate(quality.topics):
        ladder = ladders.get(topic)
        if ladder is not None and quality.rung[i] >= 0:
            rung = ladder.rungs[int(quality.rung[i])]
            encodings[topic] = (rung.scale, rung.jpeg_quality)
            counted[topic] = rung.size_bytes * room
    status = Status.OPTIMAL if quality.status is QualityStatus.OPTIMAL else Status.INFEASIBLE
    return _Outcome(status, quality.message, rates, None, encodings, counted, quality)


class OptimizerNode:
    """Allocate and push rates; ``start()`` runs it in a thread, ``optimize()`` runs one round.

    ``budget_mbit`` is the hook a bandwidth estimator uses: when it returns a number, that is the
    estimate, the usable budget in place of bandwidth times utilization. With ``write_defaults``
    the defaults of unset parameters (utilization 1, period 1 s) are written, so ``rosparam get``
    shows every one; only for stores whose reads are complete at start (ROS's). ``on_round``
    sees each round on the optimizer's thread (``/diagnostics`` over rclpy); its failure is
    logged, never the allocation's.
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
        report_interval_s: float = REPORT_INTERVAL_S,
        on_round: Callable[[Round], None] | None = None,
    ) -> None:
        self._transport = transport
        self._on_round = on_round
        self._watcher_failed = False
        self._links = tuple(links)
        self._price_hint: float | None = None
        """The last quality allocation's price: the next one's search starts there."""
        self._report_interval_s = report_interval_s
        self._reported_s = -math.inf
        self._estimate = budget_mbit
        self._pushed: dict[str, tuple[_Wanted, frozenset[str]]] = {}
        self._pushed_at: dict[str, float] = {}
        """When each channel's rate was last pushed: one not acknowledged a period later is
        pushed again."""
        self._owned: dict[str, ParamValue] = {}
        """What this node last wrote of the values it owns (rates, managed flags, status)."""
        self._summary: tuple[frozenset[GraphEntry], GraphSummary] | None = None
        """The graph's entries as last summarized, and their summary."""
        self._rounds = 0
        self._beat = True
        """Whether the next round writes the heartbeat (``_round`` decides; a direct call does)."""
        self._beat_s = -math.inf
        """When the heartbeat was last written."""
        self._incomplete_since: dict[str, float] = {}
        self._asked: dict[str, float] = {}
        """Publishers seen without parameters: since when, and when they were last asked.
        Rebuilt each round from the tracked channels' publishers in the graph."""
        self._tracked: frozenset[str] = frozenset()
        """The channels tracked in the last round (``MAX_CHANNELS`` at most)."""
        self._ignored = 0
        """How many channels the last round ignored, past ``MAX_CHANNELS``."""
        self._channels_full = Overflow("channels tracked", MAX_CHANNELS, log=log)
        self._ledger = RateLedger(ack_timeout_s=ack_timeout_s)
        self._acked_s: dict[str, float] = {}
        """When each channel pushed to was last acknowledged (a drain counts from there)."""
        self._waiting: _Waiting | None = None
        """The last round's increases not pushed yet (on the worker's thread only)."""
        self._poked = threading.Event()
        """A trigger came: the next tick is a round, not only an admission."""
        self._due_s = -math.inf
        """When the next periodic round is due."""
        self.last_round: Round | None = None
        self._active = threading.Event()
        self._active.set()
        self._resumed = threading.Event()
        """Set by ``resume``: the next round pushes every rate again, as a first round would."""
        # Telemetry, not control: it never goes ahead of an allocation on a saturated link.
        self._reports = transport.declare_publisher(
            ROUND_TOPIC, priority=TransportPriority.DATA_LOW
        )
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
            interval_s=self._wait_s,
            name="dbml-optimizer",
            log=log,
            coalesce_s=coalesce_s,
            immediate=True,
            clock=transport.now,
        )
        self._handles: list[Handle] = [
            self._view.watch_params(self._on_param),
            params.watch(self._on_written),
            transport.graph.watch(self.poke),
        ]

    def _wait_s(self) -> float:
        """Until the next tick: the period's round, or a waiting decrease's settling."""
        due = self._due_s
        if self._waiting is not None and (change := self._ledger.next_change_s()) is not None:
            due = min(due, change)
        return max(0.0, due - self._transport.now())

    def _round(self) -> None:
        """A round when one is due or was asked for; else admit what waits for room."""
        now = self._transport.now()
        period_s = self._view.dbm().period_s
        if not self._active.is_set():
            self._waiting = None  # nothing is pushed while paused
            self._due_s = now + period_s
            return
        waiting = self._waiting is not None and not self._poked.is_set()
        if waiting and now < self._due_s:
            self.admit()
            return
        self._poked.clear()
        self._beat = now >= self._due_s or now - self._beat_s >= BEAT_SPACING * period_s
        self._due_s = now + period_s  # a round that raises is retried a period later
        if self._resumed.is_set():
            self._resumed.clear()
            self._pushed = {}
            self._pushed_at = {}
            self._ledger.clear()
            self._waiting = None
        try:
            self.optimize()  # looked up per round, so a wrapped ``optimize`` is the one that runs
        finally:
            self._beat = True
        self._due_s = self._transport.now() + period_s

    # -- pausing (a lifecycle's inactive state) -----------------------------------------------

    @property
    def active(self) -> bool:
        """Whether rounds run (until ``pause``)."""
        return self._active.is_set()

    def pause(self) -> None:
        """Allocate nothing from the next round on: no rate, no status, no heartbeat.

        Without the heartbeat every publisher falls back, ``failsafe_periods`` later, to what it
        does with no optimizer at all. A round under way finishes.
        """
        self._active.clear()

    def resume(self) -> None:
        """Run rounds again, the first one now, pushing every rate as if for the first time."""
        self._resumed.set()
        self._active.set()
        self.poke()

    # -- triggers -----------------------------------------------------------------------------

    def poke(self) -> None:
        """Ask for a re-optimisation as soon as possible (bursts coalesce into one)."""
        self._poked.set()
        self._worker.wake()

    def _on_param(self, parameter: Parameter, topic: str | None, _value: ParamValue) -> None:
        """A valid value arrived (the view has it already): react to what it changes."""
        if parameter in _TRIGGERS:
            self.poke()
        elif parameter in _ACKS and topic is not None and topic in self._pushed_at:
            self._acked_s[topic] = self._transport.now()  # a channel pushed to: bounded
            if self._waiting is not None:
                self._worker.wake()  # an increase may fit now: admitted on the worker's thread

    def _on_written(self, name: str, value: ParamValue) -> None:
        """Any write, valid or not: one over a value this node owns is undone at once."""
        owned = self._owned
        if name in owned and owned[name] != value:
            log.warning("%s=%s written by another node; re-asserting it", name, short_repr(value))
            self.poke()

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

    def _track(self, topics: Iterable[str]) -> list[str]:
        """The channels to track this round, sorted: at most ``MAX_CHANNELS``.

        Those tracked already keep their place; new ones take what is left, in topic order.
        """
        live = set(topics)
        if len(live) <= MAX_CHANNELS:
            tracked = live
        else:
            kept = sorted(live & self._tracked)[:MAX_CHANNELS]
            fresh = sorted(live - self._tracked)[: MAX_CHANNELS - len(kept)]
            tracked = {*kept, *fresh}
        ignored = len(live) - len(tracked)
        if ignored > self._ignored:  # the ones ignored since the last round (as counts tell)
            self._channels_full.refuse(ignored - self._ignored)
        self._channels_full.room(len(live))
        self._ignored = ignored
        self._tracked = frozenset(tracked)
        return sorted(tracked)

    def channels(self) -> tuple[ChannelState, ...]:
        """Every live channel whose publisher declared valid bounds, by topic.

        At most ``MAX_CHANNELS``: the ones tracked already, then new ones by topic.
        """
        entries = self._transport.graph.entries()
        last = self._summary
        if last is not None and last[0] is entries:  # a graph unchanged is not read again
            graph = last[1]
        else:
            graph = summarize(entries)  # one pass, not one per channel
            self._summary = (entries, graph)  # one reference: any thread may read channels()
        tracked = self._view.channels(self._track(graph.publishers))  # one read for the round
        states = []
        incomplete: set[str] = set()
        for topic, params in tracked.items():
            if params.bounded:  # else a publisher that has not declared valid bounds yet
                managed = topic in graph.managed
                states.append(
                    ChannelState(params, managed, graph.publishers[topic], graph.hosts[topic])
                )
            if not params.bounded or params.size_bytes is None:
                incomplete.add(topic)
        self._refresh(entries, incomplete)
        return tuple(states)

    def _refresh(self, entries: frozenset[GraphEntry], incomplete: set[str]) -> None:
        """Ask again, once a period at most, for the parameters of publishers seen without them.

        A publisher writes its bounds before it announces itself, so a channel seen without
        them for a period lost its writes on the way (a route not yet up): ask its process.
        """
        now = self._transport.now()
        for entry in entries:
            if entry.role is not Role.PUBLISHER or entry.topic not in incomplete:
                continue
            first = self._incomplete_since.setdefault(entry.uid, now)
            asked = self._asked.get(entry.uid, first)
            if now - asked >= self._view.dbm().period_s:
                self._asked[entry.uid] = now
                log.info("%s: asking again for its parameters", entry.topic)
                self._transport.refresh(entry)
        for uid in set(self._incomplete_since) - {e.uid for e in entries if e.topic in incomplete}:
            self._incomplete_since.pop(uid, None)
            self._asked.pop(uid, None)

    # -- one round ----------------------------------------------------------------------------

    def _allocate(self, managed: list[ChannelParams], dbm: DbmParams) -> _Outcome:
        if not managed:
            return _Outcome(Status.OPTIMAL, "no managed channels")
        if (budget := dbm.link_and_utilization()) is None:
            floors = {c.topic: c.floor_hz for c in managed}
            return _Outcome(Status.INFEASIBLE, f"no budget: set {names.BANDWIDTH}", floors)
        specs = [spec for c in managed if (spec := c.spec()) is not None]
        # Channels that have not sent a message yet have no size: nothing is pushed to them, so
        # they send nothing on [topic]/optimized until there is room for them (or fail-safe).
        if not specs:
            return _Outcome(Status.OPTIMAL, "waiting for the first message sizes")
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
            tuple(specs),
            bandwidth_mbit=budget[0],
            utilization=budget[1],
            links=links,
            frame_headroom=dbm.frame_headroom,
        )
        ladders = {c.topic: ladder for c in managed if c.topic in topics and (ladder := c.ladder())}
        crossing = [topic for link in links for topic in link.topics]
        # Ladders under the paper's strategy, or under `lp` with links that share no channel
        # (a robot's uplink): the rung and the rate together; else rates on declared sizes.
        quality = dbm.strategy is Strategy.PAPER or (
            dbm.strategy is Strategy.LP and len(crossing) == len(set(crossing))
        )
        if ladders and quality:
            outcome = _quality_outcome(problem, ladders, self._price_hint)
            assert outcome.quality is not None
            self._price_hint = outcome.quality.price_per_byte  # where the next round starts
            return outcome
        allocation = allocate(problem, strategy=dbm.strategy)
        return _Outcome(
            allocation.status, allocation.message, allocation.rates_by_topic(), allocation
        )

    def optimize(self) -> Round:
        """Read, allocate and push once."""
        channels = self.channels()
        dbm = self.dbm()
        managed = [c.params for c in channels if c.managed]
        try:
            outcome = self._allocate(managed, dbm)
        except DbmlError as err:
            # A bad combination of good values: keep every managed channel at its minimum.
            floors = {c.topic: c.floor_hz for c in managed}
            outcome = _Outcome(Status.INFEASIBLE, str(err), floors)
        status, message = outcome.status, outcome.message
        rates = dict(outcome.rates_hz)
        for channel in channels:
            if not channel.managed and channel.params.max_rate_hz is not None:
                rates[channel.topic] = channel.params.max_rate_hz
        rates = {t: self._unless_noise(t, r) for t, r in rates.items()}
        if self._ignored:
            message = f"{message}; {self._ignored} channels ignored: more than {MAX_CHANNELS}"
        problems = self._view.problems()
        if problems:
            message = f"{message}; ignored: {'; '.join(problems)}"
        owned: _Writes = {c.topic: {names.managed(c.topic): c.managed} for c in channels}
        owned[None] = {names.STATUS: status.value, names.STATUS_MESSAGE: message}
        params = self._transport.params
        updates: _Writes = {}
        for topic, values in owned.items():
            changed = {name: value for name, value in values.items() if params.get(name) != value}
            if changed:
                updates[topic] = changed
        if names.STATUS_MESSAGE in updates.get(None, {}):
            if status is Status.INFEASIBLE:
                log.warning("infeasible: %s", message)
            else:
                log.info("%s", message)
        # The label says the bytes the rung was counted at: the camera holds its frames to them.
        encodings = {
            t: encoding_label(*e, size_bytes=outcome.counted_bytes.get(t))
            for t, e in outcome.encodings.items()
            if t in rates
        }
        self._owned = {name: v for values in owned.values() for name, v in values.items()}
        self._owned |= {names.current_value(t): r for t, r in rates.items()}
        self._owned |= {names.encoding(t): e for t, e in encodings.items()}
        limits = self._limits(outcome, dbm, channels, rates, encodings)
        self._push(rates, encodings, channels, updates, limits)
        result = Round(
            channels,
            rates,
            status,
            message,
            dbm.budget_mbit,
            outcome.allocation,
            dbm.strategy,
            self._rounds,
            {t: outcome.encodings[t] for t in encodings},
            outcome.quality,
        )
        self.last_round = result
        self._report(result)
        if self._on_round is not None:
            try:
                self._on_round(result)
            except Exception:  # a watcher's failure never stops the allocation
                if not self._watcher_failed:
                    log.exception("a round's watcher failed (further failures not logged)")
                self._watcher_failed = True
        return result

    def _limits(
        self,
        outcome: _Outcome,
        dbm: DbmParams,
        channels: tuple[ChannelState, ...],
        rates: Mapping[str, float],
        encodings: Mapping[str, str],
    ) -> tuple[Limit, ...]:
        """What the managed channels may send together while rates change: the budget, each link.

        Each at least what the round pushes (an infeasible round's floors exceed the budget; a
        rung's bytes are rounded up to the byte in its label).
        """
        solved = outcome.allocation or outcome.quality
        if solved is None:
            return ()
        target = {
            c.topic: _bytes_per_s(c.params, (rates[c.topic], encodings.get(c.topic)))
            for c in channels
            if c.managed and c.topic in rates
        }
        limits = [Limit(frozenset(target), max(solved.budget_bytes_per_s, sum(target.values())))]
        budget = dbm.link_and_utilization()
        utilization = 1.0 if budget is None else budget[1]
        for link in self._links:
            topics = frozenset(link.topics) & target.keys()
            if topics:
                capacity = mbit_to_bytes_per_s(link.capacity_mbit) * utilization
                limits.append(Limit(topics, max(capacity, sum(target[t] for t in topics))))
        return tuple(limits)

    def _report(self, result: Round) -> None:
        """Say what the round decided, to whoever listens: at most once a ``report_interval_s``.

        A round within it is not reported; the next one (at most a period later) is, whole.
        """
        now = self._transport.now()
        if now - self._reported_s < self._report_interval_s or not self._reports.has_subscribers:
            return
        self._reported_s = now
        self._reports.put(result.report().encode())

    def _push(
        self,
        rates: dict[str, float],
        encodings: dict[str, str],
        channels: tuple[ChannelState, ...],
        updates: _Writes,
        limits: tuple[Limit, ...],
    ) -> None:
        """Push what changed: decreases first, the increases that fit, the rest and the heartbeat.

        A laddered channel's rung goes with its rate, and what decreases is its bytes a second
        (rate times the rung's bytes), so a channel trading detail for frames is not raised
        before another's cut is applied. An increase that does not fit beside what the others
        may still send (``RateLedger``) waits: ``admit`` pushes it once it fits.
        """
        params = self._transport.params
        publishers = {c.topic: c.publishers for c in channels}
        states = {c.topic: c.params for c in channels}
        now = self._transport.now()
        period_s = self._view.dbm().period_s  # once per round, not once per channel
        # Changed, or for new publishers (a restarted one heard nothing), or overwritten by
        # another node (the store is not ours alone), or not acknowledged for a period (the push
        # or its acknowledgement was lost on the way): pushed; an unchanged rate is not.
        wanted = {t: (r, encodings.get(t)) for t, r in rates.items()}
        changed = {
            t: w
            for t, w in wanted.items()
            if self._pushed.get(t) != (w, publishers.get(t))
            or params.get(names.current_value(t)) != w[0]
            or (w[1] is not None and params.get(names.encoding(t)) != w[1])
            or (not self._acknowledged(t, w) and now - self._pushed_at.get(t, now) >= period_s)
        }
        # A channel nobody pushed to yet sends nothing: it rises from zero, with the increases.
        before = {t: self._running(t) for t in changed}
        decreases = {
            t: w
            for t, w in changed.items()
            if before[t][0] is not None
            and _bytes_per_s(states[t], w) < _bytes_per_s(states[t], before[t])
        }
        budget = max((limit.bytes_per_s for limit in limits), default=0.0)
        queued = not self._transport.delivers_at_once
        for topic in decreases:
            channel = states[topic]
            # The frame it sent just before applying the decrease may still be queued behind
            # its acknowledgement. (Frames its limiter banked are within the limiter's own bound:
            # a window carries its rates' frames plus those, decrease or not.)
            frame = QUEUED_FRAMES * _frame_bytes(channel, before[topic][1])
            self._ledger.decrease(
                topic,
                before_bytes_per_s=_bytes_per_s(channel, before[topic]),
                drain_s=frame / budget if queued and budget > 0 else 0.0,
                now=now,
            )
        increases = {t: w for t, w in changed.items() if t not in decreases}
        if decreases and increases:
            self._send({t: _writes(t, w) for t, w in decreases.items()}, channels)
            self._pushed_at.update(dict.fromkeys(decreases, now))
            for topic, w in decreases.items():
                self._pushed[topic] = (w, publishers.get(topic, frozenset()))
            decreases = {}
        order = sorted(increases, key=lambda t: (-(states[t].priority or 0.0), t))
        going = self._fitting({t: increases[t] for t in order}, channels, limits, frozenset())
        self._rounds += 1
        pushed = decreases | going
        writes: _Writes = {t: _writes(t, w) for t, w in pushed.items()}
        for key, values in updates.items():
            writes[key] = writes.get(key, {}) | values
        if self._beat:
            writes[None] = writes.get(None, {}) | {names.ROUND: self._rounds}
            self._beat_s = now
        self._own(going)
        self._send(writes, channels)
        self._pushed_at.update(dict.fromkeys(pushed, now))
        held = {t: increases[t] for t in order if going.get(t) != increases[t]}
        kept = {t: p for t in held if (p := self._pushed.get(t)) is not None}
        self._pushed = {t: (w, publishers.get(t, frozenset())) for t, w in wanted.items()}
        self._pushed.update(kept)  # still what it runs: pushed again once it fits
        for topic in held.keys() - kept.keys():
            del self._pushed[topic]
        stepped = frozenset(held.keys() & going.keys())
        for topic in stepped:  # what it runs now: part of the way
            self._pushed[topic] = (going[topic], publishers.get(topic, frozenset()))
        for topic in set(self._pushed_at) - set(rates):
            del self._pushed_at[topic]
        for topic in set(self._acked_s) - set(rates):
            del self._acked_s[topic]
        self._ledger.forget(rates)
        self._waiting = _Waiting(held, channels, limits, stepped) if held else None
        if held:
            log.debug("round %d: %d increases wait for room: %s", self._rounds, len(held), held)

    def _fitting(
        self,
        increases: Mapping[str, _Wanted],
        channels: tuple[ChannelState, ...],
        limits: tuple[Limit, ...],
        stepped: frozenset[str],
    ) -> dict[str, _Wanted]:
        """What of ``increases`` goes now (``RateLedger.admit``), the acknowledgements in first.

        Each goes in full, or part of the way (``STEP_SHARE``) if it runs already, has not
        stepped yet and keeps its rung: a partial rise at another rung could lower the rate on
        its way up.
        """
        now = self._transport.now()
        states = {c.topic: c.params for c in channels}
        for topic in self._ledger.pending:
            pushed = self._pushed.get(topic)
            if pushed is not None and self._acknowledged(topic, pushed[0]):
                self._ledger.acknowledged(topic, min(self._acked_s.get(topic, now), now))
        late = self._ledger.settle(now)
        if late:
            log.warning("no acknowledgement of a decrease from %s; raising others anyway", late)
        current = {}
        for topic, channel in states.items():
            pushed = self._pushed.get(topic)
            running = self._running(topic) if pushed is None else pushed[0]
            current[topic] = _bytes_per_s(channel, running)
        wanted = {t: _bytes_per_s(states[t], w) for t, w in increases.items()}
        floors = {}
        for topic, (rate, label) in increases.items():
            channel = states[topic]
            pushed = self._pushed.get(topic)
            if topic in stepped or rate is None or channel.min_rate_hz is None:
                continue
            if current[topic] <= 0:  # a first rate goes whole: at a fleet's start all are first
                continue
            if label is not None and (pushed is None or pushed[0][1] != label):
                continue
            lowest = channel.min_rate_hz * _frame_bytes(channel, label)
            way = current[topic] + STEP_SHARE * (wanted[topic] - current[topic])
            floors[topic] = max(lowest, way)
        going = self._ledger.admit(wanted, current, limits, floors=floors)
        result: dict[str, _Wanted] = {}
        for topic, goes in going.items():
            rate, label = increases[topic]
            frame = _frame_bytes(states[topic], label)
            if goes >= wanted[topic] or rate is None or frame <= 0:
                result[topic] = increases[topic]
            else:
                result[topic] = (min(rate, goes / frame), label)
        return result

    def _own(self, going: Mapping[str, _Wanted]) -> None:
        """The rates about to be pushed are ours, a step on the way included."""
        self._owned = self._owned | {names.current_value(t): w[0] for t, w in going.items()}

    def admit(self) -> None:
        """Push the last round's waiting increases that fit now (on an acknowledgement)."""
        waiting = self._waiting
        if waiting is None:
            return
        going = self._fitting(waiting.increases, waiting.channels, waiting.limits, waiting.stepped)
        if going:
            now = self._transport.now()
            publishers = {c.topic: c.publishers for c in waiting.channels}
            self._own(going)
            self._send({t: _writes(t, w) for t, w in going.items()}, waiting.channels)
            self._pushed_at.update(dict.fromkeys(going, now))
            for topic, w in going.items():
                self._pushed[topic] = (w, publishers.get(topic, frozenset()))
            log.debug("admitted once room was made: %s", going)
        held = {t: w for t, w in waiting.increases.items() if going.get(t) != w}
        stepped = waiting.stepped | (held.keys() & going.keys())
        self._waiting = (
            replace(waiting, increases=held, stepped=frozenset(stepped)) if held else None
        )

    def _send(self, writes: _Writes, channels: tuple[ChannelState, ...]) -> None:
        """Write in batches: a channel's values to each host that publishes it, the rest to all.

        The rest: global values, channels without a known host. So what a robot hears per round
        is its own channels' share, whatever the fleet's size.
        """
        hosts = {c.topic: c.hosts for c in channels}
        common: dict[str, ParamValue] = {}
        by_host: dict[str, dict[str, ParamValue]] = {}
        for topic, values in writes.items():
            addressed = () if topic is None else hosts.get(topic, ())
            valid = [h for h in addressed if keys.is_host_name(h)]
            if not valid:
                common |= values
            for host in valid:
                by_host.setdefault(host, {}).update(values)
        params = self._transport.params
        for host in sorted(by_host):
            params.set_many(by_host[host], host=host)
        if common:
            params.set_many(common)

    def _unless_noise(self, topic: str, rate_hz: float) -> float:
        """``rate_hz``, or the rate pushed already when they differ by float noise only."""
        pushed = self._pushed.get(topic)
        if pushed is not None and (old := pushed[0][0]) is not None and same_rate(old, rate_hz):
            return old
        return rate_hz

    def _running(self, topic: str) -> _Wanted:
        """What the publisher acknowledged running, else what was last pushed to it."""
        pushed = self._pushed.get(topic)
        pushed_rate, pushed_label = (None, None) if pushed is None else pushed[0]
        applied = self._applied_hz(topic)
        label = self._view.get(names.encoding_applied(topic))
        return (
            pushed_rate if applied is None else applied,
            label if isinstance(label, str) else pushed_label,
        )

    def _applied_hz(self, topic: str) -> float | None:
        """The rate the publisher acknowledged (validated by the view)."""
        value = self._view.get(names.applied(topic))
        return value if isinstance(value, float) else None

    def _acknowledged(self, topic: str, wanted: _Wanted) -> bool:
        """Whether the publisher applies ``wanted``: the rate, and the rung if it has one."""
        rate, label = wanted
        if self._applied_hz(topic) != rate:
            return False
        return label is None or self._view.get(names.encoding_applied(topic)) == label

    # -- the loop -----------------------------------------------------------------------------

    @property
    def alive(self) -> bool:
        """False once its thread died (the command then exits non-zero)."""
        return self._worker.alive

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
        self._reports.close()
