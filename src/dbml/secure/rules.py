"""The fleet's access rules, derived from the wire schema: a node may write what its role owns.

zenoh enforces the rules on every node as messages arrive (ingress), keyed by the common name of
the sending peer's certificate: a subject per node; a rule applies to a message when the rule's
key expression includes the message's (so a wildcard cannot reach past what a rule grants); and
within one subject a deny rule beats an allow rule (the tests check each of these on real
sessions). What a node sends (egress) is not restricted by its own config: its peers judge it.
Because the subject is the neighbour that delivered a message, the rules hold in a full mesh of
peers, which is what the configs build (every node connects to every other node's endpoint); a
zenoh router in the path would speak for every node behind it.

Who writes a parameter is said once, by its ``writers`` in ``dbml.protocol.schema``; the keys
come from ``dbml.protocol.keys``. A new parameter gets its rule without an edit here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

from dbml.protocol import keys
from dbml.protocol.keys import ROUND_TOPIC
from dbml.protocol.schema import PARAMETERS, Parameter, Scope, Writer
from dbml.secure.fleet import Fleet, FleetNode, NodeRole

__all__ = ["ROLE_WRITERS", "access_control"]

ROLE_WRITERS: Mapping[NodeRole, frozenset[Writer]] = MappingProxyType(
    {
        NodeRole.OPTIMIZER: frozenset({Writer.OPTIMIZER, Writer.ESTIMATOR}),
        NodeRole.ROBOT: frozenset({Writer.PUBLISHER}),
        NodeRole.OPERATOR: frozenset({Writer.OPERATOR}),
    }
)
"""The schema's writers each role's node runs: the estimator runs in the optimizer's node
(``dbml optimizer --estimate``), a robot's publishers in the robot's."""
_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
"""Every message kind zenoh's access control knows."""
_LINK = keys.data_key(keys.LINK_TOPIC)
"""The estimator's beacon: the optimizer's node runs the estimator and puts it; everyone may
subscribe. Without it a secured fleet would silently lose outage handling."""
_ROUND = keys.data_key(ROUND_TOPIC)
"""What each round decided: the optimizer's node puts it, the views and monitors read it."""
_RECEPTION = keys.data_key(keys.RECEPTION_TOPIC)
"""What managed subscribers received, for the estimator: robots and operators subscribe, so
both report. Without it a secured fleet's estimator would hear nothing."""


def _writes(role: NodeRole, parameter: Parameter) -> bool:
    return bool(ROLE_WRITERS[role] & parameter.writers)


def _owned(node: FleetNode) -> tuple[list[str], list[str]]:
    """The parameter names ``node`` may write and, within them, those it may not (no slash).

    A robot owns its own channels (``<robot>/**``) but the fields another role writes there
    (the optimizer's allocation); the other roles own their fields on every channel.
    """
    role = node.role
    globals_ = [p.relative for p in PARAMETERS if p.scope is Scope.GLOBAL and _writes(role, p)]
    fields = [p for p in PARAMETERS if p.scope is Scope.CHANNEL]
    if role is NodeRole.ROBOT:
        denied = [f"{node.name}/**/{p.relative}" for p in fields if not _writes(role, p)]
        return [*globals_, f"{node.name}/**"], denied
    return [*globals_, *(f"**/{p.relative}" for p in fields if _writes(role, p))], []


def _rule(
    rule_id: str, messages: Sequence[str], key_exprs: Sequence[str], *, deny: bool = False
) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": list(messages),
        "flows": ["ingress"],
        "permission": "deny" if deny else "allow",
        "key_exprs": list(key_exprs),
    }


def _node_rules(node: FleetNode) -> list[dict[str, Any]]:
    allowed, denied = _owned(node)
    puts = [f"{keys.PARAM}/{name}" for name in allowed]
    replies = [f"{keys.OWN}/*/{name}" for name in allowed]
    if node.role is NodeRole.ROBOT:
        puts[:0] = [f"{node.name}/**", _RECEPTION]  # its topics' data: /r1/camera is r1/camera
    elif node.role is NodeRole.OPERATOR:
        puts.insert(0, _RECEPTION)
    elif node.role is NodeRole.OPTIMIZER:
        puts[:0] = [f"{keys.BATCH}/**", _LINK, _ROUND]  # the batch for all, and each host's
        replies = [f"{keys.OWN}/**"]  # it keeps, and serves, values whose writer has left
    prefix = f"{node.name}/"
    rules = [
        _rule(prefix + "put", ["put"], puts),
        _rule(prefix + "reply", ["reply"], replies),
        _rule(prefix + "graph", ["liveliness_token"], [f"{keys.GRAPH}/*/{node.name}/**"]),
    ]
    if denied:
        rules.append(
            _rule(prefix + "put-deny", ["put"], [f"{keys.PARAM}/{n}" for n in denied], deny=True)
        )
        rules.append(
            _rule(
                prefix + "reply-deny", ["reply"], [f"{keys.OWN}/*/{n}" for n in denied], deny=True
            )
        )
    return rules


def access_control(fleet: Fleet) -> dict[str, Any]:
    """The ``access_control`` section of every node's zenoh config (the same on all).

    Default deny. Every node may subscribe to anything, serve and query owned values, declare
    its session token and watch dbml's liveliness tokens; beyond that each node may put and
    reply only on what its role owns (a robot: its topics' data, its reception reports and its
    channels' parameters except the optimizer's fields; an operator: its reception reports, the
    budget settings and any channel's priority; the optimizer: its batch, its beacon, its round
    reports, status and allocation fields) and declare graph tokens under its own host name.
    Rule ids hold a ``/`` (node rules) or not (common rules), so no node name can collide with
    another rule's id.
    """
    common = [
        {
            "id": "egress",
            "messages": list(_MESSAGES),
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        },
        _rule("subscribe", ["declare_subscriber"], ["**"]),
        _rule("own-values", ["declare_queryable", "query"], [f"{keys.OWN}/**"]),
        _rule("node-token", ["liveliness_token"], [f"{keys.NODE}/*/*/*"]),
        _rule(
            "liveliness", ["declare_liveliness_subscriber", "liveliness_query"], [f"{keys.ROOT}/**"]
        ),
    ]
    rules = list(common)
    policies: list[dict[str, Any]] = [
        {
            "id": "every node",
            "rules": [rule["id"] for rule in common],
            "subjects": list(fleet.names),
        }
    ]
    for node in fleet.nodes:
        own = _node_rules(node)
        rules += own
        policies.append(
            {"id": node.name, "rules": [rule["id"] for rule in own], "subjects": [node.name]}
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": node.name, "cert_common_names": [node.name]} for node in fleet.nodes],
        "policies": policies,
    }
