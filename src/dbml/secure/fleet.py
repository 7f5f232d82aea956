"""The fleet's plan: which nodes exist, what role each plays, where each listens.

Every name and address is checked once, here, before a key is made or a file written; a bad
one raises ``SecureError`` naming the field and the value.
"""

from __future__ import annotations

import enum
import ipaddress
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from dbml.core.errors import DbmlError
from dbml.protocol import keys
from dbml.protocol.schema import GLOBAL_PREFIX

__all__ = [
    "DEFAULT_BASE_PORT",
    "Fleet",
    "FleetNode",
    "NodeRole",
    "SecureError",
    "plan_fleet",
]

DEFAULT_BASE_PORT = 17448
"""Nodes without an endpoint listen on ``tls/127.0.0.1:<base + index>`` (loopback trials); the
default stays clear of zenohd's 7447 and of dbml's loopback rendezvous 17447."""

_NAME = re.compile(r"^[A-Za-z](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")
"""A node name is a host name label that is also a topic segment and a key expression chunk."""
_RESERVED = frozenset({"ca", keys.ROOT, GLOBAL_PREFIX.lstrip("/")})
"""``ca`` names the CA's files; a robot ``dbm`` or ``dbml`` would own dbml's own key space."""
_DNS_LABEL = re.compile(r"^[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")
_MAX_DNS_NAME = 253
_MAX_PORT = 65_535
_ENDPOINT = re.compile(r"^tls/(?P<host>\[[0-9A-Fa-f:.]+\]|[^/\[\]:]+):(?P<port>[0-9]+)$")
_LOOPBACK_SANS = ("localhost", "127.0.0.1")
"""Every certificate holds these too, so any node can run on loopback or in a namespace."""


class SecureError(DbmlError, ValueError):
    """Bad input for a secure fleet, naming the field and the value; or files in the way."""


class NodeRole(enum.StrEnum):
    """What a node is, which decides what it may write."""

    OPTIMIZER = "optimizer"
    ROBOT = "robot"
    OPERATOR = "operator"


@dataclass(frozen=True, slots=True)
class FleetNode:
    """One node of the fleet: its identity (certificate name = ``--host``) and where it listens."""

    name: str
    role: NodeRole
    endpoint: str
    """``tls/HOST:PORT``: where the node listens and every other node connects."""
    sans: tuple[str, ...]
    """The DNS names and IP addresses its certificate is valid for."""


@dataclass(frozen=True, slots=True)
class Fleet:
    """Every node: the optimizer first, then the robots, then the operators."""

    nodes: tuple[FleetNode, ...]

    def node(self, name: str) -> FleetNode:
        """The node called ``name``."""
        for node in self.nodes:
            if node.name == name:
                return node
        raise SecureError(f"node={name!r} is not in the fleet ({', '.join(self.names)})")

    @property
    def names(self) -> tuple[str, ...]:
        """Every node's name, in order."""
        return tuple(node.name for node in self.nodes)

    def of_role(self, role: NodeRole) -> tuple[FleetNode, ...]:
        """The nodes that have ``role``."""
        return tuple(node for node in self.nodes if node.role is role)


def _check_name(field: str, name: object) -> str:
    if not isinstance(name, str) or not name:
        raise SecureError(f"{field}={name!r}: a node name must not be empty")
    if not _NAME.match(name):
        raise SecureError(
            f"{field}={name!r} must be a letter, then letters, digits or '-' (at most 63): "
            "it is the node's host name, a topic segment and its certificate's name"
        )
    if name.lower() in _RESERVED:
        raise SecureError(f"{field}={name!r} is reserved ({', '.join(sorted(_RESERVED))})")
    return name


def _check_san(field: str, value: str) -> str:
    """An IP address (returned in its canonical form) or a DNS name."""
    try:
        return str(ipaddress.ip_address(value.strip("[]")))
    except ValueError:
        pass
    labels = value.split(".")
    if not value or len(value) > _MAX_DNS_NAME or not all(map(_DNS_LABEL.match, labels)):
        raise SecureError(
            f"{field}={value!r} must be an IP address or a DNS name (e.g. 10.0.0.5, r1.lan)"
        )
    return value


def _check_endpoint(field: str, endpoint: str) -> tuple[str, str]:
    """The endpoint and the host part of it (what the node's certificate must be valid for)."""
    match = _ENDPOINT.match(endpoint)
    port = int(match["port"]) if match else 0
    if match is None or not 1 <= port <= _MAX_PORT:
        raise SecureError(
            f"{field}={endpoint!r} must look like 'tls/10.0.0.5:7447' or 'tls/r1.lan:7447' "
            f"(port 1-{_MAX_PORT})"
        )
    host = _check_san(field, match["host"])
    try:
        unspecified = ipaddress.ip_address(host).is_unspecified
    except ValueError:
        unspecified = False
    if unspecified:
        raise SecureError(
            f"{field}={endpoint!r}: the other nodes connect to this address, so it must be "
            "the node's own address, not a wildcard"
        )
    return endpoint, host


def plan_fleet(
    *,
    optimizer: str,
    robots: Sequence[str],
    operators: Sequence[str] = (),
    endpoints: Mapping[str, str] | None = None,
    sans: Sequence[str] = (),
    node_sans: Mapping[str, Sequence[str]] | None = None,
    base_port: int = DEFAULT_BASE_PORT,
) -> Fleet:
    """Check every name and address once, and decide each node's endpoint and certificate names.

    ``endpoints`` maps a node to ``tls/HOST:PORT``; a node without one gets
    ``tls/127.0.0.1:<base_port + its index>``. ``sans`` go into every certificate, ``node_sans``
    into one node's.
    """
    if isinstance(robots, str) or isinstance(operators, str):
        raise SecureError("robots and operators must be sequences of names, not one string")
    roles = [(_check_name("optimizer", optimizer), NodeRole.OPTIMIZER)]
    roles += [(_check_name("robots", name), NodeRole.ROBOT) for name in robots]
    roles += [(_check_name("operators", name), NodeRole.OPERATOR) for name in operators]
    if not robots:
        raise SecureError("robots=[]: a fleet needs at least one robot")
    seen: dict[str, str] = {}
    for name, role in roles:
        if name.lower() in seen:
            raise SecureError(
                f"name {name!r} appears twice ({seen[name.lower()]} and {role.value}); "
                "names must differ (ignoring case: they are host names)"
            )
        seen[name.lower()] = role.value
    endpoints = dict(endpoints or {})
    node_sans = dict(node_sans or {})
    for field, mapping in (("endpoint", endpoints), ("san", node_sans)):
        for name in mapping:
            if name not in {n for n, _ in roles}:
                raise SecureError(
                    f"{field} for {name!r}: no such node ({', '.join(n for n, _ in roles)})"
                )
    if isinstance(base_port, bool) or not 1 <= base_port <= _MAX_PORT - len(roles) + 1:
        raise SecureError(f"base_port={base_port!r} must be 1-{_MAX_PORT - len(roles) + 1}")
    common = [_check_san("san", value) for value in sans]
    nodes: list[FleetNode] = []
    used: dict[str, str] = {}
    for index, (name, role) in enumerate(roles):
        endpoint = endpoints.get(name, f"tls/127.0.0.1:{base_port + index}")
        endpoint, host = _check_endpoint(f"endpoint[{name}]", endpoint)
        if endpoint in used:
            raise SecureError(
                f"endpoint[{name}]={endpoint!r} is also the endpoint of {used[endpoint]!r}: "
                "two nodes cannot listen on one address"
            )
        used[endpoint] = name
        own = [_check_san(f"san[{name}]", value) for value in node_sans.get(name, ())]
        names = _unique([name, *_LOOPBACK_SANS, host, *common, *own])
        nodes.append(FleetNode(name, role, endpoint, tuple(names)))
    return Fleet(tuple(nodes))


def _unique(items: Iterable[str]) -> list[str]:
    return list(dict.fromkeys(items))
