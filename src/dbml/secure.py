"""A secure fleet: one certificate authority, and a certificate and a zenoh config per node.

Out of the box dbml authenticates nobody: any process that reaches the loopback mesh (or an
endpoint) may write any parameter, including the budget. A fleet across machines needs more, so
``dbml secure init`` makes:

- a fleet CA (``ca.key``, ``ca.pem``) that signs every node's certificate;
- per node a key and a certificate whose common name is the node's name (the optimizer, each
  robot, each operator), valid for the node's name, ``localhost``, 127.0.0.1, the address of its
  endpoint and any extra names given;
- per node a zenoh config (``<name>.json5``): peer mode over TLS with mutual authentication, so a
  peer without a certificate from the CA cannot even connect, and access control that lets a
  connected peer write only what its role owns.

zenoh enforces the rules on every node as messages arrive (ingress), keyed by the common name of
the sending peer's certificate: a subject per node; a rule applies to a message when the rule's
key expression includes the message's (so a wildcard cannot reach past what a rule grants); and
within one subject a deny rule beats an allow rule (the tests check each of these on real
sessions). What a node sends (egress) is not restricted by its own config: its peers judge it.
Because the subject is the neighbour that delivered a message, the rules hold in a full mesh of
peers, which is what the configs build (every node connects to every other node's endpoint); a
zenoh router in the path would speak for every node behind it.

This module is pure data plus the writing of files: it never opens a session.
"""

from __future__ import annotations

import datetime as dt
import enum
import ipaddress
import json
import os
import re
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dbml.core.errors import DbmlError

if TYPE_CHECKING:  # cryptography loads only when files are written: the CLI parser imports us
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

__all__ = [
    "CA_CERTIFICATE",
    "CA_KEY",
    "DEFAULT_BASE_PORT",
    "DEFAULT_DAYS",
    "Fleet",
    "FleetNode",
    "NodeFiles",
    "NodeRole",
    "SecureError",
    "WrittenFile",
    "access_control",
    "fleet_from_flags",
    "init_fleet",
    "plan_fleet",
    "zenoh_config",
]

CA_KEY = "ca.key"
"""The CA's private key: whoever holds it can mint any node's identity; keep it off the fleet."""
CA_CERTIFICATE = "ca.pem"
DEFAULT_BASE_PORT = 17448
"""Nodes without an endpoint listen on ``tls/127.0.0.1:<base + index>`` (loopback trials); the
default stays clear of zenohd's 7447 and of dbml's loopback rendezvous 17447."""
DEFAULT_DAYS = 365
"""How long the CA and node certificates are valid; renew by running init again (``--force``)."""

_NAME = re.compile(r"^[A-Za-z](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")
"""A node name is a host name label that is also a topic segment and a key expression chunk."""
_RESERVED = frozenset({"ca", "dbm", "dbml"})
"""``ca`` names the CA's files; a robot ``dbm`` or ``dbml`` would own dbml's own key space."""
_DNS_LABEL = re.compile(r"^[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")
_MAX_DNS_NAME = 253
_MAX_PORT = 65_535
_ENDPOINT = re.compile(r"^tls/(?P<host>\[[0-9A-Fa-f:.]+\]|[^/\[\]:]+):(?P<port>[0-9]+)$")
_LOOPBACK_SANS = ("localhost", "127.0.0.1")
"""Every certificate holds these too, so any node can run on loopback or in a namespace."""

_PARAM = "dbml/param"
_OWN = "dbml/own"
_BATCH = "dbml/batch"
_GRAPH = "dbml/graph"
_NODE = "dbml/node"
_LINK = "dbm/link"
"""The data key of the estimator's beacon (``dbml.runtime.estimator.LINK_TOPIC``, ``/dbm/link``):
the optimizer's node runs the estimator and puts it; everyone may subscribe. Without it a
secured fleet would silently lose outage handling."""
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

_OPTIMIZER_FIELDS = ("dbm/frequency/current_value", "dbm/managed")
"""A channel's fields only the optimizer writes (its allocation), relative to the topic."""
_OPTIMIZER_GLOBALS = (
    "dbm/status",
    "dbm/status_message",
    "dbm/estimated_bandwidth_in_mbit",
    "dbm/estimator_state",
    "dbm/round",
)
_OPERATOR_GLOBALS = (
    "dbm/max_bandwidth_in_mbit",
    "dbm/max_bandwidth_utilization",
    "dbm/optimization_rate_in_seconds",
    "dbm/strategy",
    "dbm/frame_headroom",
)
_OPERATOR_FIELDS = ("dbm/priority",)
"""A channel's fields an operator may set on any robot's channel."""


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


@dataclass(frozen=True, slots=True)
class NodeFiles:
    """Where a node finds its TLS files: the paths its zenoh config names."""

    ca_certificate: Path
    certificate: Path
    private_key: Path


@dataclass(frozen=True, slots=True)
class WrittenFile:
    """One file ``init_fleet`` wrote, and whether it is a secret (mode 0600)."""

    path: Path
    description: str
    secret: bool


# -- the plan -------------------------------------------------------------------------------


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


def _split_names(field: str, text: str) -> list[str]:
    """``"r1,r2"`` as names; an empty text is no name, an empty item is an error."""
    if not text.strip():
        return []
    names = [item.strip() for item in text.split(",")]
    for name in names:
        if not name:
            raise SecureError(f"{field}={text!r} has an empty name")
    return names


def _split_assignment(field: str, item: str) -> tuple[str, str]:
    name, sep, value = item.partition("=")
    if not sep or not name.strip() or not value.strip():
        raise SecureError(f"{field}={item!r} must look like NAME=VALUE")
    return name.strip(), value.strip()


def fleet_from_flags(
    *,
    optimizer: str,
    robots: str,
    operators: str = "",
    endpoints: Sequence[str] = (),
    sans: Sequence[str] = (),
    base_port: int = DEFAULT_BASE_PORT,
) -> Fleet:
    """The fleet from the command line's text: ``r1,r2``, ``NAME=ENDPOINT``, ``[NAME=]SAN``."""
    by_node: dict[str, str] = {}
    for item in endpoints:
        name, endpoint = _split_assignment("--endpoint", item)
        if name in by_node:
            raise SecureError(f"--endpoint {item!r}: {name!r} has an endpoint already")
        by_node[name] = endpoint
    common: list[str] = []
    node_sans: dict[str, list[str]] = {}
    for item in sans:
        if "=" in item:
            name, value = _split_assignment("--san", item)
            node_sans.setdefault(name, []).append(value)
        else:
            common.append(item)
    return plan_fleet(
        optimizer=optimizer,
        robots=_split_names("--robots", robots),
        operators=_split_names("--operators", operators),
        endpoints=by_node,
        sans=common,
        node_sans=node_sans,
        base_port=base_port,
    )


# -- the documents --------------------------------------------------------------------------


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


def _owned(node: FleetNode) -> tuple[list[str], list[str]]:
    """The parameter names ``node`` may write and, within them, those it may not (no slash)."""
    if node.role is NodeRole.ROBOT:
        return [f"{node.name}/**"], [f"{node.name}/**/{field}" for field in _OPTIMIZER_FIELDS]
    if node.role is NodeRole.OPERATOR:
        return [*_OPERATOR_GLOBALS, *(f"**/{field}" for field in _OPERATOR_FIELDS)], []
    return [*_OPTIMIZER_GLOBALS, *(f"**/{field}" for field in _OPTIMIZER_FIELDS)], []


def _node_rules(node: FleetNode) -> list[dict[str, Any]]:
    allowed, denied = _owned(node)
    puts = [f"{_PARAM}/{name}" for name in allowed]
    replies = [f"{_OWN}/*/{name}" for name in allowed]
    if node.role is NodeRole.ROBOT:
        puts.insert(0, f"{node.name}/**")  # its topics' data: /r1/camera is key r1/camera
    elif node.role is NodeRole.OPTIMIZER:
        puts[:0] = [_BATCH, _LINK]
        replies = [f"{_OWN}/**"]  # it keeps, and serves, values whose writer has left
    prefix = f"{node.name}/"
    rules = [
        _rule(prefix + "put", ["put"], puts),
        _rule(prefix + "reply", ["reply"], replies),
        _rule(prefix + "graph", ["liveliness_token"], [f"{_GRAPH}/*/{node.name}/**"]),
    ]
    if denied:
        rules.append(
            _rule(prefix + "put-deny", ["put"], [f"{_PARAM}/{n}" for n in denied], deny=True)
        )
        rules.append(
            _rule(prefix + "reply-deny", ["reply"], [f"{_OWN}/*/{n}" for n in denied], deny=True)
        )
    return rules


def access_control(fleet: Fleet) -> dict[str, Any]:
    """The ``access_control`` section of every node's zenoh config (the same on all).

    Default deny. Every node may subscribe to anything, serve and query ``dbml/own/**``, declare
    its session token ``dbml/node/*/*`` and watch ``dbml/**`` liveliness; beyond that each node
    may put and reply only on what its role owns (a robot: its topics' data and its channels'
    parameters except the optimizer's fields; an operator: the budget settings and any
    channel's priority; the optimizer: its batch, status and allocation fields) and declare graph
    tokens under its own host name. Rule ids hold a ``/`` (node rules) or not (common rules), so
    no node name can collide with another rule's id.
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
        _rule("own-values", ["declare_queryable", "query"], [f"{_OWN}/**"]),
        _rule("node-token", ["liveliness_token"], [f"{_NODE}/*/*"]),
        _rule("liveliness", ["declare_liveliness_subscriber", "liveliness_query"], ["dbml/**"]),
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


def zenoh_config(fleet: Fleet, name: str, files: NodeFiles) -> dict[str, Any]:
    """The zenoh config of node ``name``: a TLS peer of the mesh with the fleet's access control.

    It listens on its endpoint and connects to every other node's, retrying forever in the
    background, so nodes start in any order. It also listens on a free port of the same address:
    a second process of the node (an operator's ``dbml priority`` beside its ``dbml monitor``)
    finds the endpoint taken (not fatal) and is reached there instead, its peers learning the
    port by gossip, so every process still meets every other directly.
    """
    node = fleet.node(name)
    spare = node.endpoint.rpartition(":")[0] + ":0"
    others = [other.endpoint for other in fleet.nodes if other.name != name]
    return {
        "mode": "peer",
        "listen": {
            "endpoints": [node.endpoint, spare],
            "timeout_ms": 0,  # a taken endpoint is not retried: close() would wait for it
            "exit_on_failure": False,
        },
        "connect": {
            "endpoints": others,
            "timeout_ms": -1,
            "exit_on_failure": False,
            "retry": {"period_init_ms": 100, "period_max_ms": 2000, "period_increase_factor": 2},
        },
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}, "delay": 0},
        "transport": {
            "shared_memory": {"enabled": False},
            "link": {
                "tls": {
                    "root_ca_certificate": str(files.ca_certificate),
                    "listen_certificate": str(files.certificate),
                    "listen_private_key": str(files.private_key),
                    "connect_certificate": str(files.certificate),
                    "connect_private_key": str(files.private_key),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                },
            },
        },
        "access_control": access_control(fleet),
    }


# -- certificates and files -----------------------------------------------------------------


def _key() -> ec.EllipticCurvePrivateKey:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _general_name(value: str) -> x509.GeneralName:
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(value))
    except ValueError:
        return x509.DNSName(value)


def _ca(
    key: ec.EllipticCurvePrivateKey, now: dt.datetime, days: int, fleet: Fleet
) -> x509.Certificate:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    subject = x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, f"dbml fleet CA ({fleet.nodes[0].name})"),
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dbml"),
        ]
    )
    public = key.public_key()
    return (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .sign(key, hashes.SHA256())
    )


def _node_certificate(
    node: FleetNode,
    key: ec.EllipticCurvePrivateKey,
    *,
    ca: x509.Certificate,
    ca_key: ec.EllipticCurvePrivateKey,
    now: dt.datetime,
    days: int,
) -> x509.Certificate:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    public = key.public_key()
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, node.name)]))
        .issuer_name(ca.subject)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            # every node both listens (server) and connects (client)
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.SubjectAlternativeName([_general_name(value) for value in node.sans]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )


def _write(path: Path, data: bytes, *, secret: bool) -> None:
    """Write atomically with the final mode from the start: a key is never readable by others."""
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as file:
            os.fchmod(file.fileno(), 0o600 if secret else 0o644)
            file.write(data)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _config_text(fleet: Fleet, node: FleetNode, files: NodeFiles) -> str:
    header = (
        f"// zenoh config of dbml node {node.name!r} ({node.role.value}), "
        "written by `dbml secure init`.\n"
        f"// Use it as: dbml ... --zenoh-config {files.certificate.with_suffix('.json5')} "
        f"--host {node.name}\n"
        "// (the host identity must equal the certificate's name, or the graph rules refuse it).\n"
    )
    return header + json.dumps(zenoh_config(fleet, node.name, files), indent=2) + "\n"


def init_fleet(
    directory: str | Path,
    fleet: Fleet,
    *,
    force: bool = False,
    days: int = DEFAULT_DAYS,
    install_dir: str | Path | None = None,
    now: dt.datetime | None = None,
) -> tuple[WrittenFile, ...]:
    """Write the CA, every node's key, certificate and zenoh config into ``directory``.

    Nothing is written when one of the files exists already, unless ``force``. The configs name
    the TLS files under ``install_dir`` (default: ``directory``, absolute): where the files
    will be on the nodes. Keys are written with mode 0600, the rest 0644.
    """
    if isinstance(days, bool) or not isinstance(days, int) or days < 1:
        raise SecureError(f"days={days!r} must be a whole number of days >= 1")
    target = Path(directory)
    installed = Path(install_dir) if install_dir is not None else target.resolve()
    if not installed.is_absolute():
        raise SecureError(f"install_dir={str(install_dir)!r} must be an absolute path")
    if target.exists() and not target.is_dir():
        raise SecureError(f"directory={str(target)!r} exists and is not a directory")
    names = [CA_KEY, CA_CERTIFICATE]
    for node in fleet.nodes:
        names += [f"{node.name}.key", f"{node.name}.pem", f"{node.name}.json5"]
    existing = [name for name in names if (target / name).exists()]
    if existing and not force:
        shown = ", ".join(existing[:3]) + (f" and {len(existing) - 3} more" if existing[3:] else "")
        raise SecureError(
            f"directory={str(target)!r} already holds {shown}: "
            "pass --force to replace them (and every node's identity)"
        )
    try:
        target.mkdir(mode=0o700, parents=True, exist_ok=True)
        return _write_fleet(target, installed, fleet, days=days, now=now)
    except OSError as err:
        raise SecureError(f"directory={str(target)!r}: {err}") from err


def _write_fleet(
    target: Path, installed: Path, fleet: Fleet, *, days: int, now: dt.datetime | None
) -> tuple[WrittenFile, ...]:
    from cryptography.hazmat.primitives import serialization

    now = now or dt.datetime.now(dt.UTC)
    ca_key = _key()
    ca = _ca(ca_key, now, days, fleet)
    written = [
        WrittenFile(target / CA_KEY, "fleet CA key: keep it off the fleet", True),
        WrittenFile(target / CA_CERTIFICATE, "fleet CA certificate: every node", False),
    ]
    _write(written[0].path, _pem_key(ca_key), secret=True)
    _write(written[1].path, ca.public_bytes(serialization.Encoding.PEM), secret=False)
    for node in fleet.nodes:
        key = _key()
        certificate = _node_certificate(node, key, ca=ca, ca_key=ca_key, now=now, days=days)
        files = NodeFiles(
            installed / CA_CERTIFICATE,
            installed / f"{node.name}.pem",
            installed / f"{node.name}.key",
        )
        for path, data, what, secret in (
            (target / f"{node.name}.key", _pem_key(key), "key", True),
            (
                target / f"{node.name}.pem",
                certificate.public_bytes(serialization.Encoding.PEM),
                f"certificate (CN={node.name}, SAN={','.join(node.sans)})",
                False,
            ),
            (
                target / f"{node.name}.json5",
                _config_text(fleet, node, files).encode(),
                f"zenoh config, listens on {node.endpoint}",
                False,
            ),
        ):
            _write(path, data, secret=secret)
            written.append(WrittenFile(path, f"{node.role.value} {node.name}: {what}", secret))
    return tuple(written)
