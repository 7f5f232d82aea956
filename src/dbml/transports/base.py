"""The transport interface: what the runtime needs from a middleware, and nothing more.

A transport gives a process five things: publish bytes (with attachment metadata) on a topic,
subscribe to a topic, a parameter store with change notification, the live graph (which host
publishes or subscribes which topic variant) and this process's host identity. ``memory`` is the
in-process test double; ``zenoh`` is the real engine; ``ros1`` is rospy and a ROS master;
``rclpy`` real ROS 2; ``ros2`` rmw_zenoh's wire format. All pass one contract test suite.

A transport is a context manager (leaving the block closes it). Capabilities that only some
middleware needs (waiting for peers, confirming a write, typed topics) are part of the
protocol, with the defaults of a store that is complete and synchronous in ``TransportBase``,
so no caller has to ask whether a transport has them.

Topics are ROS-style names (``/r1/camera``). Callbacks may run on a middleware thread: keep them
short and never block in them.
"""

from __future__ import annotations

import enum
import os
import socket
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

from dbml.core.errors import TransportError
from dbml.protocol import names
from dbml.protocol.keys import is_host_name
from dbml.protocol.names import PRIORITY_SUFFIX, check_topic
from dbml.protocol.schema import ParamValue, check_param_value
from dbml.transports.codecs import CDR_FLOAT64, Float64Codec

__all__ = [
    "COMPRESSED_TYPE",
    "DEFAULT_ROUTER_ENDPOINT",
    "EXPEDITED_TOS",
    "PRIORITY_SUFFIX",
    "Closer",
    "GraphEntry",
    "GraphView",
    "Handle",
    "ParamStore",
    "ParamValue",
    "Publisher",
    "Role",
    "Sample",
    "Transport",
    "TransportBase",
    "TransportPriority",
    "Variant",
    "check_param_value",
    "check_topic",
    "of_topic",
    "resolve_host",
]

DEFAULT_ROUTER_ENDPOINT = "tcp/localhost:7447"
"""Where a zenoh router of this host listens (``dbml router``, ``rmw_zenohd``): ROS 2's default.

Here, not beside zenoh, so the command line can name it without importing zenoh."""


def resolve_host(host: str | None = None) -> str:
    """This process's host identity: the argument, else ``DBML_HOST``, else the hostname.

    Test hosts on one machine share a hostname, so the identity must be settable.
    """
    chosen = host if host is not None else os.environ.get("DBML_HOST") or socket.gethostname()
    if not is_host_name(chosen):
        raise TransportError(f"host={chosen!r} must be letters, digits and _-.~ only")
    return chosen


COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
"""The ROS 2 type of a camera's compressed copy (``Variant.COMPRESSED``) on every transport."""


class Variant(enum.StrEnum):
    """Which copy of a topic: every message (``full``), the rate-managed one (``optimized``).

    ``compressed``: a camera's rate-managed copy as ``sensor_msgs/msg/CompressedImage`` at the
    rung the optimizer chose (``[topic]/optimized/compressed``, where image_transport's
    subscribers look for it); it is managed as ``optimized`` is.
    """

    FULL = "full"
    OPTIMIZED = names.OPTIMIZED
    COMPRESSED = names.COMPRESSED

    def key(self, topic: str) -> str:
        """The name this copy of ``topic`` travels under (``/r1/camera/optimized``)."""
        if self is Variant.FULL:
            return topic
        if self is Variant.OPTIMIZED:
            return f"{topic}/{names.OPTIMIZED}"
        return f"{topic}/{names.OPTIMIZED}/{names.COMPRESSED}"

    @property
    def managed(self) -> bool:
        """Whether this copy is the rate-managed one (a remote subscriber makes it managed)."""
        return self is not Variant.FULL


class TransportPriority(enum.StrEnum):
    """A message's class in the middleware's transmission queues, most urgent first.

    zenoh's seven priorities by name (``zenoh.Priority``); a middleware without classes ignores
    it. Within a session's link, a higher class is sent before queued lower ones; with
    priority-dedicated links it also gets a connection of its own (``dbml.transports.zenoh``).
    """

    REAL_TIME = "real_time"
    INTERACTIVE_HIGH = "interactive_high"
    INTERACTIVE_LOW = "interactive_low"
    DATA_HIGH = "data_high"
    DATA = "data"
    DATA_LOW = "data_low"
    BACKGROUND = "background"


EXPEDITED_TOS = 0xB8
"""The IP header's TOS byte on an urgent class's own link: DSCP EF (46, RFC 3246) shifted past
the two ECN bits. The sender's socket is not the only queue: a network that honours DSCP (a
Wi-Fi access point's WMM maps EF to its video queue, a router's DSCP-aware qdisc) then forwards
these packets before the bulk ones waiting at the shared link."""


class Role(enum.StrEnum):
    """What a graph entry declares: publishing or subscribing."""

    PUBLISHER = "pub"
    SUBSCRIBER = "sub"


@dataclass(frozen=True, slots=True)
class GraphEntry:
    """One live declaration: ``host`` publishes or subscribes ``topic`` in ``variant``."""

    role: Role
    host: str
    topic: str
    variant: Variant
    uid: str
    """Unique per declaration, so two identical declarations stay two entries."""


def of_topic(entries: frozenset[GraphEntry], topic: str | None) -> frozenset[GraphEntry]:
    """``entries`` of ``topic`` (all of them for None): ``GraphView.entries``'s filter."""
    return entries if topic is None else frozenset(e for e in entries if e.topic == topic)


@dataclass(frozen=True, slots=True)
class Sample:
    """A received message; ``attachment`` carries the publisher's metadata."""

    topic: str
    payload: bytes
    attachment: bytes | None


class Handle(Protocol):
    """Anything declared that must be undeclared: a subscription, a watch, a graph token."""

    def close(self) -> None:
        """Undeclare it; closing twice does nothing."""
        ...


class Publisher(Protocol):
    """A declared publisher of one topic variant."""

    topic: str

    def put(self, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Send ``payload`` (and the publisher's metadata in ``attachment``).

        Keyword-only, as zenoh's own ``put``: the zenoh transport hands out zenoh's method
        itself, so a small message pays no Python frame of dbml's on the way.
        """
        ...

    @property
    def has_subscribers(self) -> bool:
        """Whether any subscriber matches, so a full-rate copy nobody reads is never sent."""
        ...

    def close(self) -> None:
        """Undeclare the publisher."""
        ...


class ParamStore(Protocol):
    """Parameters under the paper's names, such as ``/r1/camera/dbm/priority``.

    Every process sees every value; the newest write wins; ``watch`` reports every change.
    Every transport's store is a ``dbml.transports.replica.Replica`` and its middleware's sync.

    Writing never blocks, on every transport: ``set`` and ``set_many`` are called from
    middleware callback threads (a publisher answering an allocation), where waiting for the
    network, or for a ROS master whose own push is that callback, could deadlock. A write is
    applied here at once (``get`` sees it before ``set`` returns, and so do this process's
    watchers unless another thread is telling them a change meanwhile, or ``set`` runs in a
    watcher: then they hear it right after) and sent from a thread of the store's own, in
    order, once the network takes it. Watchers hear the changes in the order they were made.

    What ``set`` refuses, alike on every transport, before anything changes (each message names
    the name and the value, as ``/r1/camera/dbm/priority=1.5 must be within [0, 1]``):

    - ``TransportError``: a value that is not a bool, number, string or None;
    - ``TransportError``: a name outside the wire schema (``dbml.protocol.schema.lookup``), or
      one the middleware cannot carry (ROS 2's names have no ``-``, ``.`` or ``~``);
    - ``ParamError``: a value outside the schema's range or choices (``check_param``);
    - ``TransportError``: a new name past the bound of the names this process may write
      (``dbml.transports.replica.MAX_PARAMS``), and a malformed ``host`` of ``set_many``.

    Values from the network are another matter: each sync and the runtime's ``ParamView``
    validate them where they enter, and report and ignore a bad one.
    """

    def set(self, name: str, value: ParamValue) -> None:
        """Write ``name`` (``None`` deletes it); returns at once, never waiting on the network."""
        ...

    def set_many(self, values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
        """Write several names as one update: one message where the middleware allows.

        Every value is checked first: when one is refused, none is written. The optimizer
        pushes a round's allocation this way, not one write per channel. ``host``: the values
        concern the channels published on that host only; a middleware that can address it
        sends them to that host's sessions (and to those that follow every parameter), so a
        robot does not hear the fleet's allocation.
        """
        ...

    def get(self, name: str) -> ParamValue:
        """The value of ``name``; ``None`` when unset."""
        ...

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        """Every set parameter whose name starts with ``prefix``."""
        ...

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        """Call ``callback(name, value)`` on every change; ``value`` is ``None`` on deletion."""
        ...


class GraphView(Protocol):
    """Who publishes and subscribes what, from which host, live."""

    def announce(self, role: Role, topic: str, variant: Variant) -> Handle:
        """Declare that this host plays ``role`` on ``topic``; closing the handle withdraws it."""
        ...

    def entries(self, *, topic: str | None = None) -> frozenset[GraphEntry]:
        """Every live declaration, from every host; ``topic``'s only, if given."""
        ...

    def watch(self, callback: Callable[[], None], *, topic: str | None = None) -> Handle:
        """Call ``callback()`` whenever the entries change.

        ``topic``: at least whenever that topic's entries change. A transport that keeps its
        watchers by topic calls it for that topic's changes alone, so a process with a
        subscriber per channel of a fleet is not woken N times for every one of N changes.
        """
        ...


@runtime_checkable
class Transport(Protocol):
    """What the runtime needs from a middleware: topics, parameters, graph, host, clock."""

    @property
    def host(self) -> str:
        """This process's host identity."""
        ...

    @property
    def params(self) -> ParamStore:
        """The parameter store every process of the network shares."""
        ...

    @property
    def graph(self) -> GraphView:
        """Who publishes and subscribes what, live."""
        ...

    @property
    def has_priorities(self) -> bool:
        """Whether ``declare_publisher``'s ``priority`` and ``express`` change anything here."""
        ...

    @property
    def delivers_at_once(self) -> bool:
        """Whether a message arrives as it is put, never queued on a link (memory's network).

        Elsewhere a frame put before a control message may arrive after it.
        """
        ...

    @property
    def float64(self) -> Float64Codec:
        """A ``std_msgs/Float64`` as this middleware serialises it (a priority from a topic)."""
        ...

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> Publisher:
        """A publisher of ``topic`` in ``variant``.

        ``priority`` (None: the middleware's default class) and ``express`` (send at once,
        unbatched) are hints: a middleware without classes ignores them.
        """
        ...

    def subscribe(
        self, topic: str, callback: Callable[[Sample], None], variant: Variant = Variant.FULL
    ) -> Handle:
        """Call ``callback(sample)`` for every message of ``topic`` in ``variant``."""
        ...

    def now(self) -> float:
        """Monotonic seconds; the memory transport's is injectable."""
        ...

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Wait until another process is reachable and its parameters are known.

        A node that starts by reading parameters must not read an empty store just because its
        peers have not been found yet. True when peers were found (or there is nothing to wait
        for); False after ``timeout_s`` without one.
        """
        ...

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Whether another process holds this process's latest write of ``name``.

        A process that writes and exits at once must know its write outlived it.
        """
        ...

    def refresh(self, entry: GraphEntry) -> None:
        """Ask again for what the process that made ``entry`` wrote (its values are missing).

        A reader that sees a publisher but not its parameters calls it; a no-op where the
        store is complete.
        """
        ...

    def topic_type(self, topic: str, *, timeout_s: float) -> str | None:
        """The message type the graph shows for ``topic`` (``pkg/msg/Name``), as rostopic finds it.

        Waits up to ``timeout_s`` for a publisher. None where topics carry untyped bytes (zenoh,
        memory) or when no publisher of ``topic`` was seen in time.
        """
        ...

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        """Declare the message type of ``topic`` before publishing or subscribing to it.

        ROS 2 puts the type in the key every message travels under; a no-op where topics carry
        untyped bytes. Raises ``TransportError`` naming a type that cannot be resolved.
        """
        ...

    def close(self) -> None:
        """Undeclare everything this transport declared, as a process exit would."""
        ...

    def __enter__(self) -> Self: ...

    def __exit__(self, *_: object) -> None: ...


class TransportBase:
    """The defaults of the optional capabilities, for a store that is complete and synchronous.

    The transports subclass it and override what their middleware needs; ``close`` is theirs.
    """

    has_priorities = False
    """Messages go in one class: a publisher's priority and ``express`` are ignored."""
    delivers_at_once = False
    """Messages cross a network: a frame may wait in a queue while a later message overtakes it."""
    float64 = CDR_FLOAT64
    """CDR, ROS 2's serialisation: what rmw_zenoh and rclpy carry, and zenoh and memory too."""

    def close(self) -> None:
        """Release everything this transport declared; implemented by each transport."""
        raise NotImplementedError

    def wait_for_peers(self, timeout_s: float) -> bool:
        """Nothing to wait for: the store is complete at once."""
        return True

    def confirm_param(self, name: str, *, timeout_s: float) -> bool:
        """Nothing to confirm: a write is everyone's at once."""
        return True

    def refresh(self, entry: GraphEntry) -> None:
        """Nothing to ask again: the store is complete."""

    def topic_type(self, topic: str, *, timeout_s: float) -> str | None:
        """Topics carry untyped bytes here: no type to find."""
        return None

    def set_topic_type(self, topic: str, msg_type: str) -> None:
        """Topics carry untyped bytes here: nothing to declare."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class Closer:
    """A ``Handle`` that runs its action once, on the first ``close()``."""

    def __init__(self, action: Callable[[], None]) -> None:
        self._action: Callable[[], None] | None = action

    def close(self) -> None:
        """Run the action, the first time only."""
        action, self._action = self._action, None
        if action is not None:
            action()
