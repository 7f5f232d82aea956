"""Transports: the middleware adapters behind one small interface, found by name."""

from dbml.transports.base import (
    GraphEntry,
    GraphView,
    Handle,
    ParamStore,
    ParamValue,
    Publisher,
    Role,
    Sample,
    Transport,
    TransportBase,
    TransportPriority,
    Variant,
    check_topic,
    resolve_host,
)
from dbml.transports.memory import ManualClock, MemoryNetwork, MemoryTransport
from dbml.transports.registry import (
    DEFAULT_TRANSPORT,
    TRANSPORTS,
    TransportEntry,
    open_transport,
)

__all__ = [
    "DEFAULT_TRANSPORT",
    "TRANSPORTS",
    "GraphEntry",
    "GraphView",
    "Handle",
    "ManualClock",
    "MemoryNetwork",
    "MemoryTransport",
    "ParamStore",
    "ParamValue",
    "Publisher",
    "Role",
    "Sample",
    "Transport",
    "TransportBase",
    "TransportEntry",
    "TransportPriority",
    "Variant",
    "check_topic",
    "open_transport",
    "resolve_host",
]
