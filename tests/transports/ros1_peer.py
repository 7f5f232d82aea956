"""One ROS 1 transport in a process of its own, driven by the contract suite over a socket.

rospy runs one node per process, so each ros1 "host" of a contract test is one of these:
``python -m tests.transports.ros1_peer FD HOST`` opens ``open_transport("ros1", host=HOST)``
and serves calls arriving on the connection at file descriptor FD; callbacks go back as events
of the id the caller chose for the subscription or watch.
It ends when told to, or when the test process's end of the connection closes.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from dbml.transports import Publisher, Role, Sample, Transport, Variant, open_transport
from dbml.transports.base import Handle
from dbml.transports.replica import Replica


class Peer:
    def __init__(self, transport: Transport, connection: Connection) -> None:
        self.transport = transport
        self.connection = connection
        self.send_lock = threading.Lock()
        self.publishers: dict[int, Publisher] = {}
        self.handles: dict[int, Handle] = {}
        self.ops: dict[str, Callable[..., Any]] = {
            "subscribe": self.subscribe,
            "declare_publisher": self.declare_publisher,
            "put": lambda pid, payload, attachment: self.publishers[pid].put(
                payload, attachment=attachment
            ),
            "has_subscribers": lambda pid: self.publishers[pid].has_subscribers,
            "close_publisher": lambda pid: self.publishers.pop(pid).close(),
            "close_handle": lambda hid: self.handles.pop(hid).close(),
            "set": transport.params.set,
            "set_many": lambda values, host: transport.params.set_many(values, host=host),
            "limit_params": self.limit_params,
            "get": transport.params.get,
            "snapshot": transport.params.snapshot,
            "watch_params": lambda hid: self.keep(hid, transport.params.watch(self.emitter(hid))),
            "announce": lambda hid, role, topic, variant: self.keep(
                hid, transport.graph.announce(Role(role), topic, Variant(variant))
            ),
            "entries": lambda: sorted(transport.graph.entries(), key=lambda e: e.uid),
            "watch_graph": lambda hid: self.keep(hid, transport.graph.watch(self.emitter(hid))),
            "now": transport.now,
            "wait_for_peers": transport.wait_for_peers,
            "confirm_param": lambda name, timeout_s: transport.confirm_param(
                name, timeout_s=timeout_s
            ),
            "set_topic_type": transport.set_topic_type,
        }

    def limit_params(self, more: int) -> None:
        """Lower the store's bound to what it holds and ``more`` new names (its test)."""
        store = self.transport.params
        assert isinstance(store, Replica)
        store._max_params = len(store._own) + more

    def send(self, message: tuple[Any, ...]) -> None:
        with self.send_lock:
            self.connection.send(message)

    def keep(self, hid: int, handle: Handle) -> int:
        self.handles[hid] = handle
        return hid

    def emitter(self, hid: int) -> Callable[..., None]:
        """A callback that sends its arguments back as an event of handle ``hid``."""

        def emit(*args: Any) -> None:
            self.send(("event", hid, args))

        return emit

    def subscribe(self, hid: int, topic: str, variant: str) -> int:
        emit = self.emitter(hid)

        def deliver(sample: Sample) -> None:
            emit(sample.topic, sample.payload, sample.attachment)

        return self.keep(hid, self.transport.subscribe(topic, deliver, Variant(variant)))

    def declare_publisher(self, pid: int, topic: str, variant: str) -> int:
        self.publishers[pid] = self.transport.declare_publisher(topic, Variant(variant))
        return pid

    def serve(self) -> None:
        while True:
            try:
                call_id, op, args = self.connection.recv()
            except EOFError:
                return
            if op == "shutdown":
                self.transport.close()
                self.send(("reply", call_id, True, None))
                return
            try:
                result = self.ops[op](*args)
            except Exception as err:
                self.send(("reply", call_id, False, (type(err).__name__, str(err))))
            else:
                self.send(("reply", call_id, True, result))


def main(argv: list[str]) -> int:
    fd, host = int(argv[0]), argv[1]
    connection = Connection(fd)
    try:
        transport = open_transport("ros1", host=host)
    except Exception as err:
        connection.send(("ready", False, f"{type(err).__name__}: {err}"))
        return 1
    connection.send(("ready", True, transport.host))
    try:
        Peer(transport, connection).serve()
    finally:
        transport.close()
        connection.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
