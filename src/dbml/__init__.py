"""dbml: dynamic bandwidth management for multi-robot systems.

The names a user needs, from one place: the model (specs, ``allocate``, config), the errors, and
the runtime (managed publisher and subscriber, the optimizer node, transports by name). The
runtime's names load on first use, so ``import dbml.core`` stays free of threads and middleware.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbml.core.allocation import Allocation, Status, Strategy, allocate
from dbml.core.config import Config, DbmSettings, load_config, parse_config
from dbml.core.errors import (
    ConfigError,
    DbmlError,
    MissingExtraError,
    SpecError,
    TransportError,
)
from dbml.core.lazy import lazy_names
from dbml.core.priority import collision_priority, time_to_collision_s
from dbml.core.spec import ChannelSpec, LinkSpec, Problem

if TYPE_CHECKING:
    from dbml.runtime.optimizer import OptimizerNode
    from dbml.runtime.publisher import ManagedPublisher
    from dbml.runtime.subscriber import ManagedSubscriber
    from dbml.transports.memory import MemoryNetwork
    from dbml.transports.registry import open_transport

__all__ = [
    "Allocation",
    "ChannelSpec",
    "Config",
    "ConfigError",
    "DbmSettings",
    "DbmlError",
    "LinkSpec",
    "ManagedPublisher",
    "ManagedSubscriber",
    "MemoryNetwork",
    "MissingExtraError",
    "OptimizerNode",
    "Problem",
    "SpecError",
    "Status",
    "Strategy",
    "TransportError",
    "allocate",
    "collision_priority",
    "load_config",
    "open_transport",
    "parse_config",
    "time_to_collision_s",
]

__version__ = "0.1.0"

_LAZY = {
    "ManagedPublisher": "dbml.runtime.publisher",
    "ManagedSubscriber": "dbml.runtime.subscriber",
    "MemoryNetwork": "dbml.transports.memory",
    "OptimizerNode": "dbml.runtime.optimizer",
    "open_transport": "dbml.transports.registry",
}


__getattr__ = lazy_names(__name__, _LAZY)
