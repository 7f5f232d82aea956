"""The ROS master's API, without rospy: plain XML-RPC.

Parameters and the graph can so be read and written from any Python (only topics need rospy).
"""

from __future__ import annotations

import http.client
import os
import threading
import xmlrpc.client
from typing import Any

from dbml.core.errors import TransportError

__all__ = [
    "ANSWER_TIMEOUT_S",
    "CALL_TIMEOUT_S",
    "DEFAULT_MASTER_URI",
    "ROSPY_MISSING",
    "MasterClient",
    "answers",
]

ROSPY_MISSING = (
    "dbml's ROS 1 support needs rospy, which comes from Debian's packages, not PyPI, and imports "
    "in Debian's Python: run scripts/install-ros1, then make (see the README's ROS 1 section)"
)
"""Why ROS 1 support cannot load here, and what to do (rospy is not on PyPI)."""
DEFAULT_MASTER_URI = "http://localhost:11311/"
"""Where a ROS master listens when ``ROS_MASTER_URI`` is not set."""
CALL_TIMEOUT_S = 2.0
"""How long one XML-RPC call may take before it counts as failed."""
ANSWER_TIMEOUT_S = 0.5
"""How long ``answers`` waits: a live master replies at once."""


class _TimeoutTransport(xmlrpc.client.Transport):
    def __init__(self, timeout_s: float) -> None:
        super().__init__()
        self._timeout_s = timeout_s

    def make_connection(self, host: Any) -> http.client.HTTPConnection:
        connection = super().make_connection(host)
        connection.timeout = self._timeout_s
        return connection


class MasterClient:
    """An XML-RPC API of the ROS master (or of a node), one connection per thread.

    Calls return the value of ``[code, message, value]``; failures raise ``TransportError``.
    """

    def __init__(
        self, uri: str | None = None, *, caller_id: str = "/dbml", timeout_s: float = CALL_TIMEOUT_S
    ) -> None:
        self.uri = uri or os.environ.get("ROS_MASTER_URI") or DEFAULT_MASTER_URI
        self.caller_id = caller_id
        self.timeout_s = timeout_s
        """How long one call may take."""
        self._local = threading.local()

    def _proxy(self) -> xmlrpc.client.ServerProxy:
        proxy = getattr(self._local, "proxy", None)
        if proxy is None:
            proxy = xmlrpc.client.ServerProxy(
                self.uri, transport=_TimeoutTransport(self.timeout_s), allow_none=True
            )
            self._local.proxy = proxy
        return proxy

    def call(self, method: str, *args: Any, missing_ok: bool = False) -> Any:
        """The call's value; with ``missing_ok`` a code of -1 (unknown key or node) is None."""
        try:
            code, message, value = getattr(self._proxy(), method)(self.caller_id, *args)
        except (OSError, xmlrpc.client.Error, http.client.HTTPException) as err:
            self._local.proxy = None
            raise TransportError(f"ROS API {self.uri}: {method} failed: {err}") from err
        if code != 1:
            if missing_ok and code == -1:
                return None
            raise TransportError(f"ROS API {self.uri}: {method}{args!r}: {message}")
        return value

    def reachable(self) -> bool:
        """Whether the API answers at all (``getPid``)."""
        try:
            self.call("getPid")
        except TransportError:
            return False
        return True

    def close(self) -> None:
        """Close this thread's connection (each thread's closes when the thread ends)."""
        proxy = getattr(self._local, "proxy", None)
        self._local.proxy = None
        if proxy is not None:
            proxy("close")()

    def __enter__(self) -> MasterClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def answers(uri: str) -> bool:
    """Whether a master (or node) answers at ``uri`` within half a second."""
    with MasterClient(uri, timeout_s=ANSWER_TIMEOUT_S) as client:
        return client.reachable()
