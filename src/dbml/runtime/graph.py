"""Rules read off the live graph: where a topic is published, and whether it is managed.

Graph entries come from the network, and anyone can declare one, so each rule is the one that
keeps the budget when an entry lies: a channel is managed as soon as any host other than a
publisher's subscribes to its optimized copy, and a subscriber takes the full-rate copy only
when every publisher of the topic is on its own host. A forged "publisher on your host" then
changes nothing; a forged remote subscriber can only lower a channel's rate.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass

from dbml.transports.base import GraphEntry, Role

__all__ = [
    "GraphSummary",
    "is_managed",
    "published_topics",
    "publisher_hosts",
    "remote_subscribers",
    "summarize",
]


def publisher_hosts(entries: Iterable[GraphEntry], topic: str) -> set[str]:
    """The hosts that publish ``topic``."""
    return {e.host for e in entries if e.role is Role.PUBLISHER and e.topic == topic}


def published_topics(entries: Iterable[GraphEntry]) -> set[str]:
    """Every topic someone publishes: the live channels."""
    return {e.topic for e in entries if e.role is Role.PUBLISHER}


def _crosses(subscriber: GraphEntry, hosts: Iterable[str]) -> bool:
    """Whether ``subscriber`` receives the optimized copy from a publisher on another host."""
    return subscriber.variant.managed and any(h != subscriber.host for h in hosts)


def remote_subscribers(entries: Iterable[GraphEntry], topic: str) -> set[GraphEntry]:
    """Subscribers of ``[topic]/optimized`` on a host other than one of the topic's publishers."""
    entries = list(entries)
    hosts = publisher_hosts(entries, topic)
    return {
        e for e in entries if e.role is Role.SUBSCRIBER and e.topic == topic and _crosses(e, hosts)
    }


def is_managed(entries: Iterable[GraphEntry], topic: str) -> bool:
    """A channel is managed while at least one remote host subscribes to its optimized copy.

    (The original checked ``[topic]`` for remote subscribers, where remote subscribers never are,
    so a remote operator never made a topic managed.)
    """
    return bool(remote_subscribers(entries, topic))


@dataclass(frozen=True, slots=True)
class GraphSummary:
    """Every channel of the graph in one pass: its publishers and whether it is managed."""

    publishers: dict[str, frozenset[str]]
    """Each published topic's publisher declarations (uids): a new one has heard nothing yet."""
    hosts: dict[str, frozenset[str]]
    """Each published topic's publishing hosts."""
    managed: frozenset[str]


def summarize(entries: Iterable[GraphEntry]) -> GraphSummary:
    """The graph's channels, read in one pass (the optimizer's per round, whatever the fleet)."""
    entries = list(entries)
    uids: defaultdict[str, set[str]] = defaultdict(set)
    hosts: defaultdict[str, set[str]] = defaultdict(set)
    for entry in entries:
        if entry.role is Role.PUBLISHER:
            uids[entry.topic].add(entry.uid)
            hosts[entry.topic].add(entry.host)
    managed = frozenset(
        e.topic
        for e in entries
        if e.role is Role.SUBSCRIBER and e.topic in hosts and _crosses(e, hosts[e.topic])
    )
    return GraphSummary(
        {t: frozenset(u) for t, u in uids.items()},
        {t: frozenset(h) for t, h in hosts.items()},
        managed,
    )
