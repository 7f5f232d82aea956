"""The pure core of dbml: specs, priorities, allocation strategies and config parsing."""

from dbml.core.allocation import Allocation, ChannelAllocation, Status, Strategy, allocate
from dbml.core.config import Config, DbmSettings, parse_config
from dbml.core.errors import (
    ConfigError,
    DbmlError,
    MissingExtraError,
    SpecError,
    TransportError,
)
from dbml.core.ladder import Ladder, Preference, Rung
from dbml.core.priority import (
    collision_priority,
    linear_ramp,
    normalize_priorities,
    time_to_collision_s,
)
from dbml.core.quality import QualityAllocation, QualityStatus, allocate_quality
from dbml.core.spec import BYTES_PER_S_PER_MBIT, ChannelSpec, LinkSpec, Problem

__all__ = [
    "BYTES_PER_S_PER_MBIT",
    "Allocation",
    "ChannelAllocation",
    "ChannelSpec",
    "Config",
    "ConfigError",
    "DbmSettings",
    "DbmlError",
    "Ladder",
    "LinkSpec",
    "MissingExtraError",
    "Preference",
    "Problem",
    "QualityAllocation",
    "QualityStatus",
    "Rung",
    "SpecError",
    "Status",
    "Strategy",
    "TransportError",
    "allocate",
    "allocate_quality",
    "collision_priority",
    "linear_ramp",
    "normalize_priorities",
    "parse_config",
    "time_to_collision_s",
]
