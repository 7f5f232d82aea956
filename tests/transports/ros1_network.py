"""A ROS 1 'network' for the contract suite: a private master, one peer process per host.

rospy runs one node per process, so each host a test makes is a ``tests.transports.ros1_peer``
process, reached through ``PeerTransport``, a proxy that forwards every call over a socket and
pumps the peer's callbacks back on a thread of this process (as a middleware's thread would).

ROS names a node's host by its address, so the factory gives each host name a loopback address
(``host-a`` is 127.0.0.2, ...), opens the peer with ``host=<address>`` and maps addresses back
to names; a peer whose node did not take its address shows up under the wrong name.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import queue
import socket
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from dbml.core.errors import TransportError
from dbml.harness.rosmaster import RosMaster
from dbml.harness.supervisor import Supervisor
from dbml.protocol.schema import ParamError
from dbml.transports import (
    GraphEntry,
    Handle,
    ParamValue,
    Role,
    Sample,
    Transport,
    TransportBase,
    Variant,
)
from dbml.transports.base import Closer, TransportPriority, of_topic
from dbml.transports.codecs import ROS1_FLOAT64
from tests.conftest import require
from tests.ros1.rosnet import ros1_problem

ROOT = Path(__file__).resolve().parents[2]
READY_S = 20.0
CALL_S = 20.0
RAISED: dict[str, type[Exception]] = {"TransportError": TransportError, "ParamError": ParamError}
"""The peer's errors that the tests expect by type: raised here as the peer raised them."""

Factory = Callable[[str], Transport]


class _Hosts:
    """Host names to loopback addresses and back."""

    def __init__(self) -> None:
        self.addresses: dict[str, str] = {}
        self.names: dict[str, str] = {}

    def address(self, name: str) -> str:
        if name not in self.addresses:
            address = f"127.0.0.{len(self.addresses) + 2}"
            self.addresses[name], self.names[address] = address, name
        return self.addresses[name]

    def name(self, address: str) -> str:
        return self.names.get(address, address)


class _Peer:
    """The peer process and its connection: one call at a time, events on a thread."""

    def __init__(self, address: str, env: dict[str, str], log: Path) -> None:
        ours, theirs = socket.socketpair()
        self._log = log
        self._children = Supervisor(logs=log.parent)
        self.process = self._children.start(
            log.stem,
            [sys.executable, "-m", "tests.transports.ros1_peer", str(theirs.fileno()), address],
            cwd=ROOT,
            env=env,
            stdin=False,
            read_stdout=False,
            pass_fds=[theirs.fileno()],
        )
        theirs.close()
        self.connection = Connection(ours.detach())
        self._calls = threading.Lock()
        self._replies: queue.Queue[tuple[bool, Any]] = queue.Queue()
        self._events: queue.Queue[tuple[int, tuple[Any, ...]] | None] = queue.Queue()
        self.callbacks: dict[int, Callable[..., None]] = {}
        if not self.connection.poll(READY_S):
            self.stop()
            raise TransportError(f"ros1 peer {address} did not start: {self.stderr()}")
        _, ok, detail = self.connection.recv()
        if not ok:
            self.stop()
            raise TransportError(f"ros1 peer {address}: {detail}")
        self.host: str = detail
        self._ids = itertools.count()
        threading.Thread(target=self._read, name="ros1-peer-read", daemon=True).start()
        threading.Thread(target=self._dispatch, name="ros1-peer-events", daemon=True).start()

    def stderr(self) -> str:
        return self._log.read_text(errors="replace")[-2000:]

    def _read(self) -> None:
        try:
            while True:
                message = self.connection.recv()
                if message[0] == "event":
                    self._events.put((message[1], message[2]))
                else:
                    self._replies.put((message[2], message[3]))
        except (EOFError, OSError):
            self._replies.put((False, ("EOFError", "the peer process ended")))
        finally:
            self._events.put(None)

    def _dispatch(self) -> None:
        while (event := self._events.get()) is not None:
            hid, args = event
            callback = self.callbacks.get(hid)
            if callback is not None:
                callback(*args)

    def new_id(self) -> int:
        """An id for a publisher, subscription or watch, chosen here so events find it."""
        return next(self._ids)

    def listen(self, op: str, callback: Callable[..., None], *args: Any) -> Handle:
        """``op`` (a subscription or watch) whose events go to ``callback``."""
        hid = self.new_id()
        self.callbacks[hid] = callback  # before the call: an event may follow it at once
        try:
            self.call(op, hid, *args)
        except BaseException:
            self.callbacks.pop(hid, None)
            raise

        def close() -> None:
            self.callbacks.pop(hid, None)
            self.call("close_handle", hid)

        return Closer(close)

    def call(self, op: str, *args: Any) -> Any:
        with self._calls:
            self.connection.send((next(self._ids), op, args))
            try:
                ok, value = self._replies.get(timeout=CALL_S)
            except queue.Empty:
                raise TransportError(f"ros1 peer: {op} got no reply in {CALL_S} s") from None
        if ok:
            return value
        error, message = value
        if error in RAISED:
            raise RAISED[error](message)
        raise RuntimeError(f"ros1 peer: {op}: {error}: {message}\n{self.stderr()}")

    def stop(self) -> None:
        if self.process.poll() is None:
            with contextlib.suppress(TransportError, RuntimeError, OSError):
                self.call("shutdown")
        self.connection.close()
        self._children.close()  # SIGTERM, then SIGKILL, by its PID


class _PeerPublisher:
    def __init__(self, peer: _Peer, topic: str, variant: Variant) -> None:
        self.topic = topic
        self._peer = peer
        self._pid: int = peer.call("declare_publisher", peer.new_id(), topic, variant.value)

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        self._peer.call("put", self._pid, payload, attachment)

    @property
    def has_subscribers(self) -> bool:
        return bool(self._peer.call("has_subscribers", self._pid))

    def close(self) -> None:
        self._peer.call("close_publisher", self._pid)


class _PeerParams:
    def __init__(self, peer: _Peer) -> None:
        self._peer = peer

    def set(self, name: str, value: ParamValue) -> None:
        self._peer.call("set", name, value)

    def set_many(self, values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
        self._peer.call("set_many", dict(values), host)

    def limit(self, more: int) -> None:
        """The peer's store takes ``more`` new names of its own, and refuses the next."""
        self._peer.call("limit_params", more)

    def get(self, name: str) -> ParamValue:
        value: ParamValue = self._peer.call("get", name)
        return value

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        values: dict[str, ParamValue] = self._peer.call("snapshot", prefix)
        return values

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        return self._peer.listen("watch_params", callback)


class _PeerGraph:
    def __init__(self, peer: _Peer, hosts: _Hosts) -> None:
        self._peer = peer
        self._hosts = hosts

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        return self._peer.listen("announce", lambda: None, role.value, topic, variant.value)

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        entries: list[GraphEntry] = self._peer.call("entries")
        return of_topic(
            frozenset(
                GraphEntry(e.role, self._hosts.name(e.host), e.topic, e.variant, e.uid)
                for e in entries
            ),
            topic,
        )

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        return self._peer.listen("watch_graph", callback)


class PeerTransport(TransportBase):
    """A ``Transport`` whose every call runs in a ``ros1_peer`` process."""

    float64 = ROS1_FLOAT64

    def __init__(self, peer: _Peer, name: str, hosts: _Hosts) -> None:
        self._peer = peer
        self.host = hosts.name(peer.host)
        self.params = _PeerParams(peer)
        self.graph = _PeerGraph(peer, hosts)
        self._closed = False

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> _PeerPublisher:
        return _PeerPublisher(self._peer, topic, variant)  # ROS 1 has no classes

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        def deliver(topic: str, payload: bytes, attachment: bytes | None) -> None:
            callback(Sample(topic, payload, attachment))

        return self._peer.listen("subscribe", deliver, topic, variant.value)

    def now(self) -> float:
        now: float = self._peer.call("now")
        return now

    def wait_for_peers(self, timeout_s: float) -> bool:
        return bool(self._peer.call("wait_for_peers", timeout_s))

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        return bool(self._peer.call("confirm_param", name, timeout_s))

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        self._peer.call("set_topic_type", topic, msg_type)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._peer.stop()


def ros1_network() -> Iterator[Factory]:
    """A private master per test; each host a peer process on its own loopback address."""
    require(ros1_problem(), what="run the ROS 1 contract tests")
    hosts = _Hosts()
    made: list[PeerTransport] = []
    with tempfile.TemporaryDirectory(prefix="dbml-ros1-") as home, RosMaster() as master:
        env = {k: v for k, v in os.environ.items() if k not in {"ROS_IP", "ROS_HOSTNAME"}}
        env.update(ROS_MASTER_URI=master.uri, ROS_HOME=home, ROS_LOG_DIR=home)

        def make(name: str) -> Transport:
            address = hosts.address(name)
            peer = _Peer(address, env, Path(home) / f"{address}.log")
            transport = PeerTransport(peer, name, hosts)
            made.append(transport)
            return transport

        try:
            yield make
        finally:
            # Each peer takes a while to shut its node down: all at once.
            closing = [threading.Thread(target=transport.close) for transport in made]
            for thread in closing:
                thread.start()
            for thread in closing:
                thread.join()
