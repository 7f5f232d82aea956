"""A Foxglove WebSocket client, as the app speaks it (``foxglove.sdk.v1``): the view, headless.

It subscribes to every channel the server advertises and keeps every message with its log time;
control messages (``status``, ``parameterValues``) are kept in order. Single-threaded: ``pump``
reads until a condition holds or its time is up. The tests read dbml's live view with it, and
the benchmarks load it as the app would; it needs ``websockets`` (the ``viz`` extra).
"""

from __future__ import annotations

import contextlib
import json
import struct
import time
from collections.abc import Callable
from typing import Any

from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from dbml.core.errors import TransportError

__all__ = ["MESSAGE_DATA", "SUBPROTOCOL", "FoxgloveClient"]

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01
"""The opcode of a binary frame carrying a channel's message."""
_HEADER = struct.Struct("<BIQ")
"""A message frame's header: opcode, subscription id, log time (ns)."""
_RECV_S = 0.2
"""How long one read waits, so ``pump`` looks at its condition and its time often enough."""
_OPEN_S = 2.0
"""How long one connection attempt may take."""
_RETRY_S = 0.1
"""How long to wait before trying again to reach a server that is not up yet."""


class FoxgloveClient:
    """One connection, every channel subscribed; a context manager.

    ``TransportError`` naming the URL when no server answers within ``timeout_s``.
    """

    def __init__(self, url: str, *, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        last: Exception | None = None
        self.ws: ClientConnection | None = None
        self._stack = contextlib.ExitStack()
        while time.monotonic() < deadline:
            try:
                self.ws = self._stack.enter_context(
                    connect(url, subprotocols=[Subprotocol(SUBPROTOCOL)], open_timeout=_OPEN_S)
                )
                break
            except (OSError, TimeoutError, WebSocketException) as err:  # not up yet
                last = err
                time.sleep(_RETRY_S)
        if self.ws is None:
            raise TransportError(f"no Foxglove server at {url} within {timeout_s} s: {last}")
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[int, dict[str, Any]] = {}
        """Advertised channels by id (each with ``topic``, ``encoding``, ``schemaName``)."""
        self.messages: dict[str, list[tuple[int, bytes]]] = {}
        """Per topic, ``(log time ns, payload)`` in arrival order."""
        self.control: list[dict[str, Any]] = []
        self._subscriptions: dict[int, str] = {}

    def close(self) -> None:
        """Close the connection."""
        self._stack.close()

    def __enter__(self) -> FoxgloveClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def send(self, message: dict[str, Any]) -> None:
        """A JSON control message (``allow_nan``: a client may send a NaN literal)."""
        assert self.ws is not None
        self.ws.send(json.dumps(message, allow_nan=True))

    def _take(self, frame: str | bytes) -> None:
        if isinstance(frame, bytes):
            if frame and frame[0] == MESSAGE_DATA:
                _, subscription, log_time = _HEADER.unpack_from(frame)
                topic = self._subscriptions[subscription]
                self.messages.setdefault(topic, []).append((log_time, frame[_HEADER.size :]))
            return
        message = json.loads(frame)
        op = message.get("op")
        if op == "serverInfo":
            self.server_info = message
        elif op == "advertise":
            fresh = []
            for channel in message["channels"]:
                self.channels[channel["id"]] = channel
                self._subscriptions[channel["id"]] = channel["topic"]
                fresh.append({"id": channel["id"], "channelId": channel["id"]})
            self.send({"op": "subscribe", "subscriptions": fresh})
        elif op == "unadvertise":
            for channel_id in message["channelIds"]:
                self.channels.pop(channel_id, None)
        else:
            self.control.append(message)

    def pump(self, until: Callable[[], bool], *, timeout_s: float) -> bool:
        """Read until ``until()`` holds (True) or ``timeout_s`` passes (False)."""
        assert self.ws is not None
        deadline = time.monotonic() + timeout_s
        while not until():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                self._take(self.ws.recv(timeout=min(left, _RECV_S)))
            except TimeoutError:
                continue
            except ConnectionClosed:
                return until()
        return True

    def topics(self) -> set[str]:
        """The topics of the channels advertised now."""
        return {channel["topic"] for channel in self.channels.values()}

    def json_messages(self, topic: str) -> list[dict[str, Any]]:
        """Every message of ``topic`` so far, parsed as JSON."""
        return [json.loads(payload) for _, payload in self.messages.get(topic, [])]

    def set_parameter(self, request_id: str, name: str, value: object) -> None:
        """Ask the server to set parameter ``name``, as the app's Parameters panel does."""
        self.send(
            {
                "op": "setParameters",
                "parameters": [{"name": name, "value": value}],
                "id": request_id,
            }
        )

    def answer(self, request_id: str) -> dict[str, Any] | None:
        """The ``parameterValues`` that answered ``request_id``, if it came."""
        for message in self.control:
            if message.get("op") == "parameterValues" and message.get("id") == request_id:
                return message
        return None

    def statuses(self) -> list[str]:
        """The texts of the server's status messages so far."""
        return [m["message"] for m in self.control if m.get("op") == "status"]
