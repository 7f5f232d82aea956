"""Plain ROS 2 in tests: what ``ros2 param set`` does, from a node that knows nothing of dbml.

Such a node is ``dbml.harness.ros2node.private_node``'s: a context of its own in the test's
domain, as another process's would be. rclpy is imported here, so a test module that uses
these skips cleanly where rclpy is missing.
"""

from __future__ import annotations

from typing import Any

from rcl_interfaces.srv import DescribeParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter

from tests.conftest import wait_for

CALL_TIMEOUT_S = 5.0


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


def param_describe(
    node: Node, target: str, names: list[str], *, wait_s: float = CALL_TIMEOUT_S
) -> list[Any]:
    """What ``ros2 param describe TARGET NAME...`` does: one DescribeParameters call."""
    client: Any = node.create_client(DescribeParameters, f"{target}/describe_parameters")
    try:
        assert client.wait_for_service(timeout_sec=wait_s), f"{target} never answered"
        future = client.call_async(DescribeParameters.Request(names=names))
        wait_for(future.done, timeout_s=CALL_TIMEOUT_S, what="the DescribeParameters reply")
        response: Any = future.result()
        return list(response.descriptors)
    finally:
        node.destroy_client(client)
