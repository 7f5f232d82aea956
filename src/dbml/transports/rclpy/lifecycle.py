"""The managed optimizer over rclpy: a lifecycle node serving ``lifecycle_msgs``' services.

rclpy's lifecycle node keeps the states and answers ``<node>/change_state``, ``get_state``,
``get_available_states``, ``get_available_transitions`` and ``get_transition_graph`` (what Nav2's
lifecycle manager and ``ros2 lifecycle`` call); each transition's work is
``dbml.runtime.lifecycle.OptimizerLifecycle``'s. The node takes the command line's ``-r
__node:=`` and ``-r __ns:=`` (named ``dbml`` otherwise), so a launch file's name is the one a
lifecycle manager lists.

It spins on its own executor thread, not the transport's: a transition builds or closes the
optimizer, which waits on the transport's thread, and its reply is that work's outcome.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle import Node as LifecycleNode

from dbml.core.errors import DbmlError
from dbml.runtime.lifecycle import OptimizerLifecycle
from dbml.transports.overflow import LogOnce
from dbml.transports.rclpy.rosargs import DEFAULT_NODE_NAME
from dbml.transports.rclpy.transport import SPIN_TIMEOUT_S, RclpyTransport
from dbml.transports.worker import BackgroundThread

__all__ = ["LifecycleServer"]

log = logging.getLogger("dbml.rclpy")


class _OptimizerNode(LifecycleNode):
    """Each transition does the lifecycle's work and says how it went.

    Done is SUCCESS, a ``DbmlError`` FAILURE, anything else ERROR (logged here: rclpy would
    turn it into ERROR silently).
    """

    def __init__(self, lifecycle: OptimizerLifecycle, transport: RclpyTransport) -> None:
        super().__init__(DEFAULT_NODE_NAME, context=transport.context)
        self._lifecycle = lifecycle

    def _do(self, transition: str, work: Callable[[], None]) -> TransitionCallbackReturn:
        try:
            work()
        except DbmlError as err:
            log.warning("lifecycle %s refused: %s", transition, err)
            return TransitionCallbackReturn.FAILURE
        except Exception:
            log.exception("lifecycle %s failed", transition)
            return TransitionCallbackReturn.ERROR
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._do("configure", self._lifecycle.configure)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._do("activate", self._lifecycle.activate)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._do("deactivate", self._lifecycle.deactivate)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._do("cleanup", self._lifecycle.cleanup)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._do("shutdown", self._lifecycle.shutdown)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised something else: close what runs, back to unconfigured."""
        self._lifecycle.close()
        return TransitionCallbackReturn.SUCCESS


class LifecycleServer:
    """``lifecycle``'s node on ``transport``'s context, spun by a thread of its own until closed."""

    def __init__(self, transport: RclpyTransport, lifecycle: OptimizerLifecycle) -> None:
        self._closed = threading.Event()
        self._bad = LogOnce(log)
        self._context = transport.context
        self.node = _OptimizerNode(lifecycle, transport)
        self._executor = SingleThreadedExecutor(context=transport.context)
        self._executor.add_node(self.node)
        self._thread = BackgroundThread(self._spin, name="dbml-lifecycle", log=log).start()
        log.info("lifecycle node %s: unconfigured", self.node.get_fully_qualified_name())

    def _spin(self) -> None:
        """Spin until closed; a request that breaks a service is logged, never the thread's end."""
        while not self._closed.is_set() and self._context.ok():
            try:
                self._executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
            except Exception as err:  # a peer's request must not end the lifecycle
                if self._closed.is_set() or not self._context.ok():
                    return
                self._bad.warning(
                    f"spin:{type(err).__name__}", "a lifecycle request failed (ignored): %r", err
                )

    @property
    def alive(self) -> bool:
        """False once the spinning thread died."""
        return self._thread.alive

    def close(self) -> None:
        """Stop spinning, then destroy the node (bounded)."""
        self._closed.set()
        self._thread.join()
        self._executor.remove_node(self.node)
        self.node.destroy_node()
