"""The parameters, written once: name, scope, value type and range, who writes them.

Every other spelling of a parameter derives from this table: the names (``dbml.protocol.names``),
the validation of a value that crossed the network (``check_param``), the zenoh follow filter,
the ROS 2 parameter names, ``dbml monitor``'s columns and ``dbml secure init``'s access rules.

A parameter is global (``/dbm/<field>``, the paper's ``/dbm/max_bandwidth_in_mbit``) or belongs
to a channel (``[topic]/dbm/<field>``, the paper's ``/r1/camera/dbm/priority``). Its writers are
the roles whose processes may set it; everyone may read it.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TypeAlias

from dbml.core.allocation import Status, Strategy
from dbml.core.errors import SpecError, TransportError
from dbml.core.ladder import Preference
from dbml.core.spec import (
    MAX_BANDWIDTH_MBIT,
    MAX_PERIOD_S,
    MAX_RATE_HZ,
    MAX_SIZE_BYTES,
    MIN_PERIOD_S,
    check_number,
    short_repr,
)
from dbml.protocol.ladders import decode_rungs, parse_encoding

__all__ = [
    "APPLIED",
    "BANDWIDTH",
    "CURRENT",
    "ENCODING",
    "ENCODING_APPLIED",
    "ESTIMATE",
    "ESTIMATOR_STATE",
    "FRAME_HEADROOM",
    "GLOBAL_PREFIX",
    "LADDER",
    "MANAGED",
    "MAX_RATE",
    "MAX_TEXT_CHARS",
    "MIN_QUALITY",
    "MIN_RATE",
    "PARAMETERS",
    "PERIOD",
    "PREFERENCE",
    "PRIORITY",
    "ROUND",
    "SENT",
    "SIZE",
    "STATUS",
    "STATUS_MESSAGE",
    "STRATEGY",
    "UTILIZATION",
    "Column",
    "Kind",
    "ParamError",
    "ParamValue",
    "Parameter",
    "Scope",
    "Writer",
    "check_param",
    "check_param_value",
    "lookup",
    "ownership_table",
    "split_channel_name",
]

ParamValue: TypeAlias = bool | int | float | str | None
"""A parameter's value as a store holds it; ``None`` means deleted."""

GLOBAL_PREFIX = "/dbm"
"""dbml's own namespace: the global parameters' prefix and a channel's parameters' segment."""
MAX_TEXT_CHARS = 10_000
"""Status and estimator texts longer than this are not status lines."""


class ParamError(SpecError):
    """A parameter value that breaks its rule; the message names the key and the value."""


class Scope(enum.StrEnum):
    """Where a parameter lives: once (``/dbm/<field>``) or per channel (``[topic]/dbm/<field>``)."""

    GLOBAL = "global"
    CHANNEL = "channel"


class Writer(enum.StrEnum):
    """A role whose processes may write a parameter.

    The estimator runs beside the optimizer (``dbml optimizer --estimate``): a fleet's access
    rules give both to the optimizer's node.
    """

    PUBLISHER = "publisher"
    OPTIMIZER = "optimizer"
    ESTIMATOR = "estimator"
    OPERATOR = "operator"


class Kind(enum.StrEnum):
    """A parameter's value type as it travels."""

    NUMBER = "number"
    BOOL = "bool"
    TEXT = "text"
    CHOICE = "choice"


@dataclass(frozen=True, slots=True)
class Column:
    """How ``dbml monitor`` shows a parameter: its header and its number format."""

    title: str
    format: str
    optional: bool = False
    """Shown only when some row has a value (the ladder's columns, in a fleet with none)."""


@dataclass(frozen=True, slots=True)
class Parameter:
    """One parameter: the paper's field name, where it lives, its values and its writers."""

    field: str
    """The name below ``/dbm/`` (``max_bandwidth_in_mbit``, ``frequency/min``)."""
    scope: Scope
    kind: Kind
    writers: frozenset[Writer]
    doc: str
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    choices: tuple[str, ...] = ()
    column: Column | None = None
    """Its column in ``dbml monitor`` (None: not shown as a column)."""
    parse: Callable[[str], object] | None = None
    """A text's own rule (a ladder, an encoding's label): raises ``SpecError`` naming it."""

    @property
    def values(self) -> str:
        """Its values in words: ``(0, 1000]``, ``[0, 1]``, ``optimal / infeasible``, ``text``."""
        if self.kind is Kind.CHOICE:
            return " / ".join(self.choices)
        if self.kind is not Kind.NUMBER:
            return self.kind.value
        low = "-" if self.minimum is None else f"{self.minimum:g}"
        high = "" if self.maximum is None else f"{self.maximum:g}"
        opening = "(" if self.exclusive_minimum else "["
        return f"{opening}{low}, {high or 'inf'}{']' if high else ')'}"

    @property
    def writers_text(self) -> str:
        """Who writes it, in ``Writer``'s order: ``operator, publisher``."""
        return ", ".join(w.value for w in Writer if w in self.writers)

    @property
    def relative(self) -> str:
        """``dbm/<field>``: the name without its leading slash (global) or topic (channel)."""
        return f"{GLOBAL_PREFIX[1:]}/{self.field}"

    @property
    def name(self) -> str:
        """A global parameter's full name (``/dbm/max_bandwidth_in_mbit``)."""
        if self.scope is not Scope.GLOBAL:
            raise ValueError(f"{self.field!r} is a channel parameter: use key(topic)")
        return f"/{self.relative}"

    def key(self, topic: str) -> str:
        """A channel parameter's full name for ``topic`` (``/r1/camera/dbm/priority``)."""
        if self.scope is not Scope.CHANNEL:
            raise ValueError(f"{self.field!r} is a global parameter: use name")
        return f"{topic}/{self.relative}"

    @property
    def ros2_name(self) -> str:
        """The name ROS 2 gives it on its node (``/dbm`` or ``[topic]/dbm``): ``frequency.min``."""
        return self.field.replace("/", ".")

    def check(self, value: object, *, name: str) -> bool | int | float | str:
        """``value`` if valid (numbers as floats), else ``ParamError`` naming ``name``."""
        if self.kind is Kind.NUMBER:
            try:
                return check_number(
                    value,
                    field=name,
                    minimum=self.minimum,
                    maximum=self.maximum,
                    exclusive_minimum=self.exclusive_minimum,
                )
            except SpecError as err:
                raise ParamError(str(err)) from None
        if self.kind is Kind.BOOL and isinstance(value, bool):
            return value
        if self.kind is Kind.TEXT and isinstance(value, str) and len(value) <= MAX_TEXT_CHARS:
            if self.parse is not None:
                try:
                    self.parse(value)
                except SpecError as err:
                    raise ParamError(f"{name}: {err}") from None
            return value
        if self.kind is Kind.CHOICE and isinstance(value, str) and value in self.choices:
            return value
        raise ParamError(f"{name}={short_repr(value)} is not valid")


_OPERATOR = frozenset({Writer.OPERATOR})
_OPTIMIZER = frozenset({Writer.OPTIMIZER})
_ESTIMATOR = frozenset({Writer.ESTIMATOR})
_PUBLISHER = frozenset({Writer.PUBLISHER})

BANDWIDTH = Parameter(
    "max_bandwidth_in_mbit",
    Scope.GLOBAL,
    Kind.NUMBER,
    _OPERATOR,
    "The link's capacity in Mbit/s (1 Mbit = 10^6 bit).",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_BANDWIDTH_MBIT,
)
UTILIZATION = Parameter(
    "max_bandwidth_utilization",
    Scope.GLOBAL,
    Kind.NUMBER,
    _OPERATOR,
    "The share of the link dbml may allocate; the rest is kept for unmanaged traffic.",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=1.0,
)
PERIOD = Parameter(
    "optimization_rate_in_seconds",
    Scope.GLOBAL,
    Kind.NUMBER,
    _OPERATOR,
    "The optimizer's period in seconds (the paper's name, though it is a period).",
    minimum=MIN_PERIOD_S,
    maximum=MAX_PERIOD_S,
)
STRATEGY = Parameter(
    "strategy",
    Scope.GLOBAL,
    Kind.CHOICE,
    _OPERATOR,
    "The allocation strategy by name.",
    choices=tuple(s.value for s in Strategy),
)
FRAME_HEADROOM = Parameter(
    "frame_headroom",
    Scope.GLOBAL,
    Kind.BOOL,
    _OPERATOR,
    "Whether the optimizer keeps one message per channel but the largest out of the budget.",
)
STATUS = Parameter(
    "status",
    Scope.GLOBAL,
    Kind.CHOICE,
    _OPTIMIZER,
    "``optimal`` or ``infeasible``, written by the optimizer after every allocation.",
    choices=tuple(s.value for s in Status),
)
STATUS_MESSAGE = Parameter(
    "status_message",
    Scope.GLOBAL,
    Kind.TEXT,
    _OPTIMIZER,
    "What the last allocation found, and the bad values standing.",
)
ROUND = Parameter(
    "round",
    Scope.GLOBAL,
    Kind.NUMBER,
    _OPTIMIZER,
    "The optimizer's round counter, written every round: its heartbeat, the one value that "
    "changes when nothing else does (unchanged rates are not rewritten).",
    minimum=0.0,
)
ESTIMATE = Parameter(
    "estimated_bandwidth_in_mbit",
    Scope.GLOBAL,
    Kind.NUMBER,
    _ESTIMATOR,
    "The bandwidth estimator's current estimate (the budget in use), when one runs.",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_BANDWIDTH_MBIT,
)
ESTIMATOR_STATE = Parameter(
    "estimator_state",
    Scope.GLOBAL,
    Kind.TEXT,
    _ESTIMATOR,
    "What the estimator sees, as JSON (``dbml.protocol.messages.EstimatorState``): phase, receive "
    "rate, queueing delay, losses and when it decided.",
)
MIN_RATE = Parameter(
    "frequency/min",
    Scope.CHANNEL,
    Kind.NUMBER,
    _PUBLISHER,
    "The channel's declared minimum rate (Hz).",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_RATE_HZ,
)
MAX_RATE = Parameter(
    "frequency/max",
    Scope.CHANNEL,
    Kind.NUMBER,
    _PUBLISHER,
    "The channel's declared maximum rate (Hz).",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_RATE_HZ,
)
SIZE = Parameter(
    "message_size_in_bytes",
    Scope.CHANNEL,
    Kind.NUMBER,
    _PUBLISHER,
    "The serialised size of the channel's messages, as the publisher measures it.",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_SIZE_BYTES,
    column=Column("size B", ",.0f"),
)
PRIORITY = Parameter(
    "priority",
    Scope.CHANNEL,
    Kind.NUMBER,
    frozenset({Writer.OPERATOR, Writer.PUBLISHER}),
    "The channel's raw priority in [0, 1]: an operator's, or the robot's own priority source.",
    minimum=0.0,
    maximum=1.0,
    column=Column("priority", ".2f"),
)
CURRENT = Parameter(
    "frequency/current_value",
    Scope.CHANNEL,
    Kind.NUMBER,
    _OPTIMIZER,
    "The allocated rate, pushed by the optimizer to the publisher.",
    column=Column("allocated Hz", ".2f"),
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_RATE_HZ,
)
APPLIED = Parameter(
    "frequency/applied_value",
    Scope.CHANNEL,
    Kind.NUMBER,
    _PUBLISHER,
    "The rate the publisher is applying: its acknowledgement of ``current_value``.",
    minimum=0.0,
    exclusive_minimum=True,
    maximum=MAX_RATE_HZ,
)
SENT = Parameter(
    "frequency/sent_value",
    Scope.CHANNEL,
    Kind.NUMBER,
    _PUBLISHER,
    "The rate the publisher sent on ``[topic]/optimized`` over the optimizer's last period, "
    "written when it moves by a tenth or stops: what reaches the link (0: nothing, a driver "
    "that died).",
    minimum=0.0,
    maximum=MAX_RATE_HZ,
)
PREFERENCE = Parameter(
    "preference",
    Scope.CHANNEL,
    Kind.CHOICE,
    frozenset({Writer.OPERATOR, Writer.PUBLISHER}),
    "What a laddered channel gives up first when the budget is short: ``keep_rate`` (detail "
    "goes first), ``keep_detail`` (frames go first) or ``balanced``; set like the priority.",
    choices=tuple(p.value for p in Preference),
    column=Column("prefer", "", optional=True),
)
MIN_QUALITY = Parameter(
    "quality/min",
    Scope.CHANNEL,
    Kind.NUMBER,
    frozenset({Writer.OPERATOR, Writer.PUBLISHER}),
    "A laddered channel's quality floor in [0, 1]: rungs below it are never chosen.",
    minimum=0.0,
    maximum=1.0,
)
LADDER = Parameter(
    "ladder",
    Scope.CHANNEL,
    Kind.TEXT,
    _PUBLISHER,
    "The channel's ladder as the publisher measures it on its own frames: JSON, one "
    "``[size_bytes, quality, scale, jpeg_quality]`` a rung (``dbml.protocol.ladders``).",
    parse=decode_rungs,
)
ENCODING = Parameter(
    "encoding/current_value",
    Scope.CHANNEL,
    Kind.TEXT,
    _OPTIMIZER,
    "The rung chosen for a laddered channel, pushed with its rate: ``x0.5 q80 31234B`` (scale, "
    "JPEG quality, the bytes a frame may carry) or ``x1 raw``.",
    parse=parse_encoding,
    column=Column("encoding", "", optional=True),
)
ENCODING_APPLIED = Parameter(
    "encoding/applied_value",
    Scope.CHANNEL,
    Kind.TEXT,
    _PUBLISHER,
    "The encoding the publisher is applying: its acknowledgement of ``encoding/current_value``.",
    parse=parse_encoding,
)
MANAGED = Parameter(
    "managed",
    Scope.CHANNEL,
    Kind.BOOL,
    _OPTIMIZER,
    "Whether the optimizer manages the channel (a remote host subscribes).",
)

PARAMETERS: tuple[Parameter, ...] = (
    BANDWIDTH,
    UTILIZATION,
    PERIOD,
    STRATEGY,
    FRAME_HEADROOM,
    STATUS,
    STATUS_MESSAGE,
    ROUND,
    ESTIMATE,
    ESTIMATOR_STATE,
    MIN_RATE,
    MAX_RATE,
    PRIORITY,
    SIZE,
    CURRENT,
    APPLIED,
    SENT,
    PREFERENCE,
    MIN_QUALITY,
    LADDER,
    ENCODING,
    ENCODING_APPLIED,
    MANAGED,
)
"""Every parameter dbml reads or writes (those with a ``column`` in ``dbml monitor``'s order)."""

_GLOBALS: Mapping[str, Parameter] = {p.name: p for p in PARAMETERS if p.scope is Scope.GLOBAL}
_FIELDS: Mapping[str, Parameter] = {p.field: p for p in PARAMETERS if p.scope is Scope.CHANNEL}
_CHANNEL_SEGMENT = f"{GLOBAL_PREFIX}/"


def split_channel_name(name: str) -> tuple[str, str] | None:
    """``/r1/camera/dbm/priority`` as ``('/r1/camera', 'priority')``; None if not a channel's.

    The one reading of ``[topic]/dbm/<field>``: a channel's topic never holds a ``dbm``
    segment (``dbml.protocol.names.check_channel``), so the split is unambiguous.
    """
    topic, sep, tail = name.rpartition(_CHANNEL_SEGMENT)
    if not sep or not topic:
        return None
    return topic, tail


def lookup(name: str) -> tuple[Parameter, str | None] | None:
    """The parameter ``name`` is, and its channel's topic (None for a global); None if unknown."""
    parameter = _GLOBALS.get(name)
    if parameter is not None:
        return parameter, None
    split = split_channel_name(name)
    if split is None:
        return None
    parameter = _FIELDS.get(split[1])
    return None if parameter is None else (parameter, split[0])


def check_param_value(value: object) -> ParamValue:
    """``value`` if a store can hold it (a bool, number, string or ``None``), else an error."""
    if value is not None and not isinstance(value, bool | int | float | str):
        raise TransportError(
            f"parameter value={short_repr(value)} must be a bool, number or string"
        )
    return value


def check_param(name: str, value: ParamValue) -> ParamValue:
    """``value`` if it is valid for ``name`` (numbers as floats; None means unset).

    Raises ``ParamError`` naming the key and the value. Names dbml does not know pass unchanged:
    they are not dbml's to judge.
    """
    if value is None:
        return None
    found = lookup(name)
    if found is None:
        return value
    return found[0].check(value, name=name)


def ownership_table() -> str:
    """Every parameter as a Markdown table: name, values, who writes it (the README's)."""
    lines = ["| parameter | values | written by |", "|---|---|---|"]
    for parameter in PARAMETERS:
        name = (
            parameter.name if parameter.scope is Scope.GLOBAL else f"[topic]/{parameter.relative}"
        )
        lines.append(f"| `{name}` | {parameter.values} | {parameter.writers_text} |")
    return "\n".join(lines)
