"""The zenoh transport: the default real engine (eclipse-zenoh, peer mode).

With no flags, processes on one machine find each other over loopback without multicast: each
session tries to listen on a well-known port (non-fatal if taken) and on a port of its own, and
connects to the well-known port with retry; gossip then meshes everyone, and a newcomer re-forms
the rendezvous if its holder exits. ``connect`` / ``listen`` endpoints, or a zenoh config file,
span machines. Shared memory is off unless asked for: it would bypass any shaped link.

Key layout: topic ``/r1/camera`` is key ``r1/camera`` (and ``r1/camera/optimized``); parameter
``/r1/camera/dbm/priority`` is ``dbml/param/r1/camera/dbm/priority``; graph declarations are
liveliness tokens ``dbml/graph/<role>/<host>/<uid>/<variant>/<topic>``. Parameters are
replicated: every session caches every write, answers queries from its cache, and the newest
write (stamp, then writer) wins.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from dbml.core.errors import TransportError
from dbml.transports.base import (
    Closer,
    GraphEntry,
    Handle,
    ParamValue,
    Role,
    Sample,
    Variant,
    check_param_value,
    check_topic,
    decode_param,
    encode_param,
    resolve_host,
)

try:
    import zenoh
except ImportError as err:  # pragma: no cover - eclipse-zenoh is a declared dependency
    raise TransportError(
        "the zenoh transport needs eclipse-zenoh: pip install 'eclipse-zenoh>=1.10'"
    ) from err

__all__ = ["DEFAULT_PORT", "ZenohTransport"]

log = logging.getLogger("dbml.zenoh")

DEFAULT_PORT = 17447
"""The loopback rendezvous port of the no-flags mode; ``DBML_ZENOH_PORT`` overrides it."""

_PARAM = "dbml/param"
_GRAPH = "dbml/graph"
_NODE = "dbml/node"


def _data_key(topic: str, variant: Variant) -> str:
    return variant.key(check_topic(topic))[1:]


def _param_key(name: str) -> str:
    return _PARAM + check_topic(name)


def _config(
    *,
    connect: Iterable[str],
    listen: Iterable[str],
    config_file: str | Path | None,
    shared_memory: bool,
    port: int,
) -> Any:
    connect, listen = list(connect), list(listen)
    try:
        config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()

        def put(key: str, value: str) -> None:
            config.insert_json5(key, value)

        if not config_file:
            put("mode", '"peer"')
        put("scouting/multicast/enabled", "false")
        put("scouting/delay", "0")
        put("transport/shared_memory/enabled", "true" if shared_memory else "false")
        if connect or listen:
            if listen:
                put("listen/endpoints", _json_list(listen))
            if connect:
                put("connect/endpoints", _json_list(connect))
                put("connect/exit_on_failure", "false")
                put("connect/timeout_ms", "-1")
                put("connect/retry", "{period_init_ms: 100, period_max_ms: 1000}")
        elif not config_file:
            rendezvous = f"tcp/127.0.0.1:{port}"
            put("listen/endpoints", _json_list([rendezvous, "tcp/127.0.0.1:0"]))
            put("listen/exit_on_failure", "false")
            put("listen/timeout_ms", "0")  # never retry a listen: close() would hang 10 s
            put("connect/endpoints", _json_list([rendezvous]))
            put("connect/exit_on_failure", "false")
            put("connect/timeout_ms", "-1")
            put("connect/retry", "{period_init_ms: 100, period_max_ms: 500}")
    except (zenoh.ZError, OSError) as err:
        raise TransportError(f"zenoh config: {err}") from err
    return config


def _json_list(items: list[str]) -> str:
    for item in items:
        if "/" not in item or '"' in item:
            raise TransportError(f"endpoint={item!r} must look like 'tcp/192.168.1.2:7447'")
    return "[" + ", ".join(f'"{item}"' for item in items) + "]"


class _Watchers:
    """Callbacks to notify, safe to add and remove from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._items: list[Callable[..., None]] = []

    def add(self, fn: Callable[..., None]) -> Handle:
        with self._lock:
            self._items.append(fn)

        def remove() -> None:
            with self._lock:
                if fn in self._items:
                    self._items.remove(fn)

        return Closer(remove)

    def fire(self, *args: object) -> None:
        with self._lock:
            items = list(self._items)
        for fn in items:
            try:
                fn(*args)
            except Exception:
                log.exception("watcher %r failed", fn)


class _ZenohPublisher:
    def __init__(self, session: Any, topic: str, variant: Variant) -> None:
        self.topic = topic
        self._publisher = session.declare_publisher(
            _data_key(topic, variant), congestion_control=zenoh.CongestionControl.DROP
        )
        self._matching = bool(self._publisher.matching_status.matching)
        self._listener = self._publisher.declare_matching_listener(self._on_matching)

    def _on_matching(self, status: Any) -> None:
        self._matching = bool(status.matching)

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self._publisher.put(payload, attachment=attachment)

    @property
    def has_subscribers(self) -> bool:
        return self._matching

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):  # the session may be closed already
            self._listener.undeclare()
            self._publisher.undeclare()


class _ZenohParams:
    def __init__(self, transport: ZenohTransport) -> None:
        self._transport = transport
        self._lock = threading.Lock()
        self._values: dict[str, tuple[ParamValue, int, str]] = {}
        self.watchers = _Watchers()
        self._replier = transport.node_id.encode()

    def _merge(self, name: str, value: ParamValue, stamp: int, writer: str) -> bool:
        with self._lock:
            old = self._values.get(name)
            if old is not None and (old[1], old[2]) >= (stamp, writer):
                return False
            self._values[name] = (value, stamp, writer)
        return True

    def set(self, name: str, value: ParamValue) -> None:
        check_param_value(value)
        key = _param_key(name)
        stamp = time.time_ns()
        writer = self._transport.node_id
        self._merge(name, value, stamp, writer)
        # Control traffic: never dropped behind bulk data (which uses DROP), and sent ahead of it.
        self._transport.session.put(
            key,
            encode_param(value, stamp, writer),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        self.watchers.fire(name, value)

    def get(self, name: str) -> ParamValue:
        with self._lock:
            entry = self._values.get(name)
        return None if entry is None else entry[0]

    def stamp(self, name: str) -> tuple[int, str] | None:
        with self._lock:
            entry = self._values.get(name)
        return None if entry is None else (entry[1], entry[2])

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        with self._lock:
            return {
                name: value
                for name, (value, _, _) in self._values.items()
                if name.startswith(prefix) and value is not None
            }

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        return self.watchers.add(callback)

    # -- the wire -----------------------------------------------------------------------------

    def on_sample(self, sample: Any) -> None:
        self._accept(str(sample.key_expr), sample.payload.to_bytes(), notify=True)

    def _accept(self, key: str, data: bytes, *, notify: bool) -> None:
        try:
            value, stamp, writer = decode_param(data)
        except TransportError as err:
            log.warning("ignoring %s: %s", key, err)
            return
        if writer == self._transport.node_id:
            return  # our own write, already applied in set()
        name = key[len(_PARAM) :]
        if self._merge(name, value, stamp, writer) and notify:
            self.watchers.fire(name, value)

    def on_query(self, query: Any) -> None:
        with self._lock:
            values = list(self._values.items())
        for name, (value, stamp, writer) in values:
            key = _PARAM + name
            if query.key_expr.intersects(zenoh.KeyExpr(key)):
                query.reply(key, encode_param(value, stamp, writer), attachment=self._replier)

    def sync(self, timeout_s: float = 2.0) -> None:
        """Fetch every parameter the reachable sessions hold (newest wins)."""
        replies = self._transport.session.get(
            f"{_PARAM}/**",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout_s,
        )
        for reply in replies:
            if reply.ok is not None:
                self._accept(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), notify=True)


class _ZenohGraph:
    def __init__(self, transport: ZenohTransport) -> None:
        self._transport = transport
        self._lock = threading.Lock()
        self._entries: dict[str, GraphEntry] = {}
        self._tokens: dict[str, Any] = {}  # a dropped token is undeclared: keep them until closed
        self.watchers = _Watchers()
        self._count = 0

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        check_topic(topic)
        transport = self._transport
        with self._lock:
            self._count += 1
            uid = f"{transport.node_id}.{self._count}"
        key = f"{_GRAPH}/{role.value}/{transport.host}/{uid}/{variant.value}{topic}"
        entry = GraphEntry(role, transport.host, topic, variant, uid)
        token: Any = transport.session.liveliness().declare_token(key)
        with self._lock:
            self._entries[key] = entry
            self._tokens[key] = token
        self.watchers.fire()

        def withdraw() -> None:
            with self._lock:
                self._entries.pop(key, None)
                self._tokens.pop(key, None)
            with contextlib.suppress(zenoh.ZError):  # the session may be closed already
                token.undeclare()
            self.watchers.fire()

        return Closer(withdraw)

    def entries(self) -> frozenset[GraphEntry]:
        with self._lock:
            return frozenset(self._entries.values())

    def watch(self, callback: Callable[[], None]) -> Handle:
        return self.watchers.add(callback)

    def on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        parts = key.split("/", 6)  # dbml graph role host uid variant topic...
        try:
            entry = GraphEntry(
                Role(parts[2]), parts[3], "/" + parts[6], Variant(parts[5]), parts[4]
            )
        except (IndexError, ValueError):
            log.warning("ignoring malformed graph token %s", key)
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                if key in self._entries:
                    return
                self._entries[key] = entry
            elif self._entries.pop(key, None) is None:
                return
        self.watchers.fire()


class ZenohTransport:
    """A zenoh session wrapped as a dbml transport. Always ``close()`` it (or use ``with``):
    zenoh's callback threads keep the interpreter alive otherwise."""

    def __init__(
        self,
        *,
        host: str | None = None,
        connect: Iterable[str] = (),
        listen: Iterable[str] = (),
        config_file: str | Path | None = None,
        shared_memory: bool = False,
        port: int | None = None,
    ) -> None:
        self.host = resolve_host(host)
        self.node_id = uuid.uuid4().hex[:16]
        if port is None:
            port = int(os.environ.get("DBML_ZENOH_PORT", DEFAULT_PORT))
        config = _config(
            connect=connect,
            listen=listen,
            config_file=config_file,
            shared_memory=shared_memory,
            port=port,
        )
        try:
            self.session: Any = zenoh.open(config)
        except zenoh.ZError as err:
            raise TransportError(f"zenoh: cannot open a session: {err}") from err
        self._closed = False
        self._lock = threading.Lock()
        self._declared: list[Any] = []
        self._peers = threading.Event()
        self.params = _ZenohParams(self)
        self.graph = _ZenohGraph(self)
        session = self.session
        self._declared += [
            session.declare_subscriber(f"{_PARAM}/**", self.params.on_sample),
            session.declare_queryable(f"{_PARAM}/**", self.params.on_query),
            session.liveliness().declare_subscriber(
                f"{_GRAPH}/**", self.graph.on_sample, history=True
            ),
            session.liveliness().declare_subscriber(f"{_NODE}/**", self._on_node, history=True),
            session.liveliness().declare_token(f"{_NODE}/{self.node_id}"),
        ]
        # zenoh's callback threads are not daemons: close the session before they are joined.
        register = getattr(threading, "_register_atexit", None)
        if register is not None:
            register(self.close)

    def _on_node(self, sample: Any) -> None:
        node = str(sample.key_expr).rsplit("/", 1)[-1]
        if node == self.node_id or sample.kind != zenoh.SampleKind.PUT:
            return
        self._peers.set()
        # A session we had not seen: fetch what it knows, off the callback thread.
        threading.Thread(target=self._sync, name="dbml-param-sync", daemon=True).start()

    def _sync(self) -> None:
        try:
            self.params.sync()
        except zenoh.ZError as err:
            if not self._closed:
                log.warning("parameter sync failed: %s", err)

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Wait until another dbml session is reachable (and its parameters fetched)."""
        if not self._peers.wait(timeout_s):
            return False
        self.params.sync(timeout_s)
        return True

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether another session holds our latest write of ``name`` (polled, bounded)."""
        mine = self.params.stamp(name)
        if mine is None:
            return False
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            replies = self.session.get(
                _param_key(name),
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=min(0.5, left),
            )
            for reply in replies:
                sample = reply.ok
                if sample is None or sample.attachment is None:
                    continue
                if sample.attachment.to_bytes() == self.node_id.encode():
                    continue  # our own cache answering
                _, stamp, writer = decode_param(sample.payload.to_bytes())
                if (stamp, writer) == mine:
                    return True
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))
        return False

    def now(self) -> float:
        return time.monotonic()

    def camera_frame(self, topic: str, size_bytes: int) -> bytes:
        """A synthetic camera frame of ``size_bytes``: raw bytes over this transport."""
        return bytes(size_bytes)

    def declare_publisher(self, topic: str, variant: Variant = Variant.FULL) -> _ZenohPublisher:
        check_topic(topic)
        publisher = _ZenohPublisher(self.session, topic, variant)
        with self._lock:
            self._declared.append(publisher)
        return publisher

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        key = _data_key(topic, variant)

        def on_sample(sample: Any) -> None:
            attachment = sample.attachment
            callback(
                Sample(
                    topic,
                    sample.payload.to_bytes(),
                    None if attachment is None else attachment.to_bytes(),
                )
            )

        subscriber: Any = self.session.declare_subscriber(key, on_sample)
        with self._lock:
            self._declared.append(subscriber)

        def undeclare() -> None:
            with contextlib.suppress(zenoh.ZError):  # the session may be closed already
                subscriber.undeclare()

        return Closer(undeclare)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        try:
            self.session.close()
        except zenoh.ZError as err:
            log.warning("zenoh close: %s", err)

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
