"""Plain ROS 2 in tests: a node that knows nothing of dbml, and what ``ros2 param set`` does.

Each node has a context of its own in the test's domain, as another process's would; rclpy is
imported here only, so a test module that uses these skips cleanly where rclpy is missing.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from tests.conftest import wait_for

CALL_TIMEOUT_S = 5.0
SPIN_S = 0.05


@contextmanager
def plain_node(domain_id: int, name: str, namespace: str = "/") -> Iterator[Node]:
    """A ROS 2 node that knows nothing of dbml, spun on a thread of its own."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(name, namespace=namespace, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=SPIN_S)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield node
    finally:
        stop.set()
        thread.join(5.0)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def param_set(
    node: Node, target: str, name: str, value: Any, *, wait_s: float = CALL_TIMEOUT_S
) -> Any:
    """What ``ros2 param set TARGET NAME VALUE`` does: one SetParameters call; its result."""
    client: Any = node.create_client(SetParameters, f"{target}/set_parameters")
    try:
        assert client.wait_for_service(timeout_sec=wait_s), f"{target} never answered"
        request = SetParameters.Request(
            parameters=[Parameter(name, value=value).to_parameter_msg()]
        )
        future = client.call_async(request)
        wait_for(future.done, timeout_s=CALL_TIMEOUT_S, what="the SetParameters reply")
        response: Any = future.result()
        return response.results[0]
    finally:
        node.destroy_client(client)
