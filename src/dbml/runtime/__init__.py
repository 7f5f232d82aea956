"""The dbml runtime: managed publishers and subscribers, the optimizer node, rate control."""

from dbml.runtime.graph import is_managed, published_topics, publisher_hosts, remote_subscribers
from dbml.runtime.metadata import MessageMeta
from dbml.runtime.optimizer import ChannelState, OptimizerNode, Round
from dbml.runtime.priority import PrioritySource, collision_priority_source
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.rate import Rate, RateLimiter
from dbml.runtime.subscriber import ManagedSubscriber

__all__ = [
    "ChannelState",
    "ManagedPublisher",
    "ManagedSubscriber",
    "MessageMeta",
    "OptimizerNode",
    "PrioritySource",
    "Rate",
    "RateLimiter",
    "Round",
    "collision_priority_source",
    "is_managed",
    "published_topics",
    "publisher_hosts",
    "remote_subscribers",
]
