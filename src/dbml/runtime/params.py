"""The parameters, typed: the last good value of each and the one budget rule.

Every value dbml reads from a parameter store crosses the network first, so it is untrusted:
the wire schema's ``check_param`` (``dbml.protocol.schema``) decides whether a value of a known
name is valid. ``ParamView`` keeps, per name, the last good value and ignores a bad one: it
logs it once with the key and the value and lists it in ``problems()`` (the optimizer appends
those to ``/dbm/status_message``), so a bad write never raises in the optimizer's or a publisher's
thread and never takes a channel out of the allocation.

``DbmParams`` and ``ChannelParams`` are what the optimizer, the publishers, the estimator and
the monitor read; ``DbmParams.budget_mbit`` is the one budget rule: an estimate, when one runs,
else bandwidth times utilization (an estimate never above that). A name is read once, where a
value enters (``ParamView`` parses it into its parameter and topic), and kept by parameter per
channel: reading a channel builds no name, and watchers that want the parameter get it parsed.

What a view keeps is bounded as its store is (``MAX_VALUES`` names, ``MAX_PROBLEMS`` problems):
past a bound a new name is refused and the flood logged once, with a count.
"""

from __future__ import annotations

import functools
import logging
import threading
import weakref
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import ClassVar, TypeAlias

from dbml.core.allocation import Strategy
from dbml.core.config import DbmSettings
from dbml.core.errors import SpecError
from dbml.core.ladder import Ladder, Preference, Rung
from dbml.core.spec import ChannelSpec
from dbml.protocol import names, schema
from dbml.protocol.ladders import Encoding, decode_rungs, parse_encoding
from dbml.protocol.schema import ParamError, Parameter, lookup
from dbml.transports.base import Closer, Handle, ParamStore, ParamValue
from dbml.transports.callbacks import CallbackList
from dbml.transports.overflow import Overflow
from dbml.transports.replica import MAX_PARAMS

__all__ = [
    "MAX_PROBLEMS",
    "MAX_VALUES",
    "SPECS_CACHED",
    "ByParameter",
    "ChannelParams",
    "DbmParams",
    "ParamView",
    "Snapshot",
    "dbm_params",
    "read_snapshot",
    "write_settings",
]

log = logging.getLogger("dbml.params")

ByParameter: TypeAlias = Mapping[Parameter, ParamValue]
"""Valid values of one channel's parameters, or of the global ones, keyed by the parameter."""

MAX_VALUES = 2 * MAX_PARAMS
"""The most names whose last good value a view keeps. A view holds what its store holds: the
zenoh store keeps up to ``MAX_PARAMS`` names from the network and this process's own besides,
so this is twice that (ROS 1's mirror is bounded alike), and it bounds any store that does not
bound itself. Past it a new name is refused (not kept, nobody told) and the flood logged once,
with a count; names held are still updated and deleted."""
SPECS_CACHED = 8192
"""Distinct channel specs kept built (``ChannelParams.spec``): twice the channels an optimizer
tracks, so every round finds an unchanged channel's spec built and checked already."""
MAX_PROBLEMS = 64
"""The most bad values ``problems()`` lists, each once in the log: they end up in
``/dbm/status_message``, which every process fetches, so a flood of bad names must not make it
megabytes (a misconfigured fleet shows a handful). Past it a new bad name is neither kept nor
logged by itself: the flood is logged once with a count, and ``problems()`` ends with a line
saying that more are not listed."""


@dataclass(frozen=True, slots=True)
class DbmParams:
    """The ``/dbm/...`` parameters in force."""

    bandwidth_mbit: float | None = None
    utilization: float = 1.0
    period_s: float = 1.0
    strategy: Strategy = Strategy.PAPER
    frame_headroom: bool = False
    estimate_mbit: float | None = None
    """The bandwidth estimator's estimate, when one runs: already the usable budget."""

    @property
    def configured_mbit(self) -> float | None:
        """What the configuration allows: bandwidth times utilization (the estimate's cap)."""
        return None if self.bandwidth_mbit is None else self.bandwidth_mbit * self.utilization

    @property
    def budget_mbit(self) -> float | None:
        """What may be allocated: the estimate, else bandwidth times utilization.

        An estimate never widens the configured budget, and without one there is no budget.
        """
        budget = self.link_and_utilization()
        return None if budget is None else budget[0] * budget[1]

    def link_and_utilization(self) -> tuple[float, float] | None:
        """The budget as a ``Problem`` takes it: a link of Mbit/s and the usable fraction.

        The configured bandwidth and utilization (which per-link capacities share), or an
        estimate below them, which is usable whole.
        """
        if self.bandwidth_mbit is None:
            return None
        configured = self.bandwidth_mbit * self.utilization
        if self.estimate_mbit is not None and self.estimate_mbit < configured:
            return self.estimate_mbit, 1.0
        return self.bandwidth_mbit, self.utilization


@dataclass(frozen=True, slots=True)
class ChannelParams:
    """One channel's ``[topic]/dbm/...`` parameters in force (None: unset)."""

    topic: str
    min_rate_hz: float | None = None
    max_rate_hz: float | None = None
    size_bytes: float | None = None
    priority: float = 0.0
    current_rate_hz: float | None = None
    """The allocation the optimizer pushed."""
    applied_rate_hz: float | None = None
    """The rate the publisher acknowledged applying."""
    sent_rate_hz: float | None = None
    """The rate the publisher last said it sent (None: it has not said)."""
    managed: bool | None = None
    rungs: tuple[Rung, ...] | None = None
    """The ladder the publisher measured (None: the channel has none)."""
    preference: Preference = Preference.BALANCED
    min_quality: float = 0.0
    encoding: Encoding | None = None
    """The rung the optimizer pushed: ``(scale, jpeg_quality)``."""
    applied_encoding: Encoding | None = None
    """The encoding the publisher acknowledged applying."""

    def ladder(self) -> Ladder | None:
        """The channel's ladder with its quality floor and preference (None: no ladder)."""
        if self.rungs is None:
            return None
        return _ladder(self.rungs, self.min_quality, self.preference)

    @property
    def bounded(self) -> bool:
        """Whether the publisher declared usable bounds (``0 < min <= max``)."""
        return (
            self.min_rate_hz is not None
            and self.max_rate_hz is not None
            and self.min_rate_hz <= self.max_rate_hz
        )

    @property
    def floor_hz(self) -> float:
        """The declared minimum rate (0 when undeclared): where an unsized channel stays."""
        return self.min_rate_hz or 0.0

    def spec(self) -> ChannelSpec | None:
        """The channel as the allocator takes it, once bounds and size are known."""
        if not self.bounded or self.size_bytes is None:
            return None
        return _spec(
            self.topic, self.floor_hz, self.max_rate_hz or 0.0, self.size_bytes, self.priority
        )


@functools.lru_cache(maxsize=SPECS_CACHED)
def _spec(
    topic: str, min_rate_hz: float, max_rate_hz: float, size_bytes: float, priority: float
) -> ChannelSpec:
    """A spec, checked once per distinct value: the optimizer asks every channel every round."""
    return ChannelSpec(topic, min_rate_hz, max_rate_hz, size_bytes, priority)


@functools.lru_cache(maxsize=1024)
def _ladder(rungs: tuple[Rung, ...], min_quality: float, preference: Preference) -> Ladder:
    """A ladder, made once per distinct value: the optimizer asks every channel every round."""
    return Ladder(rungs, min_quality=min_quality, preference=preference)


def write_settings(store: ParamStore, settings: DbmSettings) -> None:
    """Write a config's ``dbm:`` section under the paper's names."""
    store.set(names.BANDWIDTH, settings.max_bandwidth_mbit)
    store.set(names.UTILIZATION, settings.utilization)
    store.set(names.PERIOD, settings.optimization_period_s)
    store.set(names.STRATEGY, settings.strategy.value)
    store.set(names.FRAME_HEADROOM, settings.frame_headroom)


class ParamView:
    """The last good value of every parameter, kept current from the store's notifications.

    One view per store and process (``ParamView.of``), so every value is checked, and a bad one
    logged, once. ``watch(callback)`` is called with ``(name, value)`` after a valid value is
    taken in (on the store's thread); a bad value calls nothing. ``watch_params(callback)`` is
    called with ``(parameter, topic, value)`` for dbml's own names, already parsed.
    ``watch_channel(topic, ...)`` and ``watch_dbm(...)`` hear only one channel's parameters or
    only the global ones: a write's name is parsed once, when it enters, and goes to its
    channel's watchers alone, so a process with many publishers does not have each of them
    filter every write. Reading never touches the middleware, and ``dbm()``, ``channel()``
    and ``channels()`` read the values kept by parameter, building no name.
    """

    _shared: ClassVar[weakref.WeakKeyDictionary[ParamStore, ParamView]] = (
        weakref.WeakKeyDictionary()
    )
    _shared_lock: ClassVar[threading.Lock] = threading.Lock()

    @classmethod
    def of(cls, store: ParamStore) -> ParamView:
        """The view of ``store`` that every reader in this process shares."""
        with cls._shared_lock:
            view = cls._shared.get(store)
            if view is None:
                view = cls._shared[store] = cls(store)
        return view

    def __init__(self, store: ParamStore) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, ParamValue] = {}
        """The last good value per name (``MAX_VALUES`` names at most)."""
        self._globals: dict[Parameter, ParamValue] = {}
        self._channels: dict[str, dict[Parameter, ParamValue]] = {}
        """The same values of dbml's own names, by parameter: the globals, and per channel."""
        self._built: dict[str, ChannelParams] = {}
        """Each channel's ``ChannelParams`` as last read, until one of its values changes (an
        optimizer reads every channel every round; a round changes few). Only channels some
        value names: bounded as ``_channels`` is."""
        self._dbm: DbmParams | None = None
        """The global parameters as last read, until one of them changes."""
        self._values_full = Overflow("parameter names viewed", MAX_VALUES, log=log)
        self._problems: dict[str, str] = {}
        """The bad value standing per name, as its error says it (``MAX_PROBLEMS`` at most)."""
        self._problems_full = Overflow("bad parameter values", MAX_PROBLEMS, log=log)
        self._listeners: CallbackList[[str, ParamValue]] = CallbackList()
        self._param_listeners: CallbackList[[Parameter, str | None, ParamValue]] = CallbackList()
        self._dbm_listeners: CallbackList[[str, ParamValue]] = CallbackList()
        self._channel_listeners: dict[str, CallbackList[[str, ParamValue]]] = {}
        """Per topic, its watchers; a topic's entry goes when its last watcher does."""
        self._notified: set[str] | None = set()
        self._watch: Handle = store.watch(self._take)  # for the store's life, as the view
        # After the watch, so nothing falls between; a name notified meanwhile is newer than
        # what the snapshot says of it (over ROS 1 the snapshot is a slow XML-RPC call).
        for name, value in store.snapshot().items():
            self._take(name, value, from_snapshot=True)
        with self._lock:
            self._notified = None

    def _take(self, name: str, value: ParamValue, *, from_snapshot: bool = False) -> None:
        with self._lock:
            if self._notified is not None:
                if from_snapshot and name in self._notified:
                    return
                self._notified.add(name)
        found = lookup(name)  # the one parse of the name
        try:
            good = value if found is None or value is None else found[0].check(value, name=name)
        except ParamError as err:
            self._problem(name, str(err))
            return
        with self._lock:
            if self._problems.pop(name, None) is not None:
                self._problems_full.room(len(self._problems))
            if good is None:
                self._values.pop(name, None)
                self._values_full.room(len(self._values))
            elif name in self._values or len(self._values) < MAX_VALUES:
                self._values[name] = good
            else:
                self._values_full.refuse()
                return
            channel = None
            if found is not None:
                parameter, topic = found
                self._keep_locked(parameter, topic, good)
                if topic is not None:
                    channel = self._channel_listeners.get(topic)
        if from_snapshot:
            return
        self._listeners.fire(name, good)
        if found is None:
            return
        parameter, topic = found
        self._param_listeners.fire(parameter, topic, good)
        if topic is None:
            self._dbm_listeners.fire(name, good)
        elif channel is not None:
            channel.fire(parameter.field, good)

    def _keep_locked(self, parameter: Parameter, topic: str | None, value: ParamValue) -> None:
        """The value by parameter too (lock held): what ``dbm()`` and ``channel()`` read."""
        if topic is None:
            self._dbm = None
            if value is None:
                self._globals.pop(parameter, None)
            else:
                self._globals[parameter] = value
            return
        self._built.pop(topic, None)
        kept = self._channels.get(topic)
        if value is not None:
            if kept is None:
                kept = self._channels[topic] = {}
            kept[parameter] = value
        elif kept is not None:
            kept.pop(parameter, None)
            if not kept:
                del self._channels[topic]

    def _problem(self, name: str, problem: str) -> None:
        """A bad value of ``name``: listed and logged once, unless ``MAX_PROBLEMS`` stand."""
        with self._lock:
            known = self._problems.get(name)
            full = known is None and len(self._problems) >= MAX_PROBLEMS
            if not full:
                self._problems[name] = problem
        if full:
            self._problems_full.refuse()
        elif known != problem:
            log.warning("ignoring %s (the last good value stands)", problem)

    def watch(self, callback: Callable[[str, ParamValue], object]) -> Handle:
        """Call ``callback(name, value)`` for every valid value taken in from now on."""
        return self._listeners.add(callback)

    def watch_params(
        self, callback: Callable[[Parameter, str | None, ParamValue], object]
    ) -> Handle:
        """Call ``callback(parameter, topic, value)`` for every valid value of dbml's names.

        ``topic`` is the channel's, None for a global parameter: parsed once, when it entered.
        """
        return self._param_listeners.add(callback)

    def watch_dbm(self, callback: Callable[[str, ParamValue], object]) -> Handle:
        """Call ``callback(name, value)`` for every valid value of a global parameter.

        dbml's own ``/dbm/...`` names: the period, the optimizer's heartbeat, the budget.
        """
        return self._dbm_listeners.add(callback)

    def watch_channel(self, topic: str, callback: Callable[[str, ParamValue], object]) -> Handle:
        """Call ``callback(field, value)`` for every valid value of one of ``topic``'s parameters.

        ``field`` is the parameter's name after ``[topic]/dbm/`` (``names.CURRENT_FIELD``, ...).
        """
        with self._lock:  # so a closing watcher cannot drop the list this one joins
            listeners = self._channel_listeners.get(topic)
            if listeners is None:
                listeners = self._channel_listeners[topic] = CallbackList()
            added = listeners.add(callback)

        def remove() -> None:
            added.close()
            with self._lock:
                if not listeners and self._channel_listeners.get(topic) is listeners:
                    del self._channel_listeners[topic]

        return Closer(remove)

    def get(self, name: str) -> ParamValue:
        """The last good value of ``name`` (None: unset)."""
        with self._lock:
            return self._values.get(name)

    def values(self) -> Mapping[str, ParamValue]:
        """A copy of every last good value."""
        with self._lock:
            return dict(self._values)

    def problems(self) -> tuple[str, ...]:
        """The bad values standing now, one line each (key and value named).

        At most ``MAX_PROBLEMS``, and then a line saying that more are not listed.
        """
        with self._lock:
            listed = tuple(self._problems[name] for name in sorted(self._problems))
        if self._problems_full.flooding:
            listed += (f"more than {MAX_PROBLEMS} bad values: the others are not listed",)
        return listed

    def dbm(self) -> DbmParams:
        """The ``/dbm/...`` parameters, with their defaults where unset."""
        with self._lock:
            if self._dbm is None:
                self._dbm = _dbm(self._globals)
            return self._dbm

    def channel(self, topic: str) -> ChannelParams:
        """One channel's parameters."""
        with self._lock:
            return self._channel_locked(topic)

    def channels(self, topics: Iterable[str]) -> dict[str, ChannelParams]:
        """Several channels' parameters, read at once (an optimizer's round)."""
        with self._lock:
            return {t: self._channel_locked(t) for t in topics}

    def _channel_locked(self, topic: str) -> ChannelParams:
        built = self._built.get(topic)
        if built is None:
            kept = self._channels.get(topic)
            if kept is None:
                return _channel(topic, _NONE)  # not kept: any name may be asked of
            built = self._built[topic] = _channel(topic, kept)
        return built

    def topics(self) -> list[str]:
        """The channels some parameter is known of, sorted."""
        with self._lock:
            return sorted(self._channels)


_NONE: ByParameter = {}


def _float(value: ParamValue) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _dbm(values: ByParameter) -> DbmParams:
    strategy = values.get(schema.STRATEGY)
    return DbmParams(
        bandwidth_mbit=_float(values.get(schema.BANDWIDTH)),
        utilization=_float(values.get(schema.UTILIZATION)) or 1.0,
        period_s=_float(values.get(schema.PERIOD)) or 1.0,
        strategy=Strategy(strategy) if isinstance(strategy, str) else Strategy.PAPER,
        frame_headroom=values.get(schema.FRAME_HEADROOM) is True,
        estimate_mbit=_float(values.get(schema.ESTIMATE)),
    )


def _text(values: ByParameter, parameter: Parameter) -> str | None:
    value = values.get(parameter)
    return value if isinstance(value, str) else None


def _rungs(text: str | None) -> tuple[Rung, ...] | None:
    """A checked ladder's rungs (the view checked it as it entered; cached by text)."""
    if text is None:
        return None
    try:
        return decode_rungs(text)
    except SpecError:  # not reached for a value the view took in; a snapshot's is checked too
        return None


def _encoding(text: str | None) -> Encoding | None:
    if text is None:
        return None
    try:
        return parse_encoding(text)
    except SpecError:
        return None


def _channel(topic: str, values: ByParameter) -> ChannelParams:
    managed = values.get(schema.MANAGED)
    preference = _text(values, schema.PREFERENCE)
    return ChannelParams(
        topic=topic,
        min_rate_hz=_float(values.get(schema.MIN_RATE)),
        max_rate_hz=_float(values.get(schema.MAX_RATE)),
        size_bytes=_float(values.get(schema.SIZE)),
        priority=_float(values.get(schema.PRIORITY)) or 0.0,
        current_rate_hz=_float(values.get(schema.CURRENT)),
        applied_rate_hz=_float(values.get(schema.APPLIED)),
        sent_rate_hz=_float(values.get(schema.SENT)),
        managed=managed if isinstance(managed, bool) else None,
        rungs=_rungs(_text(values, schema.LADDER)),
        preference=Preference(preference) if preference is not None else Preference.BALANCED,
        min_quality=_float(values.get(schema.MIN_QUALITY)) or 0.0,
        encoding=_encoding(_text(values, schema.ENCODING)),
        applied_encoding=_encoding(_text(values, schema.ENCODING_APPLIED)),
    )


@dataclass(frozen=True, slots=True)
class Snapshot:
    """A one-off read of the store, validated, each name parsed once (``dbml monitor``'s)."""

    globals: ByParameter
    """The global parameters' valid values."""
    channels: Mapping[str, ChannelParams]
    """Every channel some valid value names, by topic."""

    @property
    def dbm(self) -> DbmParams:
        """The ``/dbm/...`` parameters in force, with their defaults where unset."""
        return _dbm(self.globals)


def _by_parameter(
    values: Mapping[str, ParamValue], *, check: bool = False
) -> tuple[dict[Parameter, ParamValue], dict[str, dict[Parameter, ParamValue]]]:
    """Values by name as the globals and each channel's, by parameter (one parse each).

    ``check``: a value its parameter's rule refuses is left out (it came from the network).
    """
    globals_: dict[Parameter, ParamValue] = {}
    channels: dict[str, dict[Parameter, ParamValue]] = {}
    for name, raw in values.items():
        found = lookup(name)
        if found is None or raw is None:
            continue
        parameter, topic = found
        try:
            value = parameter.check(raw, name=name) if check else raw
        except ParamError:
            continue
        if topic is None:
            globals_[parameter] = value
        else:
            channels.setdefault(topic, {})[parameter] = value
    return globals_, channels


def read_snapshot(snapshot: Mapping[str, ParamValue]) -> Snapshot:
    """A store's ``snapshot()`` validated and by parameter, each name parsed once."""
    globals_, channels = _by_parameter(snapshot, check=True)
    return Snapshot(globals_, {t: _channel(t, kept) for t, kept in channels.items()})


def dbm_params(values: Mapping[str, ParamValue]) -> DbmParams:
    """``DbmParams`` from valid values by name (as ``ParamView.values`` gives them)."""
    return _dbm(_by_parameter(values)[0])
