"""The ROS 1 graph: the master's registrations, by the host of each node.

Each node's host is the host of its URI, which ``ROS_IP`` / ``ROS_HOSTNAME`` decide. The graph is
refreshed only while someone watches it, and nodes that no longer answer (killed without
unregistering) are left out. Nothing here imports rospy: it is the master's XML-RPC API.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from urllib.parse import urlparse

from dbml.core.errors import TransportError
from dbml.protocol.schema import GLOBAL_PREFIX
from dbml.transports.base import (
    Closer,
    GraphEntry,
    Handle,
    Role,
    Variant,
    check_topic,
    of_topic,
)
from dbml.transports.callbacks import CallbackList
from dbml.transports.ros1.master import CALL_TIMEOUT_S, MasterClient
from dbml.transports.worker import PeriodicWorker

__all__ = ["GRAPH_POLL_S", "LIVENESS_S", "NODE_PING_TIMEOUT_S", "Ros1Graph", "split"]

log = logging.getLogger("dbml.ros1")

GRAPH_POLL_S = 0.25
"""How often a watched graph is re-read from the master (one ``getSystemState`` call)."""
LIVENESS_S = 2.0
"""How long a node's answer to ``getPid`` counts as alive."""
NODE_PING_TIMEOUT_S = 0.5
"""How long a node has to answer ``getPid`` before it counts as gone."""
_OPTIMIZED = "/" + Variant.OPTIMIZED.value
_RESERVED = f"{GLOBAL_PREFIX}/"
"""A ``dbm`` segment: the topic is dbml's own (``[topic]/dbm/priority``), not a channel."""


def split(ros_topic: str) -> tuple[str, Variant]:
    """A ROS topic as dbml's topic and variant: ``/x/optimized`` is ``/x``'s optimized copy."""
    if ros_topic.endswith(_OPTIMIZED) and len(ros_topic) > len(_OPTIMIZED):
        return ros_topic[: -len(_OPTIMIZED)], Variant.OPTIMIZED
    return ros_topic, Variant.FULL


class Ros1Graph:
    """The master's view of who publishes and subscribes what, by the host of each node.

    A watched graph is re-read every ``poll_s`` by a ``PeriodicWorker``: a read that fails is
    logged and the next one retries; should the thread die all the same, ``alive`` says so.
    What is remembered of nodes (their URIs, when they last answered) is kept for the nodes of
    the last read only, so it never outgrows the graph.
    """

    def __init__(self, master: MasterClient, poll_s: float) -> None:
        self._master = master
        self._lock = threading.Lock()
        self._entries: frozenset[GraphEntry] | None = None
        self._uris: dict[str, str] = {}
        self._alive: dict[str, float] = {}
        self._watchers: CallbackList[[]] = CallbackList()
        self._worker = PeriodicWorker(
            self._poll, interval_s=poll_s, name="dbml-ros1-graph", log=log
        )
        self._polling = False
        self._reading = threading.Lock()
        """One read at a time (the poller's, a caller's): they share what is known of nodes."""

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        """Nothing to do: declaring the ROS publisher or subscriber registered it already."""
        check_topic(topic)
        return Closer(lambda: None)

    def _host(self, node: str) -> str | None:
        """The host part of a node's URI, if the node answers (cached for ``LIVENESS_S``)."""
        uri = self._uris.get(node)
        if uri is None:
            uri = self._master.call("lookupNode", node, missing_ok=True)
            if uri is None:
                return None
            self._uris[node] = uri
        now = time.monotonic()
        if now - self._alive.get(node, -LIVENESS_S) >= LIVENESS_S:
            try:
                with MasterClient(
                    uri, caller_id=self._master.caller_id, timeout_s=NODE_PING_TIMEOUT_S
                ) as node_api:
                    node_api.call("getPid")
            except TransportError:
                self._uris.pop(node, None)
                return None
            self._alive[node] = now
        return urlparse(uri).hostname

    def _read(self) -> frozenset[GraphEntry]:
        with self._reading:
            return self._read_locked()

    def _read_locked(self) -> frozenset[GraphEntry]:
        publishers, subscribers, _services = self._master.call("getSystemState")
        entries = set()
        listed: set[str] = set()
        for role, listing in ((Role.PUBLISHER, publishers), (Role.SUBSCRIBER, subscribers)):
            for ros_topic, nodes in listing:
                topic, variant = split(ros_topic)
                if _RESERVED in f"{topic}/":
                    continue  # dbml's own (a channel's priority topic): not a channel
                for node in nodes:
                    listed.add(node)
                    host = self._host(node)
                    if host is not None:
                        entries.add(GraphEntry(role, host, topic, variant, f"{node} {ros_topic}"))
        for known in (self._uris, self._alive):  # forget the nodes that left the graph
            for node in [n for n in known if n not in listed]:
                known.pop(node, None)
        return frozenset(entries)

    def refresh(self) -> bool:
        """Re-read the graph; True if it changed."""
        fresh = self._read()
        with self._lock:
            changed = fresh != self._entries
            self._entries = fresh
        return changed

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        """The graph as last read (read now when nobody watches it)."""
        with self._lock:
            cached, polling = self._entries, self._polling
        if cached is None or not polling:
            self.refresh()  # nobody keeps it fresh: read it now
            with self._lock:
                cached = self._entries
        assert cached is not None
        return of_topic(cached, topic)

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        """Call ``callback()`` when any topic's entries change; the first watch starts polling."""
        handle = self._watchers.add(callback)
        with self._lock:
            start, self._polling = not self._polling, True
        if start:
            self._worker.start()
        return handle

    def _poll(self) -> None:
        """One poll: re-read, and tell the watchers if the graph changed."""
        try:
            changed = self.refresh()
        except TransportError as err:  # the master is away: the next poll retries
            log.warning("graph: %s", err)
            return
        if changed:
            self._watchers.fire()

    @property
    def alive(self) -> bool:
        """False once the polling thread died."""
        return self._worker.alive

    def close(self) -> None:
        """Stop the polling (waiting for a poll in progress, bounded)."""
        self._worker.stop(timeout_s=CALL_TIMEOUT_S * 2)
