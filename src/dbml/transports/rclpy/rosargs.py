"""ROS 2's own arguments on dbml's rclpy commands: ``--ros-args`` blocks, params files, ``-p``.

rclpy parses them (``rclpy.init(args=...)``), so an unknown one is refused by rclpy's rules,
with its message. dbml's parameter nodes keep the paper's names whatever the remapping (a
launch file's namespace moves the command, not ``/dbm``): their values in a ``ros__parameters``
file (keyed ``/dbm`` or ``[topic]/dbm``, or ``/**`` for every one), or a ``-p name:=value``
naming a global, are read here and checked against the schema before any network is opened.
What an operator may set is then written as ``dbml budget`` or ``dbml priority`` would; a
channel's bounds are what ``dbml bridge`` bridges. A value only dbml writes (an allocation, a
status) is refused. The command's own node (``-r __ns:=``, ``-r __node:=``) may carry rclpy's
``qos_overrides.*`` for its ``[topic]/optimized`` publishers.

Pure: PyYAML and the schema, no rclpy (the CLI checks a file before a transport opens).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from dbml.core.errors import TransportError
from dbml.core.spec import short_repr
from dbml.protocol.schema import (
    GLOBAL_PREFIX,
    ParamError,
    ParamValue,
    Writer,
    check_param,
    check_param_value,
    lookup,
)
from dbml.transports.rclpy.nodes import full_name

__all__ = [
    "DEFAULT_NODE_NAME",
    "END_FLAG",
    "QOS_PREFIX",
    "ROS_ARGS_FLAG",
    "WILDCARD_NODE",
    "channel_bounds",
    "namespace_of",
    "node_name_of",
    "overrides",
    "qos_overrides",
    "split_ros_args",
]

ROS_ARGS_FLAG = "--ros-args"
END_FLAG = "--"
"""Ends a ``--ros-args`` block: what follows is the program's again (rcl's rule)."""
WILDCARD_NODE = "/**"
"""A params file's key for every node."""
DEFAULT_NODE_NAME = "dbml"
"""The command's node name in a params file when no ``-r __node:=`` names it."""
QOS_PREFIX = "qos_overrides."
"""rclpy's QoS override parameters: ``qos_overrides.<topic>.publisher.<policy>``."""
_QOS_VALUES: dict[str, frozenset[str]] = {
    "reliability": frozenset({"reliable", "best_effort", "system_default", "best_available"}),
    "history": frozenset({"keep_last", "keep_all", "system_default"}),
}
"""The policies ``QoSOverridingOptions.with_default_policies`` declares, depth aside."""
_PARAMS_KEY = "ros__parameters"
_PARAM_FLAGS = frozenset({"-p", "--param"})
_REMAP_FLAGS = frozenset({"-r", "--remap"})
_FILE_FLAG = "--params-file"
_SETTABLE = frozenset({Writer.OPERATOR, Writer.PUBLISHER})
"""Who may be named in a params file: an operator's values, and a channel's own declaration."""


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], tuple[str, ...]]:
    """The program's arguments, and ROS 2's: each ``--ros-args`` block up to ``--`` or the end."""
    own: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == ROS_ARGS_FLAG:
            inside = True
            ros.append(arg)
        elif inside and arg == END_FLAG:
            inside = False
        else:
            (ros if inside else own).append(arg)
    return own, tuple(ros)


def _flagged(ros_args: Sequence[str], flags: frozenset[str]) -> Iterator[str]:
    """The value after each of ``flags`` (in order)."""
    for flag, value in itertools.pairwise(ros_args):
        if flag in flags:
            yield value


def namespace_of(ros_args: Sequence[str]) -> str:
    """The namespace ``-r __ns:=/r1`` gives the command's node (the last one wins); ``/``."""
    namespace = "/"
    for rule in _flagged(ros_args, _REMAP_FLAGS):
        source, sep, target = rule.partition(":=")
        if sep and source == "__ns":
            namespace = target if target.startswith("/") else f"/{target}"
    return namespace.rstrip("/") or "/"


def node_name_of(ros_args: Sequence[str]) -> str:
    """The name ``-r __node:=NAME`` gives the command's node (the last one wins)."""
    name = DEFAULT_NODE_NAME
    for rule in _flagged(ros_args, _REMAP_FLAGS):
        source, sep, target = rule.partition(":=")
        if sep and source in {"__node", "__name"}:
            name = target
    return name


def _check_qos(name: str, value: object, *, origin: str) -> None:
    """A ``qos_overrides.<topic>.publisher.<policy>`` rclpy will take, else naming it."""
    policy = name.rpartition(".")[2]
    if ".publisher." not in name:
        raise TransportError(f"{origin}: {name}: dbml's QoS overrides are its publishers'")
    if policy == "depth":
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise TransportError(f"{origin}: {name}={short_repr(value)} must be an integer >= 0")
    elif policy in _QOS_VALUES:
        if value not in _QOS_VALUES[policy]:
            allowed = ", ".join(sorted(_QOS_VALUES[policy]))
            raise TransportError(f"{origin}: {name}={short_repr(value)} must be one of {allowed}")
    else:
        raise TransportError(f"{origin}: {name}: no such QoS policy (depth, history, reliability)")


def qos_overrides(ros_args: Sequence[str]) -> dict[str, object]:
    """The ``qos_overrides.*`` for the command's node in ``ros_args``, checked (later win).

    From a params file's entry for the node (``-r __ns:=`` and ``-r __node:=``, default
    ``/dbml``) or ``/**``, and from ``-p``: what rclpy's ``QoSOverridingOptions`` reads when
    dbml declares a ``[topic]/optimized`` publisher.
    """
    namespace = namespace_of(ros_args)
    node = f"{'' if namespace == '/' else namespace}/{node_name_of(ros_args)}"
    found: dict[str, object] = {}
    for flag, value in itertools.pairwise(ros_args):
        if flag == _FILE_FLAG:
            files = _load(value)
            for key in (WILDCARD_NODE, node):
                for name, item in files.get(key, {}).items():
                    if name.startswith(QOS_PREFIX):
                        _check_qos(name, item, origin=value)
                        found[name] = item
        elif flag in _PARAM_FLAGS:
            name, sep, text = value.partition(":=")
            if sep and name.startswith(QOS_PREFIX):
                item = yaml.safe_load(text)
                _check_qos(name, item, origin=f"-p {value}")
                found[name] = item
    return found


def _flatten(values: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``ros__parameters`` as ROS 2 names: ``frequency: {min: 1}`` is ``frequency.min``."""
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from _flatten(value, f"{name}.")
        else:
            yield name, value


def _is_dbml_node(node: str) -> bool:
    return node == GLOBAL_PREFIX or node.endswith(GLOBAL_PREFIX)


def _load(path: str) -> dict[str, dict[str, Any]]:
    """A params file: node -> its ROS 2 names and values; ``TransportError`` naming the file."""
    try:
        document = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as err:
        raise TransportError(f"--params-file={path!r}: {err}") from None
    if not isinstance(document, Mapping):
        raise TransportError(f"--params-file={path!r}: not a mapping of nodes")
    nodes: dict[str, dict[str, Any]] = {}
    for node, body in document.items():
        if not isinstance(body, Mapping) or not isinstance(body.get(_PARAMS_KEY), Mapping):
            raise TransportError(f"--params-file={path!r}: node {node!r} has no {_PARAMS_KEY}")
        nodes[str(node)] = dict(_flatten(body[_PARAMS_KEY]))
    return nodes


def _take(
    found: dict[str, ParamValue], node: str, ros2_name: str, value: object, *, origin: str
) -> None:
    """Check one value for dbml's node ``node`` and keep it; errors name where it came from."""
    name = full_name(node, ros2_name)
    hit = None if name is None else lookup(name)
    if name is None or hit is None:
        raise TransportError(f"{origin}: {node} has no parameter {ros2_name!r}")
    if not hit[0].writers & _SETTABLE:
        raise TransportError(
            f"{origin}: {name}={short_repr(value)} is written by dbml's {hit[0].writers_text}"
        )
    try:
        found[name] = check_param(name, check_param_value(value))
    except ParamError as err:  # it names the key and the value
        raise TransportError(f"{origin}: {err}") from None
    except TransportError as err:
        raise TransportError(f"{origin}: {name}: {err}") from None


def overrides(ros_args: Sequence[str]) -> dict[str, ParamValue]:
    """The values of dbml's parameters in ``ros_args``, by full name, checked (later win).

    A params file's ``/dbm`` and ``[topic]/dbm`` entries (its other nodes are not dbml's), its
    ``/**`` entry for each of them that holds the parameter, and ``-p name:=value`` for a
    global (rcl gives ``-p`` to every node; only ``/dbm`` holds the globals).
    """
    found: dict[str, ParamValue] = {}
    for flag, value in itertools.pairwise(ros_args):
        if flag == _FILE_FLAG:
            files = _load(value)
            nodes = [n for n in files if _is_dbml_node(n)]
            for node, values in files.items():
                if node == WILDCARD_NODE:
                    for target in nodes or [GLOBAL_PREFIX]:
                        for ros2_name, item in values.items():
                            if _holds(target, ros2_name):
                                _take(found, target, ros2_name, item, origin=value)
                elif _is_dbml_node(node):
                    for ros2_name, item in values.items():
                        _take(found, node, ros2_name, item, origin=value)
        elif flag in _PARAM_FLAGS:
            ros2_name, sep, text = value.partition(":=")
            if sep and _holds(GLOBAL_PREFIX, ros2_name):
                _take(found, GLOBAL_PREFIX, ros2_name, yaml.safe_load(text), origin=f"-p {value}")
    return found


def _holds(node: str, ros2_name: str) -> bool:
    """Whether dbml's node ``node`` has parameter ``ros2_name``."""
    return full_name(node, ros2_name) is not None


def channel_bounds(
    values: Mapping[str, ParamValue], *, namespace: str = "/"
) -> dict[str, tuple[float, float, float | None]]:
    """Each channel under ``namespace`` with both bounds: topic -> (min Hz, max Hz, priority)."""
    prefix = "/" if namespace == "/" else f"{namespace}/"
    channels: dict[str, tuple[float, float, float | None]] = {}
    for name in values:
        hit = lookup(name)
        if hit is None or hit[1] is None or not hit[1].startswith(prefix):
            continue
        topic = hit[1]
        low = values.get(f"{topic}/dbm/frequency/min")
        high = values.get(f"{topic}/dbm/frequency/max")
        priority = values.get(f"{topic}/dbm/priority")
        if isinstance(low, float) and isinstance(high, float):
            channels[topic] = (low, high, priority if isinstance(priority, float) else None)
    return channels
