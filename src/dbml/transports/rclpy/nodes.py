"""dbml's parameters as ROS 2 nodes and their names: which node holds a name, who hosts it.

The paper's globals live on the optimizer's node ``/dbm``, a channel's on ``[topic]/dbm``; each
parameter's ROS 2 name is its field with ``.`` for ``/`` (``frequency.min``). Pure rules, read by
the parameter sync (``dbml.transports.rclpy.params``) and the graph poll of the transport.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from collections.abc import Set as AbstractSet
from typing import Any

from dbml.core.errors import TransportError
from dbml.protocol.names import check_topic
from dbml.protocol.schema import GLOBAL_PREFIX, Parameter, Scope, Writer, lookup

__all__ = [
    "CLAIM_SUFFIX",
    "DBM_NODE",
    "HOSTING_WRITERS",
    "PARTICIPANT_BYTES",
    "ROS_OWN",
    "allocated",
    "check_ros_name",
    "check_ros_topic",
    "claim_topic",
    "full_name",
    "hosts_it",
    "is_param_node",
    "node_of",
    "python_value",
    "scope_of",
    "yields",
]

CLAIM_SUFFIX = f"{GLOBAL_PREFIX}/host"
"""A claimed channel node's ``std_msgs/msg/String`` topic, ``[topic]/dbm/host``: its publisher
says in the graph that this process hosts ``[topic]/dbm`` for good, its message which host."""
HOSTING_WRITERS: Mapping[Scope, frozenset[Writer]] = {
    Scope.GLOBAL: frozenset({Writer.OPTIMIZER, Writer.ESTIMATOR}),
    Scope.CHANNEL: frozenset({Writer.PUBLISHER}),
}
"""Whose writes make a process host a node: a parameter only these roles write is written by the
process the paper puts it on (the optimizer's ``/dbm``, the publisher's ``[topic]/dbm``)."""
PARTICIPANT_BYTES = 12
"""A GID's first bytes name its participant (Fast DDS: vendor, host, process, participant)."""
DBM_NODE = GLOBAL_PREFIX[1:]
"""Every parameter node's own name: ``dbm``, in the namespace ``/`` or ``[topic]``."""
_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
"""A ROS 2 topic name as dbml uses one: ``check_topic``'s, without ``-``, ``.`` and ``~``."""
ROS_OWN = frozenset({"use_sim_time", "start_type_description_service"})
"""Parameters every rclpy node declares: not dbml's, never reported."""


def node_of(name: str) -> tuple[Parameter, str, str]:
    """The parameter ``name`` is, its node (``/dbm``, ``/r1/camera/dbm``) and its name there.

    ``TransportError`` for a name outside dbml's schema: ROS 2 parameters live on nodes, so a
    name must say which.
    """
    found = lookup(name)
    if found is None:
        raise TransportError(
            f"parameter name={name!r} is not one of dbml's: over rclpy a parameter lives on a "
            "node, /dbm/<field> or [topic]/dbm/<field>"
        )
    parameter, topic = found
    node = GLOBAL_PREFIX if topic is None else f"{topic}{GLOBAL_PREFIX}"
    return parameter, node, parameter.ros2_name


def check_ros_topic(topic: str) -> str:
    """``topic`` if ROS 2 accepts it as a name too (no ``-``, ``.``, ``~``); else the error.

    dbml's topic rule (``check_topic``) allows those for zenoh; a ROS 2 name, a node's
    namespace included, does not.
    """
    check_topic(topic)
    if not _ROS_NAME.match(topic):
        raise TransportError(
            f"topic={topic!r} is not a ROS 2 name: letters, digits and _ only between the /"
        )
    return topic


def claim_topic(node: str) -> str:
    """The topic a claimed channel node ``[topic]/dbm`` publishes its host on."""
    return f"{node[: -len(GLOBAL_PREFIX)]}{CLAIM_SUFFIX}"


def check_ros_name(name: str) -> None:
    """A parameter's node must be a ROS 2 name: ``set`` refuses one that is not, by name."""
    _parameter, node, _ros2_name = node_of(name)
    if node != GLOBAL_PREFIX:
        check_ros_topic(node[: -len(GLOBAL_PREFIX)])


def full_name(node: str, ros2_name: str) -> str | None:
    """The store's name of parameter ``ros2_name`` on node ``node``; None if not dbml's."""
    if ros2_name in ROS_OWN:
        return None
    name = f"{node}/{ros2_name.replace('.', '/')}"
    found = lookup(name)
    if found is None:
        return None
    expected = GLOBAL_PREFIX if found[1] is None else f"{found[1]}{GLOBAL_PREFIX}"
    return name if expected == node else None


def scope_of(node: str) -> Scope:
    """Whose parameters a node holds: ``/dbm`` the globals, ``[topic]/dbm`` a channel's."""
    return Scope.GLOBAL if node == GLOBAL_PREFIX else Scope.CHANNEL


def is_param_node(namespace: str, name: str) -> str | None:
    """The fully qualified name of a parameter node (``/dbm``, ``/r1/camera/dbm``), else None."""
    if name != DBM_NODE:
        return None
    if namespace == "/":
        return GLOBAL_PREFIX
    try:
        check_topic(namespace)
    except TransportError:
        return None
    return f"{namespace}{GLOBAL_PREFIX}"


def yields(own: bytes, hosts: AbstractSet[bytes], claimed: AbstractSet[bytes]) -> bool:
    """Whether a provisional host ``own`` of a node gives it up, seeing ``hosts`` host it.

    To a host that claimed the node (its owner), always; among provisional hosts, all but the
    smallest participant: every process decides alike from the same graph, so one is left.
    """
    others = set(hosts) - {own}
    return bool(others) and (bool(set(claimed) - {own}) or min(others) < own)


def hosts_it(parameter: Parameter) -> bool:
    """Whether writing ``parameter`` makes this process its node's host (see HOSTING_WRITERS)."""
    return parameter.writers <= HOSTING_WRITERS[parameter.scope]


def allocated(parameter: Parameter) -> bool:
    """A channel's parameter only the optimizer writes: it travels in ``/dbm/allocation``."""
    return parameter.scope is Scope.CHANNEL and parameter.writers == {Writer.OPTIMIZER}


def python_value(message: Any) -> object:
    """A ``ParameterValue`` as Python (``None`` for NOT_SET, arrays as lists).

    One of a type rclpy does not know (any node may send one) is an object the store refuses,
    naming it, never an exception on the executor thread.
    """
    from rclpy.parameter import parameter_value_to_python

    try:
        value: object = parameter_value_to_python(message)
    except Exception:  # rclpy raises its own errors for an unknown type number
        return _UNKNOWN_VALUE
    return value


class _Unknown:
    """A parameter value of a type rclpy does not know: the store refuses it, naming it."""

    def __repr__(self) -> str:
        return "<a parameter value of an unknown type>"


_UNKNOWN_VALUE = _Unknown()
