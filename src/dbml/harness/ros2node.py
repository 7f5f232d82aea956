"""Plain rclpy nodes of a program's own: the demo's peers, the benchmarks' and the tests' nodes.

``PrivateRos`` is rclpy in a context of its own (``SignalHandlerOptions.NO``: signals stay the
program's), its nodes spun by one executor on a ``BackgroundThread``, so the thread's death is
said and counted; ``close`` destroys the nodes and shuts the context down (no
``/dev/shm/fastdds_*`` left behind). ``private_node`` is one such node for a ``with`` block.

Only where rclpy is installed: this module imports it (``dbml.transports.rclpy``'s executor is
its own, woken by a guard condition).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from dbml.core.errors import DbmlError
from dbml.core.extras import require
from dbml.transports.worker import BackgroundThread

require("rclpy", extra="rclpy", what="a private ROS 2 node")

import rclpy  # noqa: E402  (after require: its error names the extra)
from rclpy.context import Context  # noqa: E402
from rclpy.executors import Executor, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

__all__ = [
    "EXECUTOR_SHUTDOWN_S",
    "SPIN_JOIN_S",
    "SPIN_TIMEOUT_S",
    "PrivateRos",
    "private_node",
    "received_monotonic",
]

log = logging.getLogger("dbml.harness.ros2node")

SPIN_TIMEOUT_S = 0.1
"""The executor thread's longest wait, so closing is noticed."""
SPIN_JOIN_S = 2.0
"""How long ``close`` waits for the executor thread's spin in progress."""
EXECUTOR_SHUTDOWN_S = 1.0
"""How long ``close`` lets the executor finish the callbacks it runs."""


def _executor(context: Context, *, events: bool) -> Executor:
    """A single-threaded executor; with ``events`` rclpy's ``EventsExecutor`` where it has one."""
    if events:
        try:
            from rclpy.experimental.events_executor import EventsExecutor
        except ImportError:
            pass
        else:
            made: Executor = EventsExecutor(context=context)
            return made
    return SingleThreadedExecutor(context=context)


class PrivateRos:
    """rclpy in a context of this object's own: its nodes, one executor, one spinning thread.

    ``domain_id`` None takes ``ROS_DOMAIN_ID``; ``name`` names the thread (``spin-NAME``).
    Signals stay the program's (``SignalHandlerOptions.NO``). The thread's death (an exception,
    or the context shut down under it) is said and counted, so a ``Lifetime`` fails the run and
    ``alive`` turns False. ``close`` destroys every node and shuts the context down: nothing of
    Fast DDS is left behind. ``events`` spins with rclpy's ``EventsExecutor`` where it has one.
    """

    def __init__(self, *, domain_id: int | None, name: str, events: bool = False) -> None:
        self._name = name
        self.context = Context()
        options: dict[str, Any] = {"signal_handler_options": SignalHandlerOptions.NO}
        if domain_id is not None:
            options["domain_id"] = domain_id
        rclpy.init(context=self.context, **options)
        self._nodes: list[Node] = []
        self._closing = threading.Event()
        self._spinner: BackgroundThread | None = None
        try:
            self._executor = _executor(self.context, events=events)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise

    def node(self, name: str, *, namespace: str = "/") -> Node:
        """A node of this context, spun by its executor."""
        node = Node(name, namespace=namespace, context=self.context)
        self._nodes.append(node)
        self._executor.add_node(node)
        return node

    def start(self) -> PrivateRos:
        """Start spinning (once)."""
        if self._spinner is None:
            self._spinner = BackgroundThread(self._spin, name=f"spin-{self._name}", log=log)
            self._spinner.start()
        return self

    @property
    def alive(self) -> bool:
        """False once the executor thread died."""
        return self._spinner is None or self._spinner.alive

    def _spin(self) -> None:
        while not self._closing.is_set():
            if not self.context.ok():
                raise DbmlError(f"{self._name}: the ROS 2 context was shut down under the node")
            self._executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)

    def close(self) -> None:
        """Stop spinning, destroy the nodes and shut the context down."""
        self._closing.set()
        if self._spinner is not None:
            self._spinner.join(SPIN_JOIN_S)
        try:
            self._executor.shutdown(timeout_sec=EXECUTOR_SHUTDOWN_S)
            for node in self._nodes:
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)


@contextmanager
def private_node(name: str, *, domain_id: int | None, namespace: str = "/") -> Iterator[Node]:
    """One node ``name`` of a ``PrivateRos`` of its own, spinning until the block ends."""
    ros = PrivateRos(domain_id=domain_id, name=name)
    try:
        node = ros.node(name, namespace=namespace)
        ros.start()
        yield node
    finally:
        ros.close()


def received_monotonic(info: Any, *, now: float, wall_ns: int) -> float:
    """When DDS received a message, on the monotonic clock of ``now`` (the callback's time).

    A loaded executor calls back up to 0.3 s late (a hostile peer's flood, measured), and
    callbacks it bunched would fill a 1-s window the frames did not arrive in: a counter of the
    wire stamps them when they were received. ``info`` is the callback's message info;
    ``wall_ns``: ``time.time_ns()`` taken with ``now``. Without a plausible stamp: ``now``.
    """
    received_ns = info.get("received_timestamp") if hasattr(info, "get") else None
    if isinstance(received_ns, int) and 0 < received_ns <= wall_ns:
        return now - (wall_ns - received_ns) / 1e9
    return now
