"""dbml's parameters as real ROS 2 parameters: ``ros2 param set`` does what ``rosparam set`` did.

The paper's globals live on the optimizer's node ``/dbm`` (``ros2 param set /dbm
max_bandwidth_in_mbit 5``), a channel's on ``[topic]/dbm``, hosted by the process that publishes
or bridges the channel (``ros2 param set /r1/camera/dbm priority 0.8``). Each node declares the
wire schema's parameters of its scope (``dbml.protocol.schema``, ``frequency.min`` for
``frequency/min``) with their values, so ``ros2 param list/get/describe`` show them.

What carries what, and why:

- **Every process's view** is fed by ``/parameter_events`` (the node that hosts a value announces
  each change) and, for a node met for the first time, one ``GetParameters`` call: the node is
  the value's single source, as ROS 2 intends. Anyone may publish an event naming any node, so
  one is believed only from a participant the graph shows hosting that node (a new host's
  events wait, in order, until the graph names it), and a node's values leave the view with it.
- **An operator's write** (``ros2 param set``, ``dbml budget``, ``dbml priority``) goes through
  the hosting node's ``SetParameters`` service. The node validates it with the schema and refuses,
  with the reason, a value out of range or one that dbml owns: a service call names no caller,
  so only the values anyone may write are taken from it.
- **The optimizer's allocation** (``frequency.current_value``, ``managed`` of every channel) is
  one message per round on the dbml topic ``/dbm/allocation``, sent by the ``/dbm`` node: one
  message, not a service call per channel, and its sender is known (the publisher's GID), so the
  channel's host takes it from the optimizer's node only and applies it to its own parameter.
  The message holds the whole allocation and is sent again with each round's heartbeat on a
  transient-local topic, so a host that joined or matched late has it all within a round.
- **A process's own parameters** (a publisher's sizes and rates, the optimizer's status) are set
  on the node it hosts, which announces them.

Writing never blocks: ``set`` updates this process's view at once and hands the write to the
transport's executor thread, where every rclpy call of the store runs (no lock is held across
one). A write for a node nobody hosts yet makes this process its provisional host, so values can
precede the process that owns them (an operator's priority before the robot starts); a
provisional host gives the node up once another process hosts it too, pushing its values there
first.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from dbml.core.errors import TransportError
from dbml.protocol import keys
from dbml.protocol.schema import (
    GLOBAL_PREFIX,
    PARAMETERS,
    ROUND,
    Kind,
    ParamError,
    Parameter,
    Scope,
    Writer,
    check_param,
    lookup,
)
from dbml.transports.base import ParamValue, check_param_value
from dbml.transports.overflow import LogOnce, Overflow
from dbml.transports.rclpy.nodes import (
    DBM_NODE,
    PARTICIPANT_BYTES,
    ROS_OWN,
    allocated,
    check_ros_name,
    claim_topic,
    full_name,
    hosts_it,
    node_of,
    python_value,
    scope_of,
    yields,
)
from dbml.transports.replica import Replica, Write

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.publisher import Publisher as RosPublisher

__all__ = [
    "FETCH_TIMEOUT_S",
    "MAX_CLIENTS",
    "MAX_PARAM_NODES",
    "MAX_UNATTRIBUTED",
    "MAX_UNVERIFIED",
    "MAX_UNVERIFIED_SENDERS",
    "UNATTRIBUTED_S",
    "RclpyHost",
    "RclpyParams",
    "descriptor",
]

log = logging.getLogger("dbml.rclpy")

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
"""An ``IntegerRange``'s bounds are int64."""

MAX_PARAM_NODES = 8_192
"""The most parameter nodes remembered (met, fetched); beyond, new ones are ignored (logged)."""
MAX_UNVERIFIED = 1_024
"""Events of one sender waiting for the graph to name it a host (the oldest go first)."""
MAX_UNVERIFIED_SENDERS = 64
"""Senders whose events wait so at once (a fleet starting; beyond, the oldest go)."""
MAX_UNATTRIBUTED = 8
"""Senders whose allocation waits for the graph to name them (their newest message each)."""
UNATTRIBUTED_S = 5.0
"""How long an allocation waits for the graph to name its sender (discovery takes < 1 s)."""
FETCH_TIMEOUT_S = 2.0
"""A ``GetParameters`` unanswered this long is asked again (an answer takes milliseconds)."""
MAX_CLIENTS = 256
"""Service clients kept open to other processes' nodes; the least recently used is closed."""


@dataclass
class _Hosted:
    """A parameter node this process hosts."""

    node: Node
    provisional: bool
    """Hosted only because nobody did when this process wrote: given up once another hosts it."""
    claim: RosPublisher[Any] | None = None
    """The endpoint that says this process hosts the node for good (None while provisional):
    the ``/dbm`` node's allocation publisher, a channel node's ``[topic]/dbm/host``."""


class RclpyHost(Protocol):
    """What the parameter sync needs of its transport: the executor thread and a few entities.

    The rclpy transport is one; the sync never names its class (no import circle).
    """

    @property
    def host(self) -> str:
        """This process's host identity."""
        ...

    @property
    def context(self) -> Any:
        """The transport's rclpy context, for the parameter nodes."""
        ...

    @property
    def node(self) -> Node:
        """The transport's own node, for service clients."""
        ...

    def run(self, task: Callable[[], None]) -> bool:
        """Run ``task`` on the executor thread and wait for it; False if the transport closed."""
        ...

    def call_soon(self, task: Callable[[], None]) -> None:
        """Run ``task`` on the executor thread, soon (where every rclpy call of dbml's runs)."""
        ...

    def poll_soon(self) -> None:
        """Read the graph at once rather than at the next tick."""
        ...

    def add_node(self, node: Node) -> None:
        """Spin a parameter node with the transport's own (executor thread)."""
        ...

    def remove_node(self, node: Node) -> None:
        """Stop spinning and destroy a parameter node (executor thread)."""
        ...

    def string_publisher(self, node: Node, topic: str) -> Any:
        """``node``'s ``std_msgs/msg/String`` publisher of ``topic``, its newest message kept."""
        ...


class RclpyParams:
    """The ``ParamStore`` of ``RclpyTransport`` (``replica``) and its sync with the nodes.

    Every method that touches rclpy runs on the transport's executor thread (``_on_*``,
    ``_drain``, ``poll``, ``on_event``, ``on_allocation``); the replica is read and written
    from any thread.
    """

    def __init__(self, transport: RclpyHost) -> None:
        self._transport = transport
        self._lock = threading.Lock()
        self._handed: dict[str, int] = {}
        """Per name this process wrote: the stamp of its latest write handed to rclpy."""
        self._confirmed: dict[str, int] = {}
        """Per name written to another process's node: the stamp of the write it took last."""
        self._nodes_overflow = Overflow("parameter nodes", MAX_PARAM_NODES, log=log)
        self._bad = LogOnce(log)
        self.replica = Replica(
            transport.host,
            send=self._send,
            log=log,
            check_name=check_ros_name,
            sender_name="dbml-rclpy-param-send",
        )
        # Executor-thread state: never touched elsewhere.
        self._hosted: dict[str, _Hosted] = {}
        self._internal = False
        """True while this process sets its own node's parameters (not a service request)."""
        self._live: dict[str, int] = {}
        """Parameter nodes other processes host (fully qualified name: how many host it)."""
        self._hosts: Mapping[str, frozenset[bytes]] = {}
        """Each parameter node's hosting participants, as the graph last showed them."""
        self._unverified: OrderedDict[bytes, deque[tuple[str, list[tuple[str, object]]]]] = (
            OrderedDict()
        )
        """Events waiting for the graph to show their sender hosting their node: by sender
        participant, in arrival order (executor thread)."""
        self._unverified_since: dict[bytes, float] = {}
        """Since when each sender's first waiting event waits."""
        self._fetched: set[str] = set()
        """Live nodes whose values were fetched once (a node met again is fetched again)."""
        self._fetching: dict[str, float] = {}
        """Nodes asked and not answered yet, and when (an answer lost is asked again)."""
        self._clients: OrderedDict[tuple[str, str], Any] = OrderedDict()
        self._waiting: OrderedDict[str, dict[str, ParamValue]] = OrderedDict()
        """Operator writes for nodes that another process will host, by node, until it does."""
        self._allocation_senders: AbstractSet[bytes] = frozenset()
        """GIDs of ``/dbm``'s allocation publishers, as the graph last showed them."""
        self._unattributed: OrderedDict[bytes, tuple[str, float]] = OrderedDict()
        """The newest allocation of each sender the graph did not name yet, and when."""
        self._allocation: dict[str, ParamValue] = {}
        """Everything this process allocated (it is the optimizer): sent whole every time."""

    # -- this process's writes: the replica hands them over -------------------------------------

    def _send(self, write: Write) -> None:
        """Hand one write to the executor thread and wait until it was (the sender's thread)."""
        if not self._transport.run(lambda: self._drain(write)):
            log.debug("closed with a parameter write not handed over: %s", ", ".join(write.values))

    def confirmed(self, name: str) -> bool:
        """Whether a node of another process took this process's latest write of ``name``."""
        if self.replica.pending(name):
            return False
        with self._lock:
            handed = self._handed.get(name)
            return handed is not None and self._confirmed.get(name) == handed

    def settled(self) -> bool:
        """Whether every write was handed over and every live parameter node met was read."""
        with self._lock:
            read = set(self._live) <= self._fetched
        return read and self.replica.unsent() == 0

    def _learn(
        self, node: str, values: Iterable[tuple[str, object]], *, asked_at: int | None = None
    ) -> None:
        """Values a node announced or returned: validated, then held; changes are told.

        A fetch's answer (``asked_at``: the replica's mark when it was asked) is older than any
        value written or announced since it was asked: those names keep what they have.
        """
        for ros2_name, raw in values:
            name = full_name(node, ros2_name)
            if name is None:
                continue
            try:
                value = check_param(name, check_param_value(raw))
            except (ParamError, TransportError) as err:
                self._bad.warning(name, "ignoring %s from node %s: %s", name, node, err)
                continue
            self.replica.arrived(name, value, writer=node, asked_at=asked_at)

    # -- executor thread -----------------------------------------------------------------------

    def _drain(self, write: Write) -> None:
        """Hand a write to rclpy: local nodes, allocation, other processes' nodes.

        Only what is still the newest of it: a name another process set on a node hosted here
        meanwhile keeps that process's value.
        """
        pending = self.replica.current(write)
        with self._lock:
            for name in pending:
                self._handed[name] = write.stamp
        by_node: dict[str, dict[str, tuple[Parameter, ParamValue]]] = {}
        allocation: dict[str, ParamValue] = {}
        for name, value in pending.items():
            parameter, node, ros2_name = node_of(name)
            if allocated(parameter) and node not in self._hosted:
                allocation[name] = value
                continue
            by_node.setdefault(node, {})[ros2_name] = (parameter, value)
        if allocation and GLOBAL_PREFIX not in self._hosted:
            # Only the optimizer writes these: this process is the optimizer, /dbm is its node.
            self._host(GLOBAL_PREFIX, provisional=False)
        elif allocation and self._hosted[GLOBAL_PREFIX].provisional:
            self._claim(GLOBAL_PREFIX, self._hosted[GLOBAL_PREFIX])
        for node, writes in by_node.items():
            hosting = any(hosts_it(p) for p, _v in writes.values())
            hosted = self._hosted.get(node)
            if hosted is None and (hosting or node not in self._live):
                hosted = self._host(node, provisional=not hosting)
            elif hosted is not None and hosted.provisional and hosting:
                self._claim(node, hosted)
            if hosted is not None:
                self._set_local(node, hosted, {n: v for n, (_p, v) in writes.items()})
            else:
                self._set_remote(node, {n: v for n, (_p, v) in writes.items()})
        if allocation or (self._allocation and ROUND.name in pending):
            self._send_allocation(allocation)

    def _host(self, node: str, *, provisional: bool) -> _Hosted | None:
        """Create node ``node`` here, declaring its scope's parameters with the view's values."""
        from rclpy.node import Node

        scope = scope_of(node)
        namespace = "/" if scope is Scope.GLOBAL else node[: -len(GLOBAL_PREFIX)]
        ros_node = Node(
            DBM_NODE,
            namespace=namespace,
            context=self._transport.context,
            start_parameter_services=True,
            use_global_arguments=False,  # the paper's names, whatever remapping moves
        )
        ros_node.add_on_set_parameters_callback(lambda parameters: self._on_set(node, parameters))
        hosted = _Hosted(ros_node, provisional)
        self._hosted[node] = hosted
        self._internal = True
        try:
            for parameter in PARAMETERS:
                if parameter.scope is not scope:
                    continue
                name = parameter.name if scope is Scope.GLOBAL else f"{node}/{parameter.field}"
                ros_node.declare_parameter(
                    parameter.ros2_name, self.replica.get(name), descriptor(parameter)
                )
        finally:
            self._internal = False
        if not provisional:
            self._claim(node, hosted)
        self._transport.add_node(ros_node)
        log.debug("hosting %s%s", node, " (provisionally)" if provisional else "")
        return hosted

    def _claim(self, node: str, hosted: _Hosted) -> None:
        """Host ``node`` for good: an endpoint of it says so to every provisional host.

        The ``/dbm`` node's allocation publisher; a channel node's ``[topic]/dbm/host``, which
        holds this process's host (``ros2 topic echo /r1/camera/dbm/host`` says who hosts it).
        """
        from std_msgs.msg import String

        hosted.provisional = False
        if node == GLOBAL_PREFIX:
            hosted.claim = self._transport.string_publisher(hosted.node, keys.ALLOCATION_TOPIC)
        else:
            hosted.claim = self._transport.string_publisher(hosted.node, claim_topic(node))
            hosted.claim.publish(String(data=self._transport.host))

    def _set_local(self, node: str, hosted: _Hosted, writes: Mapping[str, ParamValue]) -> None:
        """Set parameters of a node this process hosts (its announcement reaches everyone)."""
        from rclpy.parameter import Parameter as RosParameter

        self._internal = True
        try:
            for ros2_name, value in writes.items():
                found = lookup(f"{node}/{ros2_name.replace('.', '/')}")
                assert found is not None, ros2_name  # the view holds dbml's parameters only
                if not hosted.node.has_parameter(ros2_name):
                    hosted.node.declare_parameter(ros2_name, None, descriptor(found[0]))
                if value is None:
                    # Unset, and declared again with no value: ``ros2 param list`` still shows it.
                    hosted.node.set_parameters([RosParameter(ros2_name, RosParameter.Type.NOT_SET)])
                    hosted.node.declare_parameter(ros2_name, None, descriptor(found[0]))
                    continue
                results = hosted.node.set_parameters([RosParameter(ros2_name, value=value)])
                if not results[0].successful:
                    log.warning("%s/%s=%r not set: %s", node, ros2_name, value, results[0].reason)
        except Exception:  # one node's failure must not lose the other nodes' writes
            log.exception("%s: parameters not set", node)
        finally:
            self._internal = False

    def _on_set(self, node: str, parameters: list[Any]) -> Any:
        """A hosted node's set: this process's own writes pass; a service request is checked."""
        from rcl_interfaces.msg import SetParametersResult

        taken: list[tuple[str, ParamValue]] = []
        for parameter in parameters:
            name = full_name(node, parameter.name)
            if name is None:
                if parameter.name in ROS_OWN:
                    continue
                return SetParametersResult(
                    successful=False, reason=f"{parameter.name!r} is not a dbml parameter"
                )
            if not self._internal and parameter.value is None:
                return SetParametersResult(
                    successful=False, reason=f"{name} cannot be deleted: set a value instead"
                )
            try:
                checked = check_param(name, check_param_value(parameter.value))
            except (ParamError, TransportError) as err:
                return SetParametersResult(successful=False, reason=str(err))
            found = lookup(name)
            assert found is not None
            if not self._internal and Writer.OPERATOR not in found[0].writers:
                owners = ", ".join(sorted(w.value for w in found[0].writers))
                return SetParametersResult(
                    successful=False,
                    reason=f"{name} is written by dbml's {owners}, not by an operator",
                )
            taken.append((name, checked))
        if not self._internal:
            # Another process set them on a node hosted here: the view follows at once, and a
            # write of this process still on its way is older (it is not handed over).
            for name, value in taken:
                self.replica.arrived(name, value, writer=node, supersede=True)
        return SetParametersResult(successful=True)

    def _client(self, kind: str, node: str) -> Any:
        """A cached service client of ``node``'s ``get_parameters``/``set_parameters``."""
        from rcl_interfaces.srv import GetParameters, SetParameters

        key = (kind, node)
        client = self._clients.get(key)
        if client is None:
            service = GetParameters if kind == "get" else SetParameters
            client = self._transport.node.create_client(service, f"{node}/{kind}_parameters")
            self._clients[key] = client
            if len(self._clients) > MAX_CLIENTS:
                _old, oldest = self._clients.popitem(last=False)
                self._transport.node.destroy_client(oldest)
        self._clients.move_to_end(key)
        return client

    def _set_remote(self, node: str, writes: Mapping[str, ParamValue]) -> None:
        """Ask another process's node to take operator writes (its ``SetParameters``)."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter as RosParameter

        client = self._client("set", node)
        if not client.service_is_ready():
            self._waiting.setdefault(node, {}).update(writes)
            self._waiting.move_to_end(node)
            while len(self._waiting) > MAX_PARAM_NODES:
                self._waiting.popitem(last=False)
                self._nodes_overflow.refuse()
            return
        request = SetParameters.Request()
        request.parameters = [
            RosParameter(name, RosParameter.Type.NOT_SET).to_parameter_msg()
            if value is None
            else RosParameter(name, value=value).to_parameter_msg()
            for name, value in writes.items()
        ]
        future = client.call_async(request)
        names = list(writes)
        with self._lock:  # which of this process's writes the request carries
            stamps = [self._handed.get(full_name(node, n) or "") for n in names]
        future.add_done_callback(lambda done: self._on_set_reply(node, names, stamps, done))

    def _on_set_reply(
        self, node: str, names: list[str], stamps: list[int | None], future: Any
    ) -> None:
        response = future.result()
        if response is None:
            return
        refused = False
        for ros2_name, stamp, result in zip(names, stamps, response.results, strict=False):
            name = full_name(node, ros2_name)
            if name is None:
                continue
            if result.successful:
                if stamp is not None:
                    with self._lock:
                        self._confirmed[name] = stamp
            else:
                refused = True
                log.warning("%s refused %s: %s", node, name, result.reason)
        if refused:
            self._fetch(node)  # the view held the refused value: take the node's again

    def _send_allocation(self, values: Mapping[str, ParamValue]) -> None:
        """The whole allocation, changed by ``values``, from the ``/dbm`` node hosted here.

        Whole, and sent again with every round's heartbeat on a transient-local topic: a channel
        host that matched the publisher late, or missed a message, has it all by the next round.
        """
        hosted = self._hosted.get(GLOBAL_PREFIX)
        if hosted is None or hosted.claim is None:
            return
        self._allocation.update(values)
        for name in list(self._allocation):  # channels whose node left are allocated no more
            if node_of(name)[1] not in self._hosts and node_of(name)[1] not in self._hosted:
                del self._allocation[name]
        from std_msgs.msg import String

        data = keys.encode_batch(self._allocation, time.time_ns(), self._transport.host)
        hosted.claim.publish(String(data=data.decode()))

    def on_allocation(self, data: str, *, sender: bytes | None) -> None:
        """``/dbm/allocation``: values for the channels hosted here, from ``/dbm``'s node only.

        DDS may deliver a new publisher's message before the graph names its node: such a
        message waits (the newest per sender, a few senders) for the next poll to say whose.
        """
        if sender is None:
            return
        if sender not in self._allocation_senders:
            if len(data) > keys.MAX_WRITE_BYTES:
                return
            self._unattributed[sender] = (data, time.monotonic())
            self._unattributed.move_to_end(sender)
            while len(self._unattributed) > MAX_UNATTRIBUTED:
                self._unattributed.popitem(last=False)
            return
        self._apply_allocation(data)

    def _apply_allocation(self, data: str) -> None:
        try:
            values, _stamp, _writer = keys.decode_batch(data.encode())
        except TransportError as err:
            self._bad.warning("allocation", "ignoring an allocation: %s", err)
            return
        by_node: dict[str, dict[str, ParamValue]] = {}
        for name, value in values.items():
            found = lookup(name)
            if found is None or not allocated(found[0]):
                self._bad.warning(name, "ignoring %s in an allocation: not the optimizer's", name)
                continue
            try:
                checked = check_param(name, value)
            except ParamError as err:
                self._bad.warning(name, "ignoring an allocation: %s", err)
                continue
            _parameter, node, ros2_name = node_of(name)
            hosted = self._hosted.get(node)
            if hosted is not None and hosted.node.get_parameter(ros2_name).value != checked:
                by_node.setdefault(node, {})[ros2_name] = checked
        for node, writes in by_node.items():
            self._set_local(node, self._hosted[node], writes)
            self._learn(node, writes.items())

    def _attribute(self) -> None:
        """Apply the waiting allocations whose sender the graph now shows as ``/dbm``'s."""
        now = time.monotonic()
        for gid, (data, heard_s) in list(self._unattributed.items()):
            if gid in self._allocation_senders:
                del self._unattributed[gid]
                self._apply_allocation(data)
            elif now - heard_s > UNATTRIBUTED_S:
                del self._unattributed[gid]
                self._bad.warning(
                    "allocation-sender",
                    "ignoring allocations from a publisher that is not the /dbm node (gid %s)",
                    gid.hex(),
                )

    def on_event(
        self, node: str, changed: Iterable[tuple[str, object]], *, sender: bytes | None
    ) -> None:
        """``/parameter_events`` of a parameter node: its new, changed and deleted values.

        Believed only from a participant the graph shows hosting ``node`` (anyone may publish
        an event naming any node), and never about a node hosted here (this process knows its
        own values). A node hosted elsewhere and not read yet is read at the next poll.
        """
        if node in self._hosted or sender is None:
            return
        participant = sender[:PARTICIPANT_BYTES]
        queue = self._unverified.get(participant)
        if queue is None and participant in self._hosts.get(node, frozenset()):
            self._learn(node, changed)
            return
        # A node that just started may announce before the graph names it: its events wait
        # (dbml's names only) for the graph to say whose they are, and so do the sender's
        # later ones, in order: one writer's writes are seen in the order written.
        if queue is None:
            queue = self._unverified[participant] = deque()
        if len(queue) >= MAX_UNVERIFIED:
            queue.popleft()
        queue.append((node, [(n, v) for n, v in changed if full_name(node, n) is not None]))
        self._unverified_since.setdefault(participant, time.monotonic())
        while len(self._unverified) > MAX_UNVERIFIED_SENDERS:
            dropped, _queue = self._unverified.popitem(last=False)
            self._unverified_since.pop(dropped, None)
        self._transport.poll_soon()

    def _verify(self) -> None:
        """Learn waiting events, in order, as the graph shows their sender hosting their node.

        A sender whose first waiting event stays unverified for ``UNATTRIBUTED_S`` is not a
        host of that node: its waiting events are dropped (logged once per node).
        """
        now = time.monotonic()
        for participant, queue in list(self._unverified.items()):
            while queue and participant in self._hosts.get(queue[0][0], frozenset()):
                node, values = queue.popleft()
                if node not in self._hosted:
                    self._learn(node, values)
                self._unverified_since[participant] = now
            if not queue:
                del self._unverified[participant]
                self._unverified_since.pop(participant, None)
            elif now - self._unverified_since.get(participant, now) > UNATTRIBUTED_S:
                del self._unverified[participant]
                self._unverified_since.pop(participant, None)
                self._bad.warning(
                    f"events:{queue[0][0]}",
                    "ignoring events about %s from a process not hosting it",
                    queue[0][0],
                )

    def _fetch(self, node: str, *, again: bool = False) -> None:
        """Ask ``node`` for its values once it answers (``GetParameters``).

        One question at a time per node; one unanswered for ``FETCH_TIMEOUT_S`` is asked again.
        ``again`` asks even if the node was read already (a reader missing its values).
        """
        from rcl_interfaces.srv import GetParameters

        if node not in self._live:
            return  # nobody hosts it (a publisher whose process has no parameter node)
        asked_s = self._fetching.get(node)
        if asked_s is not None and time.monotonic() - asked_s < FETCH_TIMEOUT_S:
            return
        if again:
            with self._lock:
                self._fetched.discard(node)
        client = self._client("get", node)
        if not client.service_is_ready():
            return  # the next poll tries again
        scope = scope_of(node)
        names = [p.ros2_name for p in PARAMETERS if p.scope is scope]
        self._fetching[node] = time.monotonic()
        asked_at = self.replica.mark()
        future = client.call_async(GetParameters.Request(names=names))

        def done(finished: Any) -> None:
            self._fetching.pop(node, None)
            response = finished.result()
            if response is None:
                return
            values = [(n, python_value(v)) for n, v in zip(names, response.values, strict=False)]
            # A node's unset parameter says nothing: another host may hold a value for it.
            self._learn(node, [(n, v) for n, v in values if v is not None], asked_at=asked_at)
            with self._lock:
                self._fetched.add(node)

        future.add_done_callback(done)

    def poll(
        self,
        hosts: Mapping[str, frozenset[bytes]],
        claimed: Mapping[str, frozenset[bytes]],
        own: bytes | None,
        allocation_senders: AbstractSet[bytes],
    ) -> None:
        """The graph's parameter nodes now: fetch new ones, give provisional ones up, resend.

        ``hosts`` gives each node's hosting participants (GID prefixes), ``claimed`` those that
        host it for good (``_claim``), ``own`` this process's participant.
        """
        self._allocation_senders = allocation_senders
        if len(hosts) > MAX_PARAM_NODES:
            self._nodes_overflow.refuse(len(hosts) - MAX_PARAM_NODES)
            hosts = dict(list(hosts.items())[:MAX_PARAM_NODES])
        self._hosts = hosts
        live = {node: len(by - {own}) for node, by in hosts.items() if by - {own}}
        with self._lock:
            gone = [n for n in self._live if n not in live and n not in self._hosted]
            self._live = live
            self._fetched &= set(live)
            fetch = [n for n in live if n not in self._fetched]
        for step, action in (
            ("allocations", self._attribute),
            ("events", self._verify),
            ("departures", lambda: self._forget(gone)),
            ("fetches", lambda: self._fetch_all(fetch)),
            ("hand-overs", lambda: self._hand_over(hosts, claimed, own)),
            ("waiting writes", lambda: self._resend(live)),
        ):
            try:
                action()
            except Exception:  # one step's failure must not stop the others, nor the next poll
                log.exception("parameters: %s failed", step)

    def _fetch_all(self, nodes: Iterable[str]) -> None:
        for node in nodes:
            self._fetch(node)

    def _hand_over(
        self,
        hosts: Mapping[str, frozenset[bytes]],
        claimed: Mapping[str, frozenset[bytes]],
        own: bytes | None,
    ) -> None:
        for node, hosted in list(self._hosted.items()):
            if (
                hosted.provisional
                and own is not None
                and yields(own, hosts.get(node, frozenset()), claimed.get(node, frozenset()))
            ):
                self._give_up(node, hosted)

    def _resend(self, live: Mapping[str, int]) -> None:
        for node in [n for n in self._waiting if n in live]:
            writes = self._waiting.pop(node)
            self._set_remote(node, writes)
        for node in [n for n in self._fetching if n not in live]:
            del self._fetching[node]

    def _forget(self, gone: Iterable[str]) -> None:
        """Nodes that left the graph: their values go with them, as a ROS 2 node's do.

        Names this process wrote stay (it may host them again, or hand them over), so what the
        network filled is what the network's departures empty.
        """
        for node in gone:
            self.replica.forget(f"{node}/")

    def _give_up(self, node: str, hosted: _Hosted) -> None:
        """Another process hosts ``node`` too: push what anyone may write there, then leave it.

        What is pushed is what this process wrote, as its node holds it (not the view: the view
        may have heard the new host's declaration before these values). The node is then read
        from its host again: while hosted here its announcements were not heard, and a read
        made meanwhile may have been answered by this process's own node.
        """
        writes: dict[str, ParamValue] = {}
        for parameter in PARAMETERS:
            if parameter.scope is not scope_of(node) or Writer.OPERATOR not in parameter.writers:
                continue
            name = parameter.name if node == GLOBAL_PREFIX else f"{node}/{parameter.field}"
            if not self.replica.wrote(name) or not hosted.node.has_parameter(parameter.ros2_name):
                continue  # only what this process wrote: the rest it only heard
            held = hosted.node.get_parameter(parameter.ros2_name).value
            if held is not None:
                writes[parameter.ros2_name] = held
        self._close_hosted(node, hosted)
        with self._lock:
            self._fetched.discard(node)  # the next poll reads it
        self._fetching.pop(node, None)
        if writes:
            self._set_remote(node, writes)
        log.debug("%s is hosted elsewhere now: gave it up", node)

    def _close_hosted(self, node: str, hosted: _Hosted) -> None:
        del self._hosted[node]
        self._transport.remove_node(hosted.node)  # its endpoints with it

    def refresh(self, node: str) -> None:
        """Read ``node``'s values again (a reader that sees its publisher but misses them)."""
        self._transport.call_soon(lambda: self._fetch(node, again=True))

    def hosts(self, node: str) -> bool:
        """Whether this process hosts ``node`` (executor thread)."""
        return node in self._hosted

    def close(self) -> None:
        """Destroy the hosted nodes and the clients (executor stopped)."""
        for node, hosted in list(self._hosted.items()):
            self._close_hosted(node, hosted)
        self._clients.clear()


def descriptor(parameter: Parameter) -> Any:
    """Its ROS 2 descriptor, from the schema: what ``ros2 param describe`` and rqt show.

    A number's range is a ``FloatingPointRange`` and, for an integer (which dynamic typing lets
    in where a float is expected), an ``IntegerRange`` of the integers within it: rclpy refuses
    a value outside either with its own message. An exclusive minimum is the schema's, checked
    in the node's set callback. Who writes it is said in its constraints: SetParameters refuses
    what only dbml writes.
    """
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    constraints = f"values: {parameter.values}; written by: {parameter.writers_text}"
    if Writer.OPERATOR not in parameter.writers:
        constraints += " (not settable through SetParameters)"
    described = ParameterDescriptor(
        dynamic_typing=True, description=parameter.doc, additional_constraints=constraints
    )
    if parameter.kind is Kind.NUMBER:
        low = -sys.float_info.max if parameter.minimum is None else parameter.minimum
        high = sys.float_info.max if parameter.maximum is None else parameter.maximum
        described.floating_point_range = [FloatingPointRange(from_value=low, to_value=high)]
        lowest = math.floor(low) + 1 if parameter.exclusive_minimum else math.ceil(low)
        described.integer_range = [
            IntegerRange(
                from_value=max(lowest, _INT64_MIN), to_value=min(math.floor(high), _INT64_MAX)
            )
        ]
    return described
