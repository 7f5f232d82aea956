"""What the live view shows, as data: its topics, their JSON schemas and the messages on them.

Pure: each message is built from the validated parameter values a process holds (the wire
schema's names, read through ``dbml.runtime.params``) and the live channels, so ``dbml monitor``,
``dbml optimizer`` and the demo's operator show one allocation the same way. The topics are the
paper's names where it has one (``[topic]/dbm/frequency/current_value``) and dbml's own under
``/dbm`` otherwise. A viewer may set what ``dbml budget`` and ``dbml priority`` set, checked by
the schema's own rule, where the schema gives the serving process's role the writing of it.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from dbml.core.allocation import Allocation, allocate
from dbml.core.errors import DbmlError, TransportError
from dbml.core.spec import Problem, mbit_to_bytes_per_s, short_repr
from dbml.protocol import names, schema
from dbml.protocol.schema import ParamError, Parameter, ParamValue, Scope, Writer
from dbml.runtime.params import channel_params, dbm_params

__all__ = [
    "ALLOCATION_SCHEMA",
    "ALLOCATION_TOPIC",
    "BUDGET_SCHEMA",
    "BUDGET_TOPIC",
    "DELIVERED_FIELD",
    "FREQUENCY_SCHEMA",
    "IMAGE_TYPE",
    "LOG_TOPIC",
    "SETTABLE",
    "AllocationFrame",
    "BudgetFrame",
    "ChannelFrame",
    "LogLevel",
    "allocation_frame",
    "budget_frame",
    "check_setting",
    "delivered_topic",
    "frequency_topic",
    "image_shape",
    "image_topic",
    "settable_names",
]

ALLOCATION_TOPIC = f"{schema.GLOBAL_PREFIX}/allocation"
"""One message per optimizer round: the status and every channel's allocation."""
BUDGET_TOPIC = f"{schema.GLOBAL_PREFIX}/budget"
"""The budget in force: the link's bandwidth, the utilization, the estimate."""
LOG_TOPIC = f"{schema.GLOBAL_PREFIX}/log"
"""Status changes and refused values, as ``foxglove.Log``."""
IMAGE_TYPE = "sensor_msgs/msg/Image"
"""The frames' ROS 2 type, so ROS 2 tools and the app's image panel read them."""
DELIVERED_FIELD = "frequency/delivered_value"
"""Beside the paper's ``frequency/current_value``: the rate that arrived where it is measured."""

SETTABLE: tuple[Parameter, ...] = (schema.BANDWIDTH, schema.UTILIZATION, schema.PRIORITY)
"""What a viewer may set: what ``dbml budget`` and ``dbml priority`` set."""

_NUMBER = {"type": "number"}
_NULLABLE_NUMBER = {"type": "number", "description": "null when not known"}
"""One type per field: Foxglove Studio 1.48 reads no type unions (``["number", "null"]``): a
channel whose schema has one shows no message at all."""

FREQUENCY_SCHEMA: dict[str, Any] = {
    "title": "dbml.Frequency",
    "description": "A rate in Hz, as the paper's std_msgs/Float64 parameter topics carry it.",
    "type": "object",
    "properties": {"data": _NUMBER},
    "required": ["data"],
}
_CHANNEL_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "topic": {"type": "string"},
        "priority": _NUMBER,
        "normalized_priority": _NULLABLE_NUMBER,
        "floor_hz": _NULLABLE_NUMBER,
        "rate_hz": _NULLABLE_NUMBER,
        "min_hz": _NUMBER,
        "max_hz": _NUMBER,
        "size_bytes": _NULLABLE_NUMBER,
        "share": _NULLABLE_NUMBER,
        "managed": {"type": "boolean"},
    },
}
ALLOCATION_SCHEMA: dict[str, Any] = {
    "title": "dbml.Allocation",
    "description": "One optimizer round: its status and every live channel's allocation.",
    "type": "object",
    "properties": {
        "round": _NULLABLE_NUMBER,
        "status": {"type": "string", "description": "null before the optimizer's first"},
        "status_message": {"type": "string", "description": "null before the first"},
        "strategy": {"type": "string"},
        "budget_mbit": _NULLABLE_NUMBER,
        "allocated_mbit": _NUMBER,
        "channels": {"type": "array", "items": _CHANNEL_SCHEMA},
    },
}
BUDGET_SCHEMA: dict[str, Any] = {
    "title": "dbml.Budget",
    "description": "The budget in force: bandwidth x utilization, or the estimate below it.",
    "type": "object",
    "properties": {
        "max_bandwidth_mbit": _NULLABLE_NUMBER,
        "utilization": _NUMBER,
        "budget_mbit": _NULLABLE_NUMBER,
        "estimate_mbit": _NULLABLE_NUMBER,
        "estimator_phase": {"type": "string", "description": "null when none runs"},
    },
}


def frequency_topic(topic: str) -> str:
    """The allocated rate's series: the paper's ``[topic]/dbm/frequency/current_value``."""
    return names.current_value(topic)


def delivered_topic(topic: str) -> str:
    """The delivered rate's series, beside the allocated one."""
    return f"{topic}/{schema.GLOBAL_PREFIX[1:]}/{DELIVERED_FIELD}"


def image_topic(topic: str) -> str:
    """The frames a remote subscriber receives: the channel's managed copy."""
    return f"{topic}/{names.OPTIMIZED}"


class LogLevel(enum.StrEnum):
    """``foxglove.Log``'s levels that dbml uses, by the SDK's names."""

    INFO = "Info"
    WARNING = "Warning"
    ERROR = "Error"


@dataclass(frozen=True, slots=True)
class ChannelFrame:
    """One channel in a round: what it declared, its priority floor and what it was given.

    ``normalized_priority`` and ``floor_hz`` are eq. 2-3 over the managed channels (None for an
    unmanaged or unsized one); ``rate_hz`` is the rate the optimizer pushed; ``share`` is of the
    budget.
    """

    topic: str
    priority: float
    normalized_priority: float | None
    floor_hz: float | None
    rate_hz: float | None
    min_hz: float
    max_hz: float
    size_bytes: float | None
    share: float | None
    managed: bool

    def as_json(self) -> dict[str, Any]:
        """The channel as ``/dbm/allocation`` carries it."""
        return {
            "topic": self.topic,
            "priority": self.priority,
            "normalized_priority": self.normalized_priority,
            "floor_hz": self.floor_hz,
            "rate_hz": self.rate_hz,
            "min_hz": self.min_hz,
            "max_hz": self.max_hz,
            "size_bytes": self.size_bytes,
            "share": self.share,
            "managed": self.managed,
        }


@dataclass(frozen=True, slots=True)
class AllocationFrame:
    """One round as ``/dbm/allocation`` carries it."""

    round: int | None
    status: str | None
    status_message: str | None
    strategy: str
    budget_mbit: float | None
    channels: tuple[ChannelFrame, ...]

    @property
    def allocated_mbit(self) -> float:
        """What the managed channels' rates add up to, in Mbit/s."""
        total = sum(
            c.rate_hz * c.size_bytes
            for c in self.channels
            if c.managed and c.rate_hz is not None and c.size_bytes is not None
        )
        return total * 8 / 1e6

    def as_json(self) -> dict[str, Any]:
        """The message."""
        return {
            "round": self.round,
            "status": self.status,
            "status_message": self.status_message,
            "strategy": self.strategy,
            "budget_mbit": self.budget_mbit,
            "allocated_mbit": self.allocated_mbit,
            "channels": [c.as_json() for c in self.channels],
        }


@dataclass(frozen=True, slots=True)
class BudgetFrame:
    """The budget in force, as ``/dbm/budget`` carries it."""

    max_bandwidth_mbit: float | None
    utilization: float
    budget_mbit: float | None
    estimate_mbit: float | None
    estimator_phase: str | None

    def as_json(self) -> dict[str, Any]:
        """The message."""
        return {
            "max_bandwidth_mbit": self.max_bandwidth_mbit,
            "utilization": self.utilization,
            "budget_mbit": self.budget_mbit,
            "estimate_mbit": self.estimate_mbit,
            "estimator_phase": self.estimator_phase,
        }


def budget_frame(values: Mapping[str, ParamValue], *, estimator_phase: str | None) -> BudgetFrame:
    """The budget from valid values; the estimator's phase as the caller decoded it."""
    dbm = dbm_params(values)
    return BudgetFrame(
        max_bandwidth_mbit=dbm.bandwidth_mbit,
        utilization=dbm.utilization,
        budget_mbit=dbm.budget_mbit,
        estimate_mbit=dbm.estimate_mbit,
        estimator_phase=estimator_phase,
    )


def _allocate(problem: Problem, strategy: str) -> Allocation | None:
    """The allocation of ``problem``, or None where the values do not make one."""
    try:
        return allocate(problem, strategy=strategy)
    except DbmlError:
        return None


def allocation_frame(values: Mapping[str, ParamValue], topics: Iterable[str]) -> AllocationFrame:
    """The round the values describe, for the live ``topics`` that declared their bounds.

    The rates are the ones pushed (``current_value``); the normalized priorities and floors are
    recomputed from the same values by the core (they are not on the wire), so they are the
    optimizer's whenever its inputs reached this process.
    """
    dbm = dbm_params(values)
    channels = [channel_params(values, topic) for topic in sorted(set(topics))]
    channels = [c for c in channels if c.bounded]
    managed = [c for c in channels if c.managed]
    specs = [spec for c in managed if (spec := c.spec()) is not None]
    budget = dbm.link_and_utilization()
    floors: dict[str, tuple[float, float]] = {}
    if specs and budget is not None:
        problem = Problem(tuple(specs), bandwidth_mbit=budget[0], utilization=budget[1])
        allocation = _allocate(problem, dbm.strategy.value)
        if allocation is not None:
            floors = {c.topic: (c.normalized_priority, c.floor_hz) for c in allocation.channels}
    budget_bytes = None if dbm.budget_mbit is None else mbit_to_bytes_per_s(dbm.budget_mbit)
    frames = []
    for channel in channels:
        rate, size = channel.current_rate_hz, channel.size_bytes
        share = None
        if channel.managed and budget_bytes and rate is not None and size is not None:
            share = rate * size / budget_bytes
        normalized, floor = floors.get(channel.topic, (None, None))
        frames.append(
            ChannelFrame(
                topic=channel.topic,
                priority=channel.priority,
                normalized_priority=normalized,
                floor_hz=floor,
                rate_hz=rate,
                min_hz=channel.min_rate_hz or 0.0,
                max_hz=channel.max_rate_hz or 0.0,
                size_bytes=size,
                share=share,
                managed=channel.managed is True,
            )
        )
    status = values.get(names.STATUS)
    message = values.get(names.STATUS_MESSAGE)
    counter = values.get(names.ROUND)
    return AllocationFrame(
        round=int(counter) if isinstance(counter, int | float) and math.isfinite(counter) else None,
        status=status if isinstance(status, str) else None,
        status_message=message if isinstance(message, str) else None,
        strategy=dbm.strategy.value,
        budget_mbit=dbm.budget_mbit,
        channels=tuple(frames),
    )


def settable_names(topics: Iterable[str]) -> list[str]:
    """Every name a viewer may set: the global ones, then each live channel's, sorted."""
    globals_ = [p.name for p in SETTABLE if p.scope is Scope.GLOBAL]
    per_channel = [
        p.key(topic) for topic in sorted(set(topics)) for p in SETTABLE if p.scope is Scope.CHANNEL
    ]
    return globals_ + per_channel


def check_setting(
    name: str, value: object, topics: Iterable[str], *, writers: frozenset[Writer]
) -> ParamValue:
    """``value`` for ``name`` as a viewer set it, checked as ``dbml budget|priority`` check it.

    ``writers`` are the roles of the process that serves the view: it writes only what the
    schema gives them (an optimizer's process does not write the budget, an operator's does),
    as a secure fleet's rules would hold it to. ``ParamError`` naming the name and the value: a
    name that is not the budget's or a live channel's priority, one these writers do not own, a
    value its rule refuses (-3, NaN, a string for a number).
    """
    shown = short_repr(name)
    if name not in settable_names(topics):
        raise ParamError(f"{shown}={short_repr(value)}: not a parameter a viewer may set")
    parameter = schema.lookup(name)
    if parameter is None or not parameter[0].writers & writers:
        owners = ", ".join(sorted(w.value for w in parameter[0].writers)) if parameter else "-"
        raise ParamError(
            f"{name}={short_repr(value)}: this process does not write it (written by: {owners})"
        )
    try:
        good = schema.check_param_value(value)
    except TransportError as err:  # a list, a dict: no parameter's value
        raise ParamError(f"{name}: {err}") from None
    checked = schema.check_param(name, good)
    if checked is None:
        raise ParamError(f"{name}=None: a value is required")
    return checked


def image_shape(size_bytes: int) -> tuple[int, int]:
    """``(height, width)`` of a mono8 image of ``size_bytes``: about twice as wide as high.

    The demo's frames are payloads of a size, not pictures; shown as one, 84,000 bytes are
    420 x 200 and 21,000 are 210 x 100. A size with no such divisor is one row.
    """
    if size_bytes <= 0:
        return 0, 0
    height = math.isqrt(size_bytes // 2)
    while height > 1 and size_bytes % height:
        height -= 1
    return max(height, 1), size_bytes // max(height, 1)
