"""The fleet's plan: roles, endpoints and certificate names, each checked once."""

from __future__ import annotations

import pytest

from dbml.secure import DEFAULT_BASE_PORT, NodeRole, SecureError, plan_fleet
from tests.secure.conftest import NODES, small_fleet


def test_the_plan_orders_roles_and_gives_loopback_defaults() -> None:
    fleet = small_fleet(base_port=20000)
    assert fleet.names == NODES
    assert [node.role for node in fleet.nodes] == [
        NodeRole.OPTIMIZER,
        NodeRole.ROBOT,
        NodeRole.ROBOT,
        NodeRole.OPERATOR,
    ]
    assert [node.endpoint for node in fleet.nodes] == [
        f"tls/127.0.0.1:{20000 + i}" for i in range(4)
    ]
    assert fleet.node("r1").sans == ("r1", "localhost", "127.0.0.1")
    assert small_fleet().nodes[0].endpoint == f"tls/127.0.0.1:{DEFAULT_BASE_PORT}"


def test_one_string_is_not_a_list_of_robots() -> None:
    with pytest.raises(SecureError, match="not one string"):
        plan_fleet(optimizer="opt", robots="r1")
