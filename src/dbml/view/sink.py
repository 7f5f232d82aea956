"""Where the live view goes: a Foxglove WebSocket server, an MCAP recording, or both.

One ``foxglove.Context`` per sink, so its channels go to its own server and file (and two sinks
of one process do not mix). Every JSON channel carries its JSON schema (the app plots no field of
a schemaless one); images are ROS 2 ``sensor_msgs/msg/Image`` in CDR with the ``ros2msg`` schema,
so ROS 2 tools read the recording too. The server offers the Parameters capability: what a
client asks for and sets goes to a ``Settings`` (the view's), which validates it; a refused value
is answered with the value in force and said to the client as a status with its reason.

foxglove-sdk is the ``viz`` extra: import this module after ``require`` (``dbml.view.live`` does).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import foxglove
from foxglove.channels import LogChannel
from foxglove.messages import Log, Timestamp
from foxglove.messages import LogLevel as FoxgloveLevel
from foxglove.websocket import Capability, Client, ServerListener, StatusLevel

from dbml.core.errors import DbmlError, SpecError
from dbml.core.spec import short_repr
from dbml.protocol.schema import ParamValue
from dbml.transports.overflow import Overflow
from dbml.view.frames import LOG_TOPIC, LogLevel
from dbml.view.target import ViewEndpoint

__all__ = [
    "MAX_CHANNELS",
    "MAX_REFUSALS_PER_S",
    "MAX_SETTINGS_PER_REQUEST",
    "Settings",
    "Sink",
]

log = logging.getLogger("dbml.view")

MAX_CHANNELS = 4096
"""The most channels a sink advertises: they follow the live graph, which any peer can fill."""
MAX_SETTINGS_PER_REQUEST = 32
"""Values one ``setParameters`` may carry: the app sends the one a person edits; a flood is not."""
MAX_REFUSALS_PER_S = 10
"""Refusals said (log, ``/dbm/log``, status to every client) per second; past it, counted and
said with the next refusal after that second: a client that loops on bad values fills neither
disk nor links."""


class Settings(Protocol):
    """What the Parameters capability shows and sets."""

    def current(self) -> Mapping[str, ParamValue]:
        """Every settable name with its value in force (None: unset)."""

    def set(self, name: str, value: object) -> ParamValue:
        """Check and write ``value``; the value written, or ``SpecError`` saying why not."""


def _parameter(name: str, value: ParamValue) -> foxglove.Parameter:
    return foxglove.Parameter(name, value=value)


class _Listener(ServerListener):
    """The server's callbacks: the Parameters capability, through ``Settings``.

    Called on the SDK's threads: they only check and hand a write to the store (which never
    blocks its caller), and answer.
    """

    def __init__(self, settings: Settings, refused: Callable[[str], None]) -> None:
        self._settings = settings
        self._refused = refused

    def _values(self, wanted: Sequence[str]) -> list[foxglove.Parameter]:
        current = self._settings.current()
        shown = [n for n in wanted if n in current] if wanted else sorted(current)
        return [_parameter(n, current[n]) for n in shown if current[n] is not None]

    def on_get_parameters(
        self, client: Client, param_names: list[str], request_id: str | None = None
    ) -> list[foxglove.Parameter]:
        del client, request_id
        return self._values(param_names)

    def on_set_parameters(
        self,
        client: Client,
        parameters: list[foxglove.Parameter],
        request_id: str | None = None,
    ) -> list[foxglove.Parameter]:
        del client, request_id
        if len(parameters) > MAX_SETTINGS_PER_REQUEST:
            self._refused(
                f"refused: a setParameters of {len(parameters)} values "
                f"(at most {MAX_SETTINGS_PER_REQUEST}): none set"
            )
            return []
        for parameter in parameters:
            try:
                self._settings.set(parameter.name, parameter.get_value())
            except SpecError as err:
                self._refused(f"refused: {err}")
            except Exception:  # a value the SDK cannot hand over: refused, never a dead thread
                self._refused(f"refused: {short_repr(parameter.name)}: unreadable value")
        return self._values([p.name for p in parameters])


class Sink:
    """A Foxglove server and/or an MCAP file, with channels advertised as topics first appear."""

    def __init__(
        self,
        *,
        endpoint: ViewEndpoint | None,
        record: Path | None,
        settings: Settings | None = None,
        name: str = "dbml",
    ) -> None:
        self._endpoint = endpoint
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._full = Overflow("view channels", MAX_CHANNELS, log=log)
        self._log_channel = LogChannel(LOG_TOPIC, context=self._context)
        self._refusals_lock = threading.Lock()
        self._refusals_window = (0, 0, 0)
        """The refusals' second (monotonic s), how many were said in it, how many not."""
        self._server = None
        self._writer = None
        try:
            if record is not None:
                self._writer = foxglove.open_mcap(
                    record, allow_overwrite=True, context=self._context
                )
            if endpoint is not None:
                self._server = foxglove.start_server(
                    name=name,
                    host=endpoint.host,
                    port=endpoint.port,
                    capabilities=[Capability.Parameters] if settings is not None else [],
                    server_listener=None if settings is None else _Listener(settings, self.refused),
                    context=self._context,
                )
        except Exception as err:  # the SDK's own errors (an address in use) as one line
            self.close()
            where = f"--foxglove={endpoint}" if endpoint is not None else f"--record={record}"
            raise DbmlError(f"{where}: {err}") from None

    @property
    def address(self) -> ViewEndpoint | None:
        """Where the server listens (the port picked for port 0); None without a server."""
        if self._server is None or self._endpoint is None:
            return None
        return ViewEndpoint(self._endpoint.host, int(self._server.port))

    def _channel(self, topic: str, make: Any) -> foxglove.Channel | None:
        channel = self._channels.get(topic)
        if channel is None:
            if len(self._channels) >= MAX_CHANNELS:
                self._full.refuse()
                return None
            channel = self._channels[topic] = make()
        return channel

    def log_json(
        self, topic: str, schema: Mapping[str, Any], message: Mapping[str, Any], *, time_ns: int
    ) -> None:
        """A JSON message on ``topic`` (advertised with ``schema`` the first time)."""
        channel = self._channel(
            topic, lambda: foxglove.Channel(topic, schema=dict(schema), context=self._context)
        )
        if channel is not None:
            channel.log(dict(message), log_time=time_ns)

    def log_cdr(
        self, topic: str, schema_name: str, definition: str, payload: bytes, *, time_ns: int
    ) -> None:
        """A ROS 2 message in CDR on ``topic``, typed ``schema_name`` (``ros2msg`` text)."""

        def make() -> foxglove.Channel:
            schema = foxglove.Schema(name=schema_name, encoding="ros2msg", data=definition.encode())
            return foxglove.Channel(
                topic, schema=schema, message_encoding="cdr", context=self._context
            )

        channel = self._channel(topic, make)
        if channel is not None:
            channel.log(payload, log_time=time_ns)

    def log_text(self, level: LogLevel, message: str, *, time_ns: int) -> None:
        """A ``foxglove.Log`` line on ``/dbm/log``."""
        stamp = Timestamp(sec=time_ns // 1_000_000_000, nsec=time_ns % 1_000_000_000)
        severity = getattr(FoxgloveLevel, level.value)
        line = Log(timestamp=stamp, level=severity, message=message, name="dbml")
        self._log_channel.log(line, log_time=time_ns)

    def publish_parameters(self, values: Mapping[str, ParamValue]) -> None:
        """Tell subscribed clients the settable values that changed."""
        if self._server is not None and values:
            self._server.publish_parameter_values(
                [_parameter(n, v) for n, v in sorted(values.items()) if v is not None]
            )

    def refused(self, message: str) -> None:
        """A value refused: said to the clients as a warning status, on ``/dbm/log``, logged.

        At most ``MAX_REFUSALS_PER_S`` a second; the others are counted, and said in one line
        with the next refusal of a later second.
        """
        second = int(time.monotonic())
        with self._refusals_lock:
            start, said, unsaid = self._refusals_window
            if second != start:
                self._refusals_window = (second, 1, 0)
            elif said < MAX_REFUSALS_PER_S:
                self._refusals_window = (start, said + 1, unsaid)
            else:
                self._refusals_window = (start, said, unsaid + 1)
                return
        if second != start and unsaid:
            self._say(f"{unsaid} more refusals in the second before not shown")
        self._say(message)

    def _say(self, message: str) -> None:
        log.warning("%s", message)
        self.log_text(LogLevel.WARNING, message, time_ns=time.time_ns())
        server = self._server  # close() may clear it meanwhile (this runs on the SDK's thread)
        if server is not None:
            with contextlib.suppress(Exception):
                server.publish_status(message, StatusLevel.Warning)

    def close(self) -> None:
        """Stop the server and finish the recording (idempotent)."""
        server, writer = self._server, self._writer
        self._server = self._writer = None
        if server is not None:
            server.stop()
        if writer is not None:
            writer.close()
