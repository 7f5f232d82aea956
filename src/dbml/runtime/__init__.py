"""The dbml runtime: typed parameters, managed publisher and subscriber, the optimizer node."""

from dbml.protocol.metadata import MessageMeta
from dbml.runtime.graph import is_managed, published_topics, publisher_hosts, remote_subscribers
from dbml.runtime.optimizer import ChannelState, OptimizerNode, Round
from dbml.runtime.params import ChannelParams, DbmParams, ParamView
from dbml.runtime.priority import PrioritySource, collision_priority_source
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.rate import Rate, RateLimiter
from dbml.runtime.subscriber import ManagedSubscriber

__all__ = [
    "ChannelParams",
    "ChannelState",
    "DbmParams",
    "ManagedPublisher",
    "ManagedSubscriber",
    "MessageMeta",
    "OptimizerNode",
    "ParamView",
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
