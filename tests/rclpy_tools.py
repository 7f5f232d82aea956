"""Plain ROS 2 in tests: what ``ros2 param set`` does, from a node that knows nothing of dbml.

Such a node is ``dbml.harness.ros2node.private_node``'s: a context of its own in the test's
domain, as another process's would be. rclpy is imported here, so a test module that uses
these skips cleanly where rclpy is missing.
"""

from __future__ import annotations

import time
from typing import Any

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.srv import DescribeParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter

from tests.conftest import wait_for

CALL_TIMEOUT_S = 5.0
QUERY_ATTEMPTS = 3
"""A query (a state, a description: asking again changes nothing) is sent anew when no reply
came in ``CALL_TIMEOUT_S``: Fast DDS drops a reply whose client's response reader the service
has not matched within 100 ms ("failed to send response (timeout): client will not receive
response"), as the ROS 2 package test's optimizer logged in a CI run while its fleet started."""
_POLL_S = 0.005


def _query(client: Any, request: Any, *, what: str) -> Any:
    """``request``'s reply, asked up to ``QUERY_ATTEMPTS`` times; the test fails without one."""
    for _ in range(QUERY_ATTEMPTS):
        future = client.call_async(request)
        deadline = time.monotonic() + CALL_TIMEOUT_S
        while not future.done() and time.monotonic() < deadline:
            time.sleep(_POLL_S)
        if future.done():
            return future.result()
        client.remove_pending_request(future)
    pytest.fail(f"no {what} to {QUERY_ATTEMPTS} requests, {CALL_TIMEOUT_S} s each")


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
        request = DescribeParameters.Request(names=names)
        response = _query(client, request, what="DescribeParameters reply")
        return list(response.descriptors)
    finally:
        node.destroy_client(client)


def lifecycle_state(node: Node, target: str, *, wait_s: float = CALL_TIMEOUT_S) -> str:
    """What ``ros2 lifecycle get TARGET`` says: the managed node's state label."""
    client: Any = node.create_client(GetState, f"{target}/get_state")
    try:
        assert client.wait_for_service(timeout_sec=wait_s), f"{target} never answered"
        response = _query(client, GetState.Request(), what="GetState reply")
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
