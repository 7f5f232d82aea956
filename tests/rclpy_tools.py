"""Plain ROS 2 in tests: what ``ros2 param set`` does, from a node that knows nothing of dbml.

Such a node is ``dbml.harness.ros2node.private_node``'s: a context of its own in the test's
domain, as another process's would be. rclpy is imported here, so a test module that uses
these skips cleanly where rclpy is missing.
"""

from __future__ import annotations

from typing import Any

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
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


def lifecycle_state(node: Node, target: str, *, wait_s: float = CALL_TIMEOUT_S) -> str:
    """What ``ros2 lifecycle get TARGET`` says: the managed node's state label."""
    client: Any = node.create_client(GetState, f"{target}/get_state")
    try:
        assert client.wait_for_service(timeout_sec=wait_s), f"{target} never answered"
        future = client.call_async(GetState.Request())
        wait_for(future.done, timeout_s=CALL_TIMEOUT_S, what="the GetState reply")
        response: Any = future.result()
        return str(response.current_state.label)
    finally:
        node.destroy_client(client)


def lifecycle_change(
    node: Node, target: str, transition_id: int, *, timeout_s: float = CALL_TIMEOUT_S
) -> bool:
    """One ChangeState call by transition id, as Nav2's lifecycle manager makes: its success."""
    client: Any = node.create_client(ChangeState, f"{target}/change_state")
    try:
        assert client.wait_for_service(timeout_sec=CALL_TIMEOUT_S), f"{target} never answered"
        future = client.call_async(ChangeState.Request(transition=Transition(id=transition_id)))
        wait_for(future.done, timeout_s=timeout_s, what=f"the reply to transition {transition_id}")
        response: Any = future.result()
        return bool(response.success)
    finally:
        node.destroy_client(client)
