"""The DDS graph as dbml reads it: who publishes and subscribes what, by host; the parameter nodes.

dbml's node names carry their host (``dbml_<host>__<id>``); another node's host is read from its
endpoint GID where the RMW is Fast DDS (bytes 2-3: a hash of the host's IPv4 addresses) and
matched to the dbml host with the same hash; elsewhere it is unknown and the endpoint counts as
remote. A foreign subscription of ``[topic]/optimized`` is always a remote consumer, as the
paper defines it. ``read_graph`` is one read of it (on the transport's executor thread); the
rest is pure.
"""

from __future__ import annotations

import re
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from dbml.core.errors import TransportError
from dbml.protocol import keys
from dbml.protocol.names import OPTIMIZED, check_topic
from dbml.protocol.schema import GLOBAL_PREFIX
from dbml.transports.base import (
    Closer,
    GraphEntry,
    Handle,
    Role,
    Variant,
    of_topic,
    resolve_host,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.overflow import LogOnce, Overflow
from dbml.transports.rclpy.fastdds import GID_BYTES, gid_host_id
from dbml.transports.rclpy.nodes import (
    PARTICIPANT_BYTES,
    claim_topic,
    is_param_node,
)

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = [
    "MAX_TOPICS",
    "DdsGraph",
    "Graph",
    "foreign_host",
    "host_of_node",
    "is_channel_topic",
    "node_name_for",
    "read_graph",
    "split",
]

MAX_TOPICS = 4_096
"""Topics of the graph read at most per poll (beyond: ignored, logged once per flood)."""
_NODE_PREFIX = "dbml_"
_ESCAPE = re.compile(r"[^A-Za-z0-9]")
_UNESCAPE = re.compile(r"_([0-9a-f]{2})")
_DBML_NODE = re.compile(r"dbml_((?:[A-Za-z0-9]|_[0-9a-f]{2})+)__[0-9a-f]{8}")
_INFRASTRUCTURE = frozenset({"/parameter_events", "/rosout"})
_OPTIMIZED_SUFFIX = Variant.OPTIMIZED.key("")
_COMPRESSED_SUFFIX = Variant.COMPRESSED.key("")
_FOREIGN_HOST = "ros2:"


def node_name_for(host: str) -> str:
    """A unique ROS 2 node name for dbml on ``host`` that says the host (``dbml_r1__1a2b3c4d``).

    Every character a node name may not hold is escaped as ``_`` and two hex digits, so the
    host reads back exactly (``host_of_node``).
    """
    escaped = _ESCAPE.sub(lambda m: f"_{ord(m.group()):02x}", resolve_host(host))
    return f"{_NODE_PREFIX}{escaped}__{uuid.uuid4().hex[:8]}"


def host_of_node(name: str) -> str | None:
    """The host a dbml node's name says, or None if the name is not dbml's."""
    match = _DBML_NODE.fullmatch(name)
    if match is None:
        return None
    return _UNESCAPE.sub(lambda m: chr(int(m.group(1), 16)), match.group(1))


def split(ros_topic: str) -> tuple[str, Variant]:
    """A ROS topic as dbml's topic and variant: ``/x/optimized`` is ``/x``'s optimized copy."""
    for suffix, variant in (
        (_OPTIMIZED_SUFFIX, Variant.OPTIMIZED),
        (_COMPRESSED_SUFFIX, Variant.COMPRESSED),
    ):
        if ros_topic.endswith(suffix) and len(ros_topic) > len(suffix):
            return ros_topic[: -len(suffix)], variant
    return ros_topic, Variant.FULL


def is_channel_topic(topic: str) -> bool:
    """A topic the graph reports: not ROS's own, not dbml's parameters or priorities."""
    if topic in _INFRASTRUCTURE:
        return False
    try:
        check_topic(topic)
    except TransportError:
        return False
    return "/dbm/" not in f"{topic}/" and OPTIMIZED not in topic.split("/")[:-1]


def foreign_host(role: Role, variant: Variant, gid: bytes, host_ids: dict[int, set[str]]) -> str:
    """Where a node that is not dbml's runs: the dbml host with its GID's host id, if one.

    A subscription of an optimized copy is a remote consumer whatever its host (the paper's
    definition), and an endpoint whose host cannot be told is another host.
    """
    if role is Role.SUBSCRIBER and variant.managed:
        return f"{_FOREIGN_HOST}{gid.hex()}"
    host_id = gid_host_id(gid)
    hosts = host_ids.get(host_id, set()) if host_id is not None else set()
    if len(hosts) == 1:
        return next(iter(hosts))
    return f"{_FOREIGN_HOST}{gid.hex() if host_id is None else f'{host_id:04x}'}"


@dataclass(frozen=True, slots=True)
class DdsGraph:
    """One read of the DDS graph: dbml's entries and what the transport and its store need."""

    entries: frozenset[GraphEntry]
    types: dict[str, str]
    """Each ROS topic's type, as other processes' publishers declare it."""
    best_effort: set[str]
    """ROS topics with at least one best-effort publisher."""
    dbml_peers: int
    """Other dbml nodes seen."""
    param_hosts: dict[str, frozenset[bytes]]
    """Each parameter node's hosting participants (GID prefixes)."""
    claimed: dict[str, frozenset[bytes]]
    """Those that host it for good (their claim endpoint)."""
    own: bytes | None
    """This process's participant, once its own node's endpoints show."""
    senders: set[bytes]
    """GIDs of ``/dbm``'s allocation publishers."""


def read_graph(node: Node, *, topics_overflow: Overflow, bad: LogOnce) -> DdsGraph:
    """One read of the graph through ``node`` (on the executor thread).

    Entries by host, topic types, parameter nodes and their claims.
    """
    from rclpy.qos import ReliabilityPolicy

    listed: set[tuple[str, str]] = set()
    dbml_hosts: dict[tuple[str, str], str] = {}
    for name, namespace in node.get_node_names_and_namespaces():
        listed.add((namespace, name))
        host = host_of_node(name)
        if host is not None:
            dbml_hosts[(namespace, name)] = host
    topics = node.get_topic_names_and_types()
    if len(topics) > MAX_TOPICS:
        topics_overflow.refuse(len(topics) - MAX_TOPICS)
        topics = topics[:MAX_TOPICS]
    infos: list[tuple[Role, str, Any]] = []
    types: dict[str, str] = {}
    best_effort: set[str] = set()
    senders: set[bytes] = set()
    host_ids: dict[int, set[str]] = {}
    param_hosts: dict[str, set[bytes]] = {}
    claimed: dict[str, set[bytes]] = {}
    published: dict[str, list[tuple[bytes, str]]] = {}
    own: bytes | None = None
    for topic, _types in topics:
        publishers = node.get_publishers_info_by_topic(topic)
        subscribers = node.get_subscriptions_info_by_topic(topic)
        for role, listing in ((Role.PUBLISHER, publishers), (Role.SUBSCRIBER, subscribers)):
            for info in listing:
                where = (info.node_namespace, info.node_name)
                if where not in listed:
                    continue  # not named yet (``_NODE_NAME_UNKNOWN_``): next poll
                gid = bytes(info.endpoint_gid)[:GID_BYTES]
                if role is Role.PUBLISHER:
                    if info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT:
                        best_effort.add(topic)
                    published.setdefault(topic, []).append(
                        (gid[:PARTICIPANT_BYTES], info.topic_type)
                    )
                host = dbml_hosts.get(where)
                host_id = gid_host_id(gid)
                if host is not None and host_id is not None:
                    host_ids.setdefault(host_id, set()).add(host)
                if info.node_name == node.get_name() and info.node_namespace == "/":
                    own = gid[:PARTICIPANT_BYTES]
                fqn = is_param_node(info.node_namespace, info.node_name)
                if fqn is not None:
                    param_hosts.setdefault(fqn, set()).add(gid[:PARTICIPANT_BYTES])
                    # A host's claim: /dbm's allocation publisher, a channel's host topic.
                    if (fqn == GLOBAL_PREFIX and topic == keys.ALLOCATION_TOPIC) or (
                        fqn != GLOBAL_PREFIX and topic == claim_topic(fqn)
                    ):
                        claimed.setdefault(fqn, set()).add(gid[:PARTICIPANT_BYTES])
                        if topic == keys.ALLOCATION_TOPIC:
                            senders.add(gid)
                infos.append((role, topic, info))
    for topic, by in published.items():
        # Other processes' publishers say a topic's type (this one's own follow it, and
        # are asked only when nobody else publishes it).
        found = {msg_type for prefix, msg_type in by if prefix != own} or {
            msg_type for _prefix, msg_type in by
        }
        if len(found) > 1:
            bad.warning(
                f"types:{topic}",
                "%s has publishers of types %s: using %s",
                topic,
                sorted(found),
                min(found),
            )
        if found:
            types[topic] = min(found)
    entries = set()
    for role, topic, info in infos:
        channel, variant = split(topic)
        if not is_channel_topic(channel):
            continue
        gid = bytes(info.endpoint_gid)[:GID_BYTES]
        host = dbml_hosts.get((info.node_namespace, info.node_name))
        if host is None:
            host = foreign_host(role, variant, gid, host_ids)
        entries.add(GraphEntry(role, host, channel, variant, gid.hex()))
    return DdsGraph(
        frozenset(entries),
        types,
        best_effort,
        len(dbml_hosts) - 1,
        {n: frozenset(p) for n, p in param_hosts.items()},
        {n: frozenset(p) for n, p in claimed.items()},
        own,
        senders,
    )


class Graph:
    """The DDS graph as dbml's entries, re-read on the executor thread every ``GRAPH_POLL_S``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: frozenset[GraphEntry] = frozenset()
        self.watchers: CallbackList[[]] = CallbackList()
        self.hosts_seen: set[str] = set()

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        """Nothing to do: the publisher or subscription declared is in the graph already."""
        check_topic(topic)
        return Closer(lambda: None)

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        """The graph as last read."""
        with self._lock:
            return of_topic(self._entries, topic)

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        """Call ``callback()`` when a read changed the entries (any topic's)."""
        return self.watchers.add(callback)

    def update(self, entries: frozenset[GraphEntry]) -> None:
        """The entries of a new read; the watchers are told if they changed."""
        with self._lock:
            changed, self._entries = entries != self._entries, entries
        if changed:
            self.watchers.fire()
