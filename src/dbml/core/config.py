"""The YAML config file, in the paper's parameter names, converted once into specs.

::

    dbm:
      max_bandwidth_in_mbit: 11          # required, > 0 (1 Mbit = 10^6 bit)
      max_bandwidth_utilization: 1.0     # optional, 0 < u <= 1, default 1
      optimization_rate_in_seconds: 1.0  # optional, > 0, default 1
      strategy: paper                    # optional: paper | static | fair | lp
    channels:                            # at least one (optional where channels come live)
      - topic: /r1/camera
        frequency: {min: 1, max: 16}
        message_size_in_bytes: 84000
        priority: 0.0                    # optional, default 0
    links:                               # optional, strategy lp only
      - {name: r1-uplink, max_bandwidth_in_mbit: 6, channels: [/r1/camera]}

``dbml bridge --config`` reads the same ``channels:`` entries, where ``message_size_in_bytes`` is
optional (the bridge measures it) and ``type: sensor_msgs/msg/Image`` may name the message type.

Parsing is pure (text in, specs out); ``_read_text`` is the one function that reads a file.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from dbml.core.allocation import Strategy
from dbml.core.errors import ConfigError, SpecError
from dbml.core.spec import (
    MAX_BANDWIDTH_MBIT,
    MAX_PERIOD_S,
    MIN_PERIOD_S,
    ChannelSpec,
    LinkSpec,
    Problem,
    check_number,
)

__all__ = [
    "LADDER_TYPE",
    "MAX_CONFIG_BYTES",
    "MAX_CONFIG_DEPTH",
    "BridgeChannel",
    "Config",
    "DbmSettings",
    "check_msg_type",
    "load_bridge_channels",
    "load_config",
    "parse_bridge_channels",
    "parse_config",
]

MAX_CONFIG_BYTES = 1 << 20
"""1 MiB: far above any fleet's config; a larger file is not a config."""
MAX_CONFIG_DEPTH = 16
"""The deepest nesting a config may have (it needs 4)."""
LADDER_TYPE = "sensor_msgs/msg/Image"
"""The one type a laddered channel carries (its managed copy is a ``CompressedImage``)."""


_POSITIVE: dict[str, Any] = {"minimum": 0, "exclusive_minimum": True}
_FRACTION: dict[str, Any] = {"minimum": 0, "maximum": 1, "exclusive_minimum": True}


@dataclass(frozen=True, slots=True)
class DbmSettings:
    """The ``dbm:`` section: budget, optimisation period and strategy (validated here)."""

    max_bandwidth_mbit: float
    utilization: float = 1.0
    optimization_period_s: float = 1.0
    strategy: Strategy = Strategy.PAPER
    frame_headroom: bool = False
    """Keep one message per channel but the largest out of the budget (``Problem``'s)."""

    def __post_init__(self) -> None:
        owner = "dbm"
        field = "max_bandwidth_in_mbit"
        bandwidth = check_number(self.max_bandwidth_mbit, field=field, owner=owner, **_POSITIVE)
        check_number(bandwidth, field=field, owner=owner, maximum=MAX_BANDWIDTH_MBIT)
        utilization = check_number(
            self.utilization, field="max_bandwidth_utilization", owner=owner, **_FRACTION
        )
        field = "optimization_rate_in_seconds"
        period = check_number(self.optimization_period_s, field=field, owner=owner, **_POSITIVE)
        check_number(period, field=field, owner=owner, minimum=MIN_PERIOD_S, maximum=MAX_PERIOD_S)
        object.__setattr__(self, "max_bandwidth_mbit", bandwidth)
        object.__setattr__(self, "utilization", utilization)
        object.__setattr__(self, "optimization_period_s", period)
        object.__setattr__(self, "strategy", _strategy(f"{owner}: strategy", self.strategy))
        if not isinstance(self.frame_headroom, bool):
            raise ConfigError(f"dbm: frame_headroom={self.frame_headroom!r} must be true or false")


@dataclass(frozen=True, slots=True)
class Config:
    """A whole config file: settings, channels and links."""

    dbm: DbmSettings
    channels: tuple[ChannelSpec, ...] = ()
    links: tuple[LinkSpec, ...] = ()

    def problem(self) -> Problem:
        """The allocation problem this config describes (raises if it has no channels)."""
        if not self.channels:
            raise ConfigError("config: channels is empty; at least one channel is required")
        return Problem(
            channels=self.channels,
            bandwidth_mbit=self.dbm.max_bandwidth_mbit,
            utilization=self.dbm.utilization,
            frame_headroom=self.dbm.frame_headroom,
            links=self.links,
        )


def _mapping(where: str, value: object, allowed: set[str], required: set[str]) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {value!r}")
    for key in value:
        if key not in allowed:
            raise ConfigError(
                f"{where}: unknown key {key!r} (allowed: {', '.join(sorted(allowed))})"
            )
    for key in sorted(required):
        if key not in value:
            raise ConfigError(f"{where}: missing required key {key!r}")
    return dict(value)


def _number(where: str, field: str, value: object, **bounds: Any) -> float:
    try:
        return check_number(value, field=field, owner=where, **bounds)
    except SpecError as err:
        raise ConfigError(str(err)) from None


def _dbm(value: object) -> DbmSettings:
    where = "dbm"
    data = _mapping(
        where,
        value,
        {
            "max_bandwidth_in_mbit",
            "max_bandwidth_utilization",
            "optimization_rate_in_seconds",
            "strategy",
            "frame_headroom",
        },
        {"max_bandwidth_in_mbit"},
    )
    try:
        return DbmSettings(
            data["max_bandwidth_in_mbit"],
            data.get("max_bandwidth_utilization", 1.0),
            data.get("optimization_rate_in_seconds", 1.0),
            data.get("strategy", Strategy.PAPER.value),
            data.get("frame_headroom", False),
        )
    except SpecError as err:
        raise ConfigError(str(err)) from None


def _strategy(field: str, value: object) -> Strategy:
    known = {s.value: s for s in Strategy}
    if isinstance(value, str) and value in known:
        return known[value]
    raise ConfigError(f"{field}={value!r} is not one of {' | '.join(known)}")


def _where(section: str, index: int, value: object, label: str) -> str:
    """``channels[1] '/r2/camera'``: the position, and the item's name when it has one."""
    where = f"{section}[{index}]"
    if isinstance(value, Mapping) and isinstance(value.get(label), str):
        where += f" {value[label]!r}"
    return where


def _channel(index: int, value: object) -> ChannelSpec:
    where = _where("channels", index, value, "topic")
    data = _mapping(
        where,
        value,
        {"topic", "frequency", "message_size_in_bytes", "priority"},
        {"topic", "frequency", "message_size_in_bytes"},
    )
    topic, fmin, fmax = _topic_and_bounds(where, data)
    size = _number(where, "message_size_in_bytes", data["message_size_in_bytes"])
    priority = _number(where, "priority", data.get("priority", 0.0))
    try:
        return ChannelSpec(topic, fmin, fmax, size, priority)
    except SpecError as err:
        # ChannelSpec names the channel already; keep the config position in front.
        raise ConfigError(f"channels[{index}] {err}") from None


def _link(index: int, value: object) -> LinkSpec:
    where = _where("links", index, value, "name")
    data = _mapping(
        where,
        value,
        {"name", "max_bandwidth_in_mbit", "channels"},
        {"name", "max_bandwidth_in_mbit", "channels"},
    )
    topics = data["channels"]
    if not isinstance(topics, list) or not all(isinstance(t, str) for t in topics):
        raise ConfigError(f"{where}: channels={topics!r} must be a list of topics")
    capacity = _number(where, "max_bandwidth_in_mbit", data["max_bandwidth_in_mbit"])
    try:
        return LinkSpec(str(data["name"]), capacity, tuple(topics))
    except SpecError as err:
        raise ConfigError(f"links[{index}] {err}") from None


class _StrictLoader(yaml.SafeLoader):
    """A safe loader that refuses a key given twice (YAML would keep the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[object] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _load_yaml(text: str, source: str) -> object:
    """The document, after a pass over its events that refuses aliases and deep nesting.

    A config needs neither; an alias bomb or 50,000 nested lists would otherwise exhaust memory
    or the stack before any field is checked.
    """
    try:
        depth = 0
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent):
                raise ConfigError(f"{source}: YAML aliases (*{event.anchor}) are not allowed")
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_CONFIG_DEPTH:
                    raise ConfigError(f"{source}: nested deeper than {MAX_CONFIG_DEPTH} levels")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
        return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader: no arbitrary objects
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        reason = getattr(err, "problem", None) or type(err).__name__
        raise ConfigError(f"{source}: invalid YAML{at}: {reason}") from None


def parse_config(
    text: str,
    *,
    source: str = "<config>",
    require_channels: bool = True,
    strategy: Strategy | str | None = None,
) -> Config:
    """Parse and validate a config document; every error names the field and the value.

    ``require_channels=False`` accepts a config with only the ``dbm:`` section, for an optimizer
    whose channels are announced live by the publishers. ``strategy`` overrides
    ``dbm.strategy`` (the CLI's ``--strategy``) before the links are checked against it.
    """
    document = _load_yaml(text, source)
    top = _mapping(source, document, {"dbm", "channels", "links"}, {"dbm"})
    dbm = _dbm(top["dbm"])
    if strategy is not None:
        dbm = replace(dbm, strategy=_strategy("strategy", strategy))
    raw_channels = top.get("channels")
    if raw_channels is None:
        raw_channels = []
    if not isinstance(raw_channels, list):
        raise ConfigError(f"{source}: channels={raw_channels!r} must be a list")
    if require_channels and not raw_channels:
        raise ConfigError(
            f"{source}: channels is missing or empty; at least one channel is required"
        )
    channels = tuple(_channel(i, c) for i, c in enumerate(raw_channels))
    seen: set[str] = set()
    for i, channel in enumerate(channels):
        if channel.topic in seen:
            raise ConfigError(f"channels[{i}] {channel.topic!r}: topic is declared twice")
        seen.add(channel.topic)
    raw_links = top.get("links") or []
    if not isinstance(raw_links, list):
        raise ConfigError(f"{source}: links={raw_links!r} must be a list")
    links = tuple(_link(i, link) for i, link in enumerate(raw_links))
    if links and dbm.strategy is not Strategy.LP:
        raise ConfigError(
            f"links[0] {links[0].name!r}: links need strategy 'lp', "
            f"but dbm.strategy={dbm.strategy.value!r}"
        )
    names: set[str] = set()
    for i, link in enumerate(links):
        if link.name in names:
            raise ConfigError(f"links[{i}] {link.name!r}: name is declared twice")
        names.add(link.name)
        for topic in link.topics:
            if topic not in seen and channels:
                raise ConfigError(
                    f"links[{i}] {link.name!r}: channels lists unknown topic {topic!r}"
                )
    return Config(dbm=dbm, channels=channels, links=links)


def _read_text(path: str | Path) -> str:
    """A config file's text; an unreadable or oversized file is a ``ConfigError`` naming it."""
    try:
        with Path(path).open("rb") as file:
            data = file.read(MAX_CONFIG_BYTES + 1)  # /dev/zero must not fill the memory
        if len(data) > MAX_CONFIG_BYTES:
            raise ConfigError(f"config {str(path)!r}: larger than {MAX_CONFIG_BYTES:,} bytes")
        text = data.decode("utf-8")
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise ConfigError(f"config {str(path)!r}: cannot read: {reason}") from None
    return text


def load_config(
    path: str | Path, *, require_channels: bool = True, strategy: Strategy | str | None = None
) -> Config:
    """Read and validate a YAML config; an unreadable file is a ``ConfigError`` naming the path."""
    text = _read_text(path)
    return parse_config(
        text,
        source=f"config {str(path)!r}",
        require_channels=require_channels,
        strategy=strategy,
    )


_MSG_TYPE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*/(msg/)?[A-Za-z][A-Za-z0-9_]*$")
"""``pkg/msg/Name`` (ROS 2) or ``pkg/Name`` (ROS 1)."""


def check_msg_type(msg_type: object, *, field: str = "type") -> str:
    """``msg_type`` if it is shaped like a ROS message type, else a ``SpecError`` naming it."""
    if not isinstance(msg_type, str) or not _MSG_TYPE.match(msg_type):
        raise SpecError(f"{field}={msg_type!r} must look like 'sensor_msgs/msg/Image'")
    return msg_type


@dataclass(frozen=True, slots=True)
class BridgeChannel:
    """One topic ``dbml bridge`` puts under management: its bounds, priority and type.

    No size: the bridge measures what it forwards. ``priority`` None keeps whatever is set.
    ``msg_type`` None means: as the graph shows it (where topics are typed).
    """

    topic: str
    min_rate_hz: float
    max_rate_hz: float
    priority: float | None = None
    msg_type: str | None = None
    ladder: bool = False
    """A camera's: its frames go as JPEG at the rung the optimizer chooses, with a ladder
    measured on them (``sensor_msgs/msg/Image`` only, the type it implies)."""

    def __post_init__(self) -> None:
        # The same rules and messages as a channel of the allocation problem.
        spec = ChannelSpec(
            self.topic,
            self.min_rate_hz,
            self.max_rate_hz,
            1.0,
            0.0 if self.priority is None else self.priority,
        )
        object.__setattr__(self, "min_rate_hz", spec.min_rate_hz)
        object.__setattr__(self, "max_rate_hz", spec.max_rate_hz)
        if self.priority is not None:
            object.__setattr__(self, "priority", spec.priority)
        if self.msg_type is not None:
            check_msg_type(self.msg_type, field=f"channel {self.topic!r}: type")
        if self.ladder:
            if self.msg_type is None:
                object.__setattr__(self, "msg_type", LADDER_TYPE)
            elif self.msg_type != LADDER_TYPE:
                raise SpecError(
                    f"channel {self.topic!r}: type={self.msg_type!r} cannot be laddered: "
                    f"only {LADDER_TYPE} is (rgb8, bgr8, mono8)"
                )


def _topic_and_bounds(where: str, data: dict[str, object]) -> tuple[str, float, float]:
    """A channel entry's topic and ``frequency: {min, max}``, as every channel list reads them."""
    topic = data["topic"]
    if not isinstance(topic, str) or not topic.startswith("/") or topic.strip() != topic:
        raise ConfigError(f"{where}: topic={topic!r} must be a string starting with '/'")
    frequency = _mapping(f"{where}: frequency", data["frequency"], {"min", "max"}, {"min", "max"})
    fmin = _number(where, "frequency.min", frequency["min"])
    fmax = _number(where, "frequency.max", frequency["max"])
    return topic, fmin, fmax


def _bridge_channel(index: int, value: object) -> BridgeChannel:
    where = _where("channels", index, value, "topic")
    data = _mapping(
        where,
        value,
        {"topic", "frequency", "message_size_in_bytes", "priority", "type", "ladder"},
        {"topic", "frequency"},
    )
    topic, fmin, fmax = _topic_and_bounds(where, data)
    if "message_size_in_bytes" in data:  # accepted for a shared config; the bridge measures it
        _number(where, "message_size_in_bytes", data["message_size_in_bytes"], **_POSITIVE)
    priority = data.get("priority")
    if priority is not None:
        priority = _number(where, "priority", priority)
    msg_type = data.get("type")
    ladder = data.get("ladder", False)
    if not isinstance(ladder, bool):
        raise ConfigError(f"{where}: ladder={ladder!r} must be true or false")
    try:
        if msg_type is not None:
            check_msg_type(msg_type)
        return BridgeChannel(topic, fmin, fmax, priority, msg_type, ladder)
    except SpecError as err:
        raise ConfigError(f"{where}: {err}") from None


def parse_bridge_channels(text: str, *, source: str = "<config>") -> tuple[BridgeChannel, ...]:
    """The ``channels:`` of a config document, as ``dbml bridge`` reads them (at least one).

    ``dbm:`` and ``links:`` may be there (one file for a fleet) and are the optimizer's business.
    """
    document = _load_yaml(text, source)
    top = _mapping(source, document, {"dbm", "channels", "links"}, {"channels"})
    raw = top["channels"]
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{source}: channels={raw!r} must be a non-empty list")
    channels = tuple(_bridge_channel(i, c) for i, c in enumerate(raw))
    seen: set[str] = set()
    for i, channel in enumerate(channels):
        if channel.topic in seen:
            raise ConfigError(f"channels[{i}] {channel.topic!r}: topic is declared twice")
        seen.add(channel.topic)
    return channels


def load_bridge_channels(path: str | Path) -> tuple[BridgeChannel, ...]:
    """Read the channels ``dbml bridge --config`` puts under management."""
    return parse_bridge_channels(_read_text(path), source=f"config {str(path)!r}")
