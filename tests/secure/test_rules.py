"""The access rules: one subject per node, and every parameter writable by its writers only.

The rules are judged here as zenoh judges them (``dbml.secure.rules`` says how): a rule applies
to an arriving message when one of its key expressions includes the message's key, and within
a subject a deny rule beats an allow rule. ``test_enforcement`` checks that zenoh agrees.
"""

from __future__ import annotations

import re
from typing import Any

import pytest
import zenoh

from dbml.protocol import keys, names
from dbml.protocol.keys import LINK_TOPIC, ROUND_TOPIC
from dbml.protocol.schema import (
    PARAMETERS,
    Kind,
    ParamError,
    Parameter,
    Scope,
    Writer,
    check_param,
    lookup,
)
from dbml.secure import NodeRole, access_control
from dbml.transports.base import Variant
from dbml.transports.zenoh.transport import _data_key
from tests.secure.conftest import NODES, small_fleet

ROLE_WRITERS = {
    NodeRole.ROBOT: frozenset({Writer.PUBLISHER}),
    NodeRole.OPERATOR: frozenset({Writer.OPERATOR}),
    NodeRole.OPTIMIZER: frozenset({Writer.OPTIMIZER, Writer.ESTIMATOR}),
}
"""Which of the schema's writers run in each role's node: the estimator in the optimizer's."""
NODE_OF = {NodeRole.ROBOT: "r1", NodeRole.OPERATOR: "op", NodeRole.OPTIMIZER: "opt"}
TOPIC = "/r1/camera"
"""A channel of robot r1 (and of no other robot)."""


def permitted(document: dict[str, Any], subject: str, message: str, key: str) -> bool:
    """Whether ``subject`` may send ``message`` on ``key`` to a node with these rules."""
    rules = {rule["id"]: rule for rule in document["rules"]}
    applying = [
        rules[rule_id]
        for policy in document["policies"]
        if subject in policy["subjects"]
        for rule_id in policy["rules"]
    ]
    matched = {
        rule["permission"]
        for rule in applying
        if message in rule["messages"]
        and "ingress" in rule["flows"]
        and any(zenoh.KeyExpr(expr).includes(zenoh.KeyExpr(key)) for expr in rule["key_exprs"])
    }
    if "deny" in matched:
        return False
    return "allow" in matched or document["default_permission"] == "allow"


def full_name(parameter: Parameter) -> str:
    return parameter.name if parameter.scope is Scope.GLOBAL else parameter.key(TOPIC)


def test_the_access_control_has_one_subject_per_node_and_unique_ids() -> None:
    document = access_control(small_fleet())
    assert document["enabled"] is True
    assert document["default_permission"] == "deny"
    assert document["subjects"] == [{"id": n, "cert_common_names": [n]} for n in NODES]
    ids = [rule["id"] for rule in document["rules"]]
    assert len(ids) == len(set(ids))
    referenced = {rule for policy in document["policies"] for rule in policy["rules"]}
    assert referenced == set(ids)
    by_id = {rule["id"]: rule for rule in document["rules"]}
    # only "egress" allows what a node sends; everything else judges what arrives
    assert [rule["id"] for rule in document["rules"] if rule["flows"] != ["ingress"]] == ["egress"]
    assert by_id["r1/put"]["key_exprs"] == ["r1/**", "dbm/reception", "dbml/param/r1/**"]
    assert by_id["r1/put-deny"]["key_exprs"] == [
        "dbml/param/r1/**/dbm/frequency/current_value",
        "dbml/param/r1/**/dbm/encoding/current_value",
        "dbml/param/r1/**/dbm/managed",
    ]
    assert by_id["opt/reply"]["key_exprs"] == ["dbml/own/**"]
    assert "op/put-deny" not in by_id


def test_the_rules_use_the_runtime_s_own_names() -> None:
    """The keys the transports use are the keys the rules name."""
    document = access_control(small_fleet())
    by_id = {rule["id"]: rule for rule in document["rules"]}
    operator, optimizer = by_id["op/put"]["key_exprs"], by_id["opt/put"]["key_exprs"]
    for name in (names.BANDWIDTH, names.UTILIZATION, names.PERIOD, names.STRATEGY):
        assert keys.PARAM + name in operator
    assert f"{keys.PARAM}/**/dbm/{names.PRIORITY_FIELD}" in operator
    for name in (names.STATUS, names.STATUS_MESSAGE, names.ESTIMATE, names.ESTIMATOR_STATE):
        assert keys.PARAM + name in optimizer
    for field in (names.CURRENT_FIELD, names.MANAGED_FIELD):
        assert f"{keys.PARAM}/**/dbm/{field}" in optimizer
        assert f"{keys.PARAM}/r1/**/dbm/{field}" in by_id["r1/put-deny"]["key_exprs"]
    assert f"{keys.BATCH}/**" in optimizer
    # the estimator's beacon: the optimizer's node puts it, and no one else may
    link_key = _data_key(LINK_TOPIC, Variant.FULL)
    assert link_key in optimizer
    assert all(link_key not in by_id[f"{n}/put"]["key_exprs"] for n in ("r1", "r2", "op"))


@pytest.mark.parametrize("parameter", PARAMETERS, ids=lambda p: p.field)
def test_every_parameter_has_an_owner_a_validator_and_a_rule(parameter: Parameter) -> None:
    """From the schema alone: its writers' nodes may put it (and serve it), no other may."""
    name = full_name(parameter)
    assert parameter.writers, f"{name} has no writer"
    topic = None if parameter.scope is Scope.GLOBAL else TOPIC
    assert lookup(name) == (parameter, topic)
    bad = 1.5 if parameter.kind is Kind.TEXT else "not valid"
    with pytest.raises(ParamError, match=re.escape(f"{name}={bad!r}")):
        check_param(name, bad)

    document = access_control(small_fleet())
    for role, node in NODE_OF.items():
        writes = bool(ROLE_WRITERS[role] & parameter.writers)
        assert permitted(document, node, "put", keys.param_key(name)) is writes, (role, name)
        # the optimizer serves every value whose writer has left; the others only their own
        serves = writes or role is NodeRole.OPTIMIZER
        assert permitted(document, node, "reply", keys.own_key("n1", name)) is serves, (role, name)
    # another robot's channel is not r2's, whatever the field
    owns = Writer.PUBLISHER in parameter.writers and parameter.scope is Scope.GLOBAL
    assert permitted(document, "r2", "put", keys.param_key(name)) is owns
    assert permitted(document, "r2", "reply", keys.own_key("n1", name)) is owns


def test_only_the_optimizer_puts_batches_and_beacons_robots_their_data_others_reports() -> None:
    document = access_control(small_fleet())
    link = keys.data_key(keys.LINK_TOPIC)
    rounds = keys.data_key(ROUND_TOPIC)
    reception = keys.data_key(keys.RECEPTION_TOPIC)
    for node in NODES:
        assert permitted(document, node, "put", reception) is (node != "opt")
        assert permitted(document, node, "put", keys.BATCH) is (node == "opt")
        assert permitted(document, node, "put", keys.batch_key("r1")) is (node == "opt")
        assert permitted(document, node, "put", link) is (node == "opt")
        assert permitted(document, node, "put", rounds) is (node == "opt")
        assert permitted(document, node, "put", keys.data_key(TOPIC)) is (node == "r1")
        assert permitted(document, node, "put", keys.data_key(TOPIC + "/optimized")) is (
            node == "r1"
        )
    # a wildcard reaches no further than the rule that grants it
    assert not permitted(document, "r1", "put", keys.param_key("/r2/camera/dbm/priority"))
    assert not permitted(document, "r1", "put", "dbml/param/*/camera/dbm/priority")
