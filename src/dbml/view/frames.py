"""What the live view shows, as data: its topics, their JSON schemas and the messages on them.

Pure. The allocation is the optimizer's own ``RoundReport`` (``dbml.protocol.messages``), shown
as it said it, so ``dbml monitor``, ``dbml optimizer`` and the demo's operator show one round the
same way; the budget is built from the validated parameter values a process holds (read through
``dbml.runtime.params``). The topics are the paper's names where it has one
(``[topic]/dbm/frequency/current_value``) and dbml's own under ``/dbm`` otherwise. A viewer may
set what ``dbml budget`` and ``dbml priority`` set, checked by the schema's own rule, where the
schema gives the serving process's role the writing of it.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from dbml.core.errors import TransportError
from dbml.core.spec import short_repr
from dbml.protocol import names, schema
from dbml.protocol.schema import ParamError, Parameter, ParamValue, Scope, Writer
from dbml.runtime.params import dbm_params

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
    "BudgetFrame",
    "LogLevel",
    "budget_frame",
    "check_setting",
    "delivered_topic",
    "frequency_topic",
    "image_shape",
    "image_topic",
    "settable_names",
]

ALLOCATION_TOPIC = f"{schema.GLOBAL_PREFIX}/allocation"
"""One message per optimizer round: its ``RoundReport``, the status and every channel's rate."""
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
        "encoding": {"type": "string", "description": "a laddered channel's rung; else null"},
        "quality": _NULLABLE_NUMBER,
        "sent_hz": _NULLABLE_NUMBER,
    },
}
ALLOCATION_SCHEMA: dict[str, Any] = {
    "title": "dbml.Allocation",
    "description": "One optimizer round: its status and every live channel's allocation.",
    "type": "object",
    "properties": {
        "round": _NUMBER,
        "status": {"type": "string"},
        "status_message": {"type": "string"},
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
