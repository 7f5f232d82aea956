"""The parameters, typed: the one validation of a value and the one budget rule.

Every value dbml reads from a parameter store crosses the network first, so it is untrusted:
``check_param`` is the single place that decides whether a value of a known name is valid (a
rate in (0, 1 MHz], a size in (0, 1 GB], a priority in [0, 1], a strategy by name, ...).
``ParamView`` keeps, per name, the last good value and ignores a bad one: it logs it once with
the key and the value and lists it in ``problems()`` (the optimizer appends those to
``/dbm/status_message``), so a bad write never raises in the optimizer's or a publisher's
thread and never takes a channel out of the allocation.

``DbmParams`` and ``ChannelParams`` are what the optimizer, the publishers, the estimator and
the monitor read; ``DbmParams.budget_mbit`` is the one budget rule: an estimate, when one runs,
else bandwidth times utilization (an estimate never above that).
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from dbml.core.allocation import Status, Strategy
from dbml.core.config import DbmSettings
from dbml.core.errors import SpecError
from dbml.core.spec import (
    MAX_BANDWIDTH_MBIT,
    MAX_PERIOD_S,
    MAX_RATE_HZ,
    MAX_SIZE_BYTES,
    MIN_PERIOD_S,
    ChannelSpec,
    check_number,
    check_priority,
    short_repr,
)
from dbml.runtime import names
from dbml.transports.base import Handle, ParamStore, ParamValue
from dbml.transports.callbacks import CallbackList

__all__ = [
    "MAX_TEXT_CHARS",
    "ChannelParams",
    "DbmParams",
    "ParamError",
    "ParamView",
    "channel_params",
    "check_param",
    "dbm_params",
    "valid_values",
    "write_settings",
]

log = logging.getLogger("dbml.params")

MAX_TEXT_CHARS = 10_000
"""Status and estimator texts longer than this are not status lines."""

_POSITIVE: dict[str, Any] = {"minimum": 0.0, "exclusive_minimum": True}
_RULES: dict[str, dict[str, Any]] = {
    names.BANDWIDTH: {**_POSITIVE, "maximum": MAX_BANDWIDTH_MBIT},
    names.ESTIMATE: {**_POSITIVE, "maximum": MAX_BANDWIDTH_MBIT},
    names.UTILIZATION: {**_POSITIVE, "maximum": 1.0},
    names.PERIOD: {"minimum": MIN_PERIOD_S, "maximum": MAX_PERIOD_S},
    names.ROUND: {"minimum": 0.0},
}
_CHANNEL_RULES: dict[str, dict[str, Any]] = {
    names.MIN_FIELD: {**_POSITIVE, "maximum": MAX_RATE_HZ},
    names.MAX_FIELD: {**_POSITIVE, "maximum": MAX_RATE_HZ},
    names.CURRENT_FIELD: {**_POSITIVE, "maximum": MAX_RATE_HZ},
    names.APPLIED_FIELD: {**_POSITIVE, "maximum": MAX_RATE_HZ},
    names.SIZE_FIELD: {**_POSITIVE, "maximum": MAX_SIZE_BYTES},
}
_TEXTS = frozenset({names.STATUS_MESSAGE, names.ESTIMATOR_STATE})


class ParamError(SpecError):
    """A parameter value that breaks its rule; the message names the key and the value."""


def check_param(name: str, value: ParamValue) -> ParamValue:
    """``value`` if it is valid for ``name`` (numbers as floats; None means unset).

    Raises ``ParamError`` naming the key and the value. Names dbml does not know pass unchanged:
    they are not dbml's to judge.
    """
    if value is None:
        return None
    try:
        return _check(name, value)
    except ParamError:
        raise
    except SpecError as err:
        raise ParamError(str(err)) from None
    except ValueError:  # an enum that does not know the value
        raise ParamError(f"{name}={short_repr(value)} is not valid") from None


def _check(name: str, value: bool | int | float | str) -> ParamValue:
    if name in _RULES:
        return check_number(value, field=name, **_RULES[name])
    if name == names.STRATEGY:
        return Strategy(value).value if isinstance(value, str) else _not(name, value)
    if name == names.STATUS:
        return Status(value).value if isinstance(value, str) else _not(name, value)
    if name == names.FRAME_HEADROOM:
        return value if isinstance(value, bool) else _not(name, value)
    if name in _TEXTS:
        return (
            value if isinstance(value, str) and len(value) <= MAX_TEXT_CHARS else _not(name, value)
        )
    split = names.topic_of(name)
    field = None if split is None else split[1]
    if field in _CHANNEL_RULES:
        return check_number(value, field=name, **_CHANNEL_RULES[field])
    if field == names.PRIORITY_FIELD:
        return check_priority(value, field=name)
    if field == names.MANAGED_FIELD and not isinstance(value, bool):
        return _not(name, value)
    return value


def _not(name: str, value: object) -> ParamValue:
    raise ParamError(f"{name}={short_repr(value)} is not valid")


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
    managed: bool | None = None

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
        return ChannelSpec(
            self.topic, self.floor_hz, self.max_rate_hz or 0.0, self.size_bytes, self.priority
        )


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
    taken in (on the store's thread); a bad value calls nothing. Reading never touches the
    middleware.
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
        self._problems: dict[str, str] = {}
        self._listeners: CallbackList[[str, ParamValue]] = CallbackList()
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
        try:
            good = check_param(name, value)
        except ParamError as err:
            with self._lock:
                known = self._problems.get(name) == str(err)
                self._problems[name] = str(err)
            if not known:
                log.warning("ignoring %s (the last good value stands)", err)
            return
        with self._lock:
            self._problems.pop(name, None)
            if good is None:
                self._values.pop(name, None)
            else:
                self._values[name] = good
        if not from_snapshot:
            self._listeners.fire(name, good)

    def watch(self, callback: Callable[[str, ParamValue], object]) -> Handle:
        """Call ``callback(name, value)`` for every valid value taken in from now on."""
        return self._listeners.add(callback)

    def get(self, name: str) -> ParamValue:
        """The last good value of ``name`` (None: unset)."""
        with self._lock:
            return self._values.get(name)

    def values(self) -> Mapping[str, ParamValue]:
        """A copy of every last good value."""
        with self._lock:
            return dict(self._values)

    def problems(self) -> tuple[str, ...]:
        """The bad values standing now, one line each (key and value named)."""
        with self._lock:
            return tuple(self._problems[name] for name in sorted(self._problems))

    def dbm(self) -> DbmParams:
        """The ``/dbm/...`` parameters, with their defaults where unset."""
        return dbm_params(self.values())

    def channel(self, topic: str) -> ChannelParams:
        """One channel's parameters."""
        return channel_params(self.values(), topic)


def _float(values: Mapping[str, ParamValue], name: str) -> float | None:
    value = values.get(name)
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def dbm_params(values: Mapping[str, ParamValue]) -> DbmParams:
    """``DbmParams`` from valid values (as ``ParamView`` keeps them)."""
    strategy = values.get(names.STRATEGY)
    return DbmParams(
        bandwidth_mbit=_float(values, names.BANDWIDTH),
        utilization=_float(values, names.UTILIZATION) or 1.0,
        period_s=_float(values, names.PERIOD) or 1.0,
        strategy=Strategy(strategy) if isinstance(strategy, str) else Strategy.PAPER,
        frame_headroom=values.get(names.FRAME_HEADROOM) is True,
        estimate_mbit=_float(values, names.ESTIMATE),
    )


def channel_params(values: Mapping[str, ParamValue], topic: str) -> ChannelParams:
    """``ChannelParams`` of ``topic`` from valid values."""
    managed = values.get(names.managed(topic))
    return ChannelParams(
        topic=topic,
        min_rate_hz=_float(values, names.min_rate(topic)),
        max_rate_hz=_float(values, names.max_rate(topic)),
        size_bytes=_float(values, names.size(topic)),
        priority=_float(values, names.priority(topic)) or 0.0,
        current_rate_hz=_float(values, names.current_value(topic)),
        applied_rate_hz=_float(values, names.applied(topic)),
        managed=managed if isinstance(managed, bool) else None,
    )


def valid_values(snapshot: Mapping[str, ParamValue]) -> dict[str, ParamValue]:
    """The valid values of a one-off snapshot, bad ones left out.

    For a reader that does not follow the store (``dbml monitor``'s rows).
    """
    good: dict[str, ParamValue] = {}
    for name, value in snapshot.items():
        try:
            checked = check_param(name, value)
        except ParamError:
            continue
        if checked is not None:
            good[name] = checked
    return good
