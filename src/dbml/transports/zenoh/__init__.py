"""The zenoh transport: eclipse-zenoh in peer mode.

``transport`` is the session and its graph, ``keyed`` the parameter store's messages over keys
(pure), ``params`` the store's sync over the session.

The transport class is imported on first use: importing the package, or a part of it that
needs no middleware, never loads zenoh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dbml.core.lazy import lazy_names

if TYPE_CHECKING:
    from dbml.transports.zenoh.transport import ZenohTransport

__all__ = ["ZenohTransport"]


__getattr__ = lazy_names(__name__, {"ZenohTransport": "dbml.transports.zenoh.transport"})
