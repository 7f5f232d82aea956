"""Rules read off the live graph: where a topic is published, and whether it is managed."""

from __future__ import annotations

from collections.abc import Iterable

from dbml.transports.base import GraphEntry, Role, Variant

__all__ = ["is_managed", "published_topics", "publisher_hosts", "remote_subscribers"]


def publisher_hosts(entries: Iterable[GraphEntry], topic: str) -> set[str]:
    """The hosts that publish ``topic``."""
    return {e.host for e in entries if e.role is Role.PUBLISHER and e.topic == topic}


def published_topics(entries: Iterable[GraphEntry]) -> set[str]:
    """Every topic someone publishes: the live channels."""
    return {e.topic for e in entries if e.role is Role.PUBLISHER}


def remote_subscribers(entries: Iterable[GraphEntry], topic: str) -> set[GraphEntry]:
    """Subscribers of ``[topic]/optimized`` on a host where ``topic`` is not published."""
    entries = list(entries)
    local = publisher_hosts(entries, topic)
    return {
        e
        for e in entries
        if e.role is Role.SUBSCRIBER
        and e.topic == topic
        and e.variant is Variant.OPTIMIZED
        and e.host not in local
    }


def is_managed(entries: Iterable[GraphEntry], topic: str) -> bool:
    """A channel is managed while at least one remote host subscribes to its optimized copy.

    (The original checked ``[topic]`` for remote subscribers, where remote subscribers never are,
    so a remote operator never made a topic managed.)
    """
    return bool(remote_subscribers(entries, topic))
