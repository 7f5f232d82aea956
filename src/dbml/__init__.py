"""dbml: dynamic bandwidth management for multi-robot systems."""

from dbml.configfile import load_config
from dbml.core import (
    BYTES_PER_S_PER_MBIT,
    Allocation,
    ChannelAllocation,
    ChannelSpec,
    Config,
    ConfigError,
    DbmlError,
    DbmSettings,
    LinkSpec,
    Problem,
    SpecError,
    Status,
    Strategy,
    TransportError,
    allocate,
    collision_priority,
    linear_ramp,
    normalize_priorities,
    parse_config,
    time_to_collision_s,
)

__all__ = [
    "BYTES_PER_S_PER_MBIT",
    "Allocation",
    "ChannelAllocation",
    "ChannelSpec",
    "Config",
    "ConfigError",
    "DbmSettings",
    "DbmlError",
    "LinkSpec",
    "Problem",
    "SpecError",
    "Status",
    "Strategy",
    "TransportError",
    "allocate",
    "collision_priority",
    "linear_ramp",
    "load_config",
    "normalize_priorities",
    "parse_config",
    "time_to_collision_s",
]

__version__ = "0.1.0"
