"""Budget integrity: the bytes on the wire in every 1-s window against the budget, under churn.

An optimizer (11 Mbit/s, period 1 s), five managed publishers (84,000 / 21,000 / 8,000 / 40,000 /
1,000 B, 1-16 Hz, hosts robot1-5) and a remote subscriber per topic (host operator) run as
``python -m dbml`` processes on a private loopback zenoh mesh. A plain zenoh session (shared
memory off) counts every sample on ``**/optimized`` with ``WireSniffer`` and checks sequence
numbers, so a sniffer that missed or doubled samples shows as ``sniffer_lost``/``_duplicates``.
After a warm-up (every channel allocated, acknowledged and seen; excluded), each run measures
the reference, steady state (10 s: nothing changes, so its worst window is whole-frame
quantisation alone), then churn (``--seconds``, 30): 10 seeded random priority writes per
second, the budget stepped 11 -> 8 Mbit/s at 1/3, a sixth publisher (30,000 B) joining at 1/2
and the 40,000 B one ended by PID at 22/30.

Each byte is charged against the budget in force when it arrived (from the instant before this
process writes the step): a window's ratio is sum(bytes / B(t)), exactly bytes / B when it does
not cross the step. Judging a whole window by one budget (the smaller, or the one at its end)
would charge up to a second of traffic correctly sent under 11 Mbit/s against 8, putting
windows near the step at ~1.37 even with an instant optimizer; this way the optimizer's
reaction time still counts in full, with no grace. The target, ``worst window <= B + one
largest message``, is ratio <= (B + L) / B with B = 11 Mbit/s: after the step that allowance
(6.1 %) is stricter than L / 8 Mbit/s (8.4 %), never more lenient. The allocated sum
(``current_value * size`` over live managed channels, polled every 50 ms) is reported too; a
poll within 0.25 s after the step is judged against the old budget, which is all it can know.

The optimizer runs with ``frame_headroom: true`` (one message per channel but the largest kept
out of the budget, so whole frames cannot add up past B + one message in a window);
``--without-headroom`` allocates the whole budget instead, to see the quantisation it covers.

``--transport rclpy`` runs the same fleet over real ROS 2 (rclpy, Fast DDS) in a ROS 2 domain
claimed for the run, logs in a temporary directory; this process writes the priorities and the
budget step with ``params.set`` (a ``SetParameters`` call to the node hosting each, as ``ros2 param
set`` makes). The sniffer is then a plain rclpy node of this process with a reliable raw
subscription of each channel's ``[topic]/optimized``, stamping each message when DDS received it
(``worst_ratio_at_callback``: by when its executor called back); it counts the bytes of dbml's
publishers (their nodes are dbml's), keeps a foreign node's apart, and checks each publisher's DDS
sequence numbers. During the churn pass a hostile peer process (``--hostile-peer``, a plain rclpy
node named ``hostile_peer``, not ``/dbm``) also runs: a foreign publisher of 84,000-B frames on
``/robot1/camera/optimized``, out-of-range and dbml-owned values through ``SetParameters``, a flood
of ``std_msgs/msg/Float64`` on every ``[topic]/dbm/priority`` (half of them invalid) and a forged
``/dbm/allocation`` giving every channel 16 Hz; ``--no-hostile`` leaves it out. What it sent and
what was refused is in the JSON, with the zenoh-only parts named as not applicable.

    python bench/budget_integrity.py [--json] [--runs 3] [--seconds 30] [--without-headroom]
        [--transport zenoh|rclpy] [--no-hostile]
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import json
import math
import os
import queue
import random
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import zenoh
from rich.console import Console
from rich.table import Table

from dbml.core.errors import TransportError
from dbml.harness.child import Control
from dbml.harness.processes import free_port
from dbml.harness.ros2env import (
    claim_domain,
    fastdds_shm_files,
    remove_fastdds_shm,
    ros2_child_env,
)
from dbml.harness.sniffer import WireSniffer, window_stats
from dbml.harness.supervisor import Supervisor
from dbml.protocol import names
from dbml.protocol.metadata import MessageMeta
from dbml.runtime.graph import is_managed, published_topics
from dbml.transports.base import Handle, ParamValue, Transport
from dbml.transports.zenoh import ZenohTransport
from nodes import Nodes

if TYPE_CHECKING:
    from rclpy.subscription import MessageInfo


class Channel(NamedTuple):
    topic: str
    size_bytes: int
    host: str


CHANNELS = (
    Channel("/robot1/camera", 84_000, "robot1"),
    Channel("/robot2/camera", 21_000, "robot2"),
    Channel("/robot3/lidar", 8_000, "robot3"),
    Channel("/robot4/depth", 40_000, "robot4"),
    Channel("/robot5/imu", 1_000, "robot5"),
)
JOINER = Channel("/robot6/camera", 30_000, "robot6")
LEAVER = CHANNELS[3]
MIN_HZ, MAX_HZ = 1.0, 16.0
BUDGET_MBIT, STEP_MBIT = 11.0, 8.0
PERIOD_S = 1.0
CHANGES_PER_S = 10
STEP_AT, JOIN_AT, LEAVE_AT = 10 / 30, 15 / 30, 22 / 30
"""When the budget step, the join and the leave happen, as shares of the churn pass."""
SEED = 20_240_917
"""Run k draws its priorities from ``random.Random(SEED + k)``."""
STEADY_S = 10.0
OVER_RATIO = 1.05
READY_S = 40.0
"""Bounds reaching the fleet, then every channel allocated, acknowledged and seen (warm-up)."""
POLL_S = 0.05
ALLOCATION_GRACE_S = 0.25
LATE_S = 2.0
"""The churn pass fails when the schedule falls further behind than this (an overloaded host)."""
STOP_S = 5.0
REFERENCE = "steady state: the same fleet with no priority changes, no step, no join, no leave"
TARGET = "worst window <= B + one largest message"
TRANSPORTS = ("zenoh", "rclpy")
HOSTILE_TICK_HZ = 200.0
"""The hostile peer's flood of ``[topic]/dbm/priority`` messages per second (all channels)."""
HOSTILE_FORGED_EVERY = 20
"""Ticks between two forged ``/dbm/allocation`` messages (10 per second)."""
HOSTILE_BAD_SET_EVERY = 40
"""Ticks between two bad ``SetParameters`` requests (5 per second)."""
HOSTILE_FRAME_EVERY = 100
"""Ticks between two foreign frames on ``[topic]/optimized`` (2 per second)."""
HOSTILE_FRAME = CHANNELS[0]
"""Whose ``[topic]/optimized`` the foreign node publishes on, at that channel's size."""
FORGED_HZ = MAX_HZ
"""The rate a forged allocation gives every channel (about twice the budget in all)."""
HOSTILE_S = 10.0
"""Bounds the hostile peer's start and its final report."""
PRIORITY_REFUSAL = "ignoring a priority"
"""What a channel's host logs (once per channel) when it ignores a bad Float64 priority."""
ACK_TIMEOUT = "no acknowledgement of a decrease"
"""What the optimizer logs when it raises rates before a decrease was acknowledged."""
SNIFFER_DEPTH = 100
HOSTILE_PEERS = {
    "foreign_optimized_publisher": (
        "a plain rclpy node publishes 84,000-B Images on /robot1/camera/optimized at 2 Hz; its "
        "bytes are counted apart (foreign_bytes), not against dbml's budget"
    ),
    "bad_set_parameters": (
        "SetParameters at 5/s on /robotN/camera/dbm and /dbm: priority 1.5, -0.1, NaN and "
        "'high', max_bandwidth_in_mbit -1 and 'eleven', frequency.current_value 16 (the "
        "optimizer's) and message_size_in_bytes 1 (the publisher's): each must be refused"
    ),
    "priority_flood": (
        "std_msgs/msg/Float64 on every /robotN/camera/dbm/priority, 200 messages/s in all: "
        "half valid random priorities (taken: a legitimate if noisy path), half NaN, inf, 1.5 "
        "or -0.5 (to be ignored)"
    ),
    "forged_allocation": (
        "std_msgs/msg/String on /dbm/allocation from node /hostile_peer (not /dbm) at 10/s, "
        "giving every channel 16 Hz (about twice the budget): to be ignored"
    ),
}
NOT_APPLICABLE = {
    "sequence numbers in dbml's message metadata": (
        "rclpy carries no dbml attachment; the sniffer checks each DDS writer's publication "
        "sequence numbers instead (sniffer_lost, sniffer_duplicates)"
    ),
    "a sniffer invisible to dbml's graph": (
        "every DDS subscription is a graph endpoint, so the sniffer's subscriptions of "
        "[topic]/optimized are remote consumers; every channel has one (its operator "
        "subscriber) anyway, so nothing is managed that would not be"
    ),
    "one key expression for every channel (**/optimized)": (
        "DDS topics take no wildcards: the sniffer subscribes each channel's, the joiner's too"
    ),
}


def bytes_per_s(mbit: float) -> float:
    return mbit * 1e6 / 8


class BenchError(Exception):
    """A run that could not be measured: a process exited, or the fleet never settled."""


class Fleet(Nodes):
    """The run's nodes; a failed one fails the run."""

    def start_publisher(self, channel: Channel) -> None:
        self.start(
            f"publish-{channel.host}",
            "publish",
            channel.topic,
            "--size-bytes",
            str(channel.size_bytes),
            "--min-hz",
            f"{MIN_HZ:g}",
            "--max-hz",
            f"{MAX_HZ:g}",
            "--host",
            channel.host,
        )

    def check(self) -> None:
        if exited := self.exited():
            raise BenchError(f"exited: {', '.join(exited)}\n{self.logs()}")


def sniffer_session(port: int) -> zenoh.Session:
    """A plain zenoh peer on the run's loopback mesh: no dbml, no shared memory."""
    config = zenoh.Config()
    for key, value in (
        ("mode", '"peer"'),
        ("scouting/multicast/enabled", "false"),
        ("transport/shared_memory/enabled", "false"),
        ("listen/endpoints", '["tcp/127.0.0.1:0"]'),
        ("connect/endpoints", f'["tcp/127.0.0.1:{port}"]'),
    ):
        config.insert_json5(key, value)
    return zenoh.open(config)


class SequenceCount:
    """Which optimized keys a sniffer saw, and the gaps and repeats in each writer's sequence."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._seen: set[str] = set()
        self._last: dict[object, int] = {}
        self._lost = self._duplicates = 0

    def _count_locked(self, key: str, writer: object, seq: int | None) -> None:
        """One sample of ``key`` numbered ``seq`` by ``writer`` (None: not numbered)."""
        self._seen.add(key)
        if seq is None:
            return
        last = self._last.get(writer)
        if last is not None and seq > last + 1:
            self._lost += seq - last - 1
        elif last is not None and seq <= last:
            self._duplicates += 1  # counted twice (or reordered): the sniffer overcounts
        self._last[writer] = seq if last is None else max(last, seq)

    def seen(self) -> set[str]:
        with self._lock:
            return set(self._seen)

    def lost(self) -> int:
        with self._lock:
            return self._lost

    def duplicates(self) -> int:
        with self._lock:
            return self._duplicates


class SequenceGaps(SequenceCount):
    """Which optimized keys were seen, and how many samples the sniffer's session missed."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        super().__init__()
        self._subscriber = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        attachment = sample.attachment
        try:
            seq = MessageMeta.decode(None if attachment is None else attachment.to_bytes()).seq
        except TransportError:
            seq = None
        with self._lock:
            self._count_locked(key, key, seq)

    def close(self) -> None:
        self._subscriber.undeclare()  # type: ignore[no-untyped-call]  # unannotated in stubs


class Sniffer(Protocol):
    """What a pass reads from the wire: dbml's bytes per arrival, and sequence checks."""

    def arrivals(self, *, since_s: float = -math.inf) -> list[tuple[float, int]]: ...
    def clear(self) -> None: ...


class Gaps(Protocol):
    def seen(self) -> set[str]: ...
    def lost(self) -> int: ...
    def duplicates(self) -> int: ...


class Ros2Sniffer(SequenceCount):
    """A plain rclpy node counting every message on each channel's ``[topic]/optimized``.

    Reliable raw subscriptions (dbml's publishers are reliable), so what is missed shows as a
    gap in a writer's DDS publication sequence numbers. Each arrival keeps its writer's GID; the
    graph, read every 0.25 s, names the writer's node, so a foreign node's bytes are kept apart
    (a writer never named is counted as dbml's: against the budget, and said).

    An arrival is stamped when DDS received it (``received_timestamp``), not when the executor
    called back: on a loaded host the callback comes up to 0.1 s later, and frames a late
    executor bunches would fill a window they did not arrive in. The callback's stamp is kept
    beside it (``arrivals(at_callback=True)``), and how late it came.
    """

    def __init__(self, domain_id: int, topics: list[str]) -> None:
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        from dbml.harness.ros2node import PrivateRos
        from dbml.transports.rclpy.graph import host_of_node

        super().__init__()
        self._host_of_node = host_of_node
        self._arrivals: list[tuple[float, int, bytes, float]] = []
        """(received s, bytes, writer, called back s), on this process's monotonic clock."""
        self._owners: dict[bytes, str] = {}
        self._topics = [f"{topic}/optimized" for topic in topics]
        self._ros = PrivateRos(domain_id=domain_id, name="sniffer")
        try:
            self._node = self._ros.node("bench_wire_sniffer")
            qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST,
                depth=SNIFFER_DEPTH,
                reliability=ReliabilityPolicy.RELIABLE,
            )
            for topic in topics:
                self._node.create_subscription(
                    Image, f"{topic}/optimized", self._receiver(optimized_key(topic)), qos, raw=True
                )
            self._node.create_timer(0.25, self._read_graph)
        except BaseException:
            self._ros.close()
            raise
        self._ros.start()

    def _receiver(self, key: str) -> Callable[[Any, MessageInfo], None]:
        from dbml.harness.ros2node import received_monotonic

        def on_message(data: Any, info: MessageInfo) -> None:
            now, wall_ns = time.monotonic(), time.time_ns()
            received = received_monotonic(info, now=now, wall_ns=wall_ns)
            sender = info.get("publisher_gid") or {}
            gid = bytes(sender.get("data", b""))[:16]
            seq = info.get("publication_sequence_number")
            with self._lock:
                self._arrivals.append((received, len(data), gid, now))
                self._count_locked(key, gid, seq if isinstance(seq, int) else None)

        return on_message

    def _read_graph(self) -> None:
        owners = {}
        for topic in self._topics:
            for info in self._node.get_publishers_info_by_topic(topic):
                owners[bytes(info.endpoint_gid)[:16]] = info.node_name
        with self._lock:
            self._owners.update(owners)  # a writer gone stays named

    def _foreign(self, gid: bytes) -> bool:
        owner = self._owners.get(gid)
        return owner is not None and self._host_of_node(owner) is None

    def arrivals(
        self, *, since_s: float = -math.inf, at_callback: bool = False
    ) -> list[tuple[float, int]]:
        """Dbml's arrivals ``(t_s, bytes)`` at or after ``since_s``, in time order.

        ``t_s``: when DDS received the message, or ``at_callback`` when this node was called.
        """
        with self._lock:
            stamped = [
                (called if at_callback else t, n, gid) for t, n, gid, called in self._arrivals
            ]
            return sorted(
                (t, n) for t, n, gid in stamped if t >= since_s and not self._foreign(gid)
            )

    def callback_lag_ms(self, start_s: float, end_s: float) -> dict[str, float | None]:
        """How long after DDS received a message this node was called: p50, p99 and max."""
        with self._lock:
            lags = sorted(
                (called - t) * 1e3
                for t, _n, _gid, called in self._arrivals
                if start_s <= t <= end_s
            )
        if not lags:
            return dict.fromkeys(
                ("callback_lag_p50_ms", "callback_lag_p99_ms", "callback_lag_max_ms")
            )
        return {
            "callback_lag_p50_ms": round(lags[len(lags) // 2], 1),
            "callback_lag_p99_ms": round(lags[int(0.99 * (len(lags) - 1))], 1),
            "callback_lag_max_ms": round(lags[-1], 1),
        }

    def foreign(self, start_s: float, end_s: float) -> dict[str, int]:
        """Bytes and messages of foreign writers, and of writers never named, in the span."""
        with self._lock:
            inside = [(n, gid) for t, n, gid, _ in self._arrivals if start_s <= t <= end_s]
            return {
                "foreign_bytes": sum(n for n, gid in inside if self._foreign(gid)),
                "foreign_messages": sum(1 for _n, gid in inside if self._foreign(gid)),
                "unnamed_writer_bytes": sum(n for n, gid in inside if gid not in self._owners),
            }

    def clear(self) -> None:
        with self._lock:
            self._arrivals.clear()

    def close(self) -> None:
        self._ros.close()


class ParamTimes:
    """When this process heard each parameter change (monotonic s), from the store's watch.

    The optimizer's round counter changes every round (its heartbeat), so a round after a moment
    is a change of it heard after that moment, whatever the transport. Each number's peak since
    ``reset_peaks`` is kept too.
    """

    def __init__(self, transport: Transport) -> None:
        self._lock = threading.Lock()
        self._times: dict[str, float] = {}
        self._peaks: dict[str, float] = {}
        self._handle: Handle = transport.params.watch(self._on_change)

    def _on_change(self, name: str, value: ParamValue) -> None:
        now = time.monotonic()
        numeric = number(value)
        with self._lock:
            self._times[name] = now
            if numeric is not None and numeric > self._peaks.get(name, -math.inf):
                self._peaks[name] = numeric

    def peak(self, name: str) -> float | None:
        """The largest number ``name`` held since ``reset_peaks``."""
        with self._lock:
            return self._peaks.get(name)

    def reset_peaks(self) -> None:
        with self._lock:
            self._peaks.clear()

    def at(self, name: str) -> float | None:
        with self._lock:
            return self._times.get(name)

    def close(self) -> None:
        self._handle.close()


# -- the hostile peer (rclpy) ---------------------------------------------------------------------


def run_hostile_peer(topics: list[str]) -> None:
    """``--hostile-peer``: a plain rclpy node that attacks dbml from ``start`` to ``stop`` (stdin).

    Prints ``{"ready": true}``, then, at the end, one JSON report of what it sent and what the
    ``SetParameters`` services answered. Its domain and logs come from the environment.
    """
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float64, String

    from dbml.harness.ros2node import PrivateRos
    from dbml.protocol.keys import ALLOCATION_TOPIC, encode_batch
    from dbml.transports.codecs import image_cdr
    from dbml.transports.rclpy.nodes import node_of

    ros = PrivateRos(domain_id=None, name="hostile")  # ROS_DOMAIN_ID
    node = ros.node("hostile_peer")
    lock = threading.Lock()
    answers: dict[str, dict[str, int]] = {}
    accepted: list[str] = []
    refusals: dict[str, str] = {}
    sent = dict.fromkeys(
        ("frames", "forged_allocations", "flood_valid", "flood_invalid", "bad_sets"), 0
    )
    unready = 0

    def answered(name: str, kind: str, value: Any, future: Any) -> None:
        response = future.result()
        with lock:
            tally = answers.setdefault(kind, {"accepted": 0, "refused": 0, "unanswered": 0})
            if response is None:
                tally["unanswered"] += 1
                return
            for result in response.results:
                if result.successful:
                    tally["accepted"] += 1
                    accepted.append(f"{name}={value!r}")
                else:
                    tally["refused"] += 1
                    refusals.setdefault(kind, result.reason)

    stop = threading.Event()
    control = Control(stop).start()  # ``start`` arrives as a command; ``stop`` or EOF ends it

    def started() -> bool:
        with contextlib.suppress(queue.Empty):
            return control.commands.get(timeout=0.05) == "start"
        return False

    print(json.dumps({"ready": True}), flush=True)
    rng = random.Random(SEED)
    invalid = (math.nan, math.inf, 1.5, -0.5)
    image = image_cdr(HOSTILE_FRAME.size_bytes)
    forged_values: dict[str, ParamValue] = {names.current_value(t): FORGED_HZ for t in topics}
    forged_values |= {names.managed(t): True for t in topics}
    while not started() and not stop.is_set():
        pass
    # The endpoints exist from the start on only: the steady pass before it sees no stranger.
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    frame = node.create_publisher(Image, f"{HOSTILE_FRAME.topic}/optimized", reliable)
    # Transient local and reliable: the strongest offer, compatible with any subscription.
    forged = node.create_publisher(
        String,
        ALLOCATION_TOPIC,
        QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        ),
    )
    floods = [node.create_publisher(Float64, names.priority(t), reliable) for t in topics]
    bad_writes: list[tuple[str, str, Any]] = []
    for topic in topics:
        for value in (1.5, -0.1, math.nan, "high"):
            bad_writes.append((names.priority(topic), "priority", value))
        bad_writes.append((names.current_value(topic), "current_value", FORGED_HZ))
        bad_writes.append((names.size(topic), "size", 1.0))
    bad_writes += [(names.BANDWIDTH, "budget", -1.0), (names.BANDWIDTH, "budget", "eleven")]
    clients: dict[str, Any] = {}
    for name, _kind, _value in bad_writes:
        _parameter, param_node, _ros2 = node_of(name)
        if param_node not in clients:
            clients[param_node] = node.create_client(SetParameters, f"{param_node}/set_parameters")
    ros.start()
    tick = 0
    start = time.monotonic()
    while not stop.is_set():
        if tick % HOSTILE_FRAME_EVERY == 0:
            frame.publish(image)
            sent["frames"] += 1
        if tick % HOSTILE_FORGED_EVERY == 0:
            data = encode_batch(forged_values, time.time_ns(), "hostile").decode()
            forged.publish(String(data=data))
            sent["forged_allocations"] += 1
        if tick % HOSTILE_BAD_SET_EVERY == 0:
            name, kind, value = bad_writes[(tick // HOSTILE_BAD_SET_EVERY) % len(bad_writes)]
            _parameter, param_node, ros2_name = node_of(name)
            client = clients[param_node]
            if client.service_is_ready():
                request = SetParameters.Request(
                    parameters=[Parameter(ros2_name, value=value).to_parameter_msg()]
                )
                future = client.call_async(request)
                future.add_done_callback(
                    lambda done, n=name, k=kind, v=value: answered(n, k, v, done)
                )
                sent["bad_sets"] += 1
            else:
                unready += 1
        flood = floods[tick % len(floods)]
        if tick % 2:
            flood.publish(Float64(data=invalid[(tick // 2) % len(invalid)]))
            sent["flood_invalid"] += 1
        else:
            flood.publish(Float64(data=rng.random()))
            sent["flood_valid"] += 1
        tick += 1
        delay = start + tick / HOSTILE_TICK_HZ - time.monotonic()
        if delay > 0:
            stop.wait(delay)
    time.sleep(0.5)  # the last answers
    with lock:
        report = {
            "seconds": round(time.monotonic() - start, 2),
            "sent": sent,
            "set_parameters": answers,
            "set_parameters_not_ready": unready,
            "accepted_bad_values": accepted[:10],
            "refusal_reasons": refusals,
        }
    print(json.dumps(report), flush=True)
    ros.close()


class HostilePeer:
    """The ``--hostile-peer`` process of one run, driven over stdin; ended by its PID.

    Its stderr is ``workdir/hostile.log``.
    """

    def __init__(self, env: dict[str, str], topics: list[str], workdir: Path) -> None:
        self._children = Supervisor(logs=workdir)
        self.process = self._children.start(
            "hostile", [sys.executable, __file__, "--hostile-peer", ",".join(topics)], env=env
        )
        self.report: dict[str, Any] | None = None

    def _line(self) -> dict[str, Any]:
        report = next(self._children.reports("hostile", timeout_s=HOSTILE_S), None)
        if report is None:
            raise BenchError(f"the hostile peer did not answer within {HOSTILE_S:g} s")
        return report

    def wait_ready(self) -> None:
        if self._line().get("ready") is not True:
            raise BenchError("the hostile peer did not start")

    def start(self) -> None:
        self.process.send("start")

    def finish(self) -> dict[str, Any]:
        """Stop attacking; what it sent and what it was answered."""
        self.process.send("stop")
        self.report = self._line()
        return self.report

    def stop(self) -> None:
        self._children.close()


@dataclass
class BudgetSchedule:
    """The budget in force over time (monotonic seconds), as this process wrote it."""

    steps: list[tuple[float, float]] = field(default_factory=list)
    """``(t_s, bytes_per_s)`` in time order; the first applies from the start."""

    def at(self, t_s: float) -> float:
        times = [t for t, _ in self.steps]
        index = max(0, bisect.bisect_right(times, t_s) - 1)
        return self.steps[index][1]


class AllocationPoller:
    """Every 50 ms: the sum of ``current_value * size`` over the live managed channels."""

    def __init__(self, transport: Transport, bound_s: float) -> None:
        self._transport = transport
        self._lock = threading.Lock()
        self._samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._deadline = time.monotonic() + bound_s
        self._thread = threading.Thread(target=self._run, name="allocated-sum", daemon=True)
        self._thread.start()

    def allocated_bytes_per_s(self) -> float:
        params = self._transport.params
        entries = self._transport.graph.entries()
        total = 0.0
        for topic in published_topics(entries):
            if not is_managed(entries, topic):
                continue
            rate = number(params.get(names.current_value(topic)))
            size = number(params.get(names.size(topic)))
            if rate is not None and size is not None:
                total += rate * size
        return total

    def _run(self) -> None:
        while not self._stop.wait(POLL_S) and time.monotonic() < self._deadline:
            sample = (time.monotonic(), self.allocated_bytes_per_s())
            with self._lock:
                self._samples.append(sample)

    def samples(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        with self._lock:
            return [s for s in self._samples if start_s <= s[0] <= end_s]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=STOP_S)


def number(value: ParamValue) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def optimized_key(topic: str) -> str:
    return f"{topic[1:]}/optimized"


@dataclass
class Rig:
    """One run's processes and observers."""

    fleet: Fleet
    transport: Transport
    sniffer: Sniffer
    gaps: Gaps
    poller: AllocationPoller
    times: ParamTimes
    rng: random.Random
    ros2_sniffer: Ros2Sniffer | None = None
    hostile: HostilePeer | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    shm: set[Path] = field(default_factory=set)
    """rclpy: the Fast DDS shared-memory files of the processes started, removed at the end."""

    def note_shm(self) -> None:
        if self.ros2_sniffer is not None:
            pids = self.fleet.live_pids()
            if self.hostile is not None:
                pids.append(self.hostile.process.pid)
            self.shm.update(fastdds_shm_files(pids))


def settled(rig: Rig, channels: tuple[Channel, ...], since_s: float) -> bool:
    """Every channel managed, allocated by a round after ``since_s``, acknowledged, on the wire.

    An unchanged rate is not written again: a round's heartbeat (``/dbm/round``) heard after
    ``since_s`` says the rates in the store are that round's.
    """
    params = rig.transport.params
    seen = rig.gaps.seen()
    heard = rig.times.at(names.ROUND)
    for channel in channels:
        current = number(params.get(names.current_value(channel.topic)))
        applied = number(params.get(names.applied(channel.topic)))
        if (
            params.get(names.managed(channel.topic)) is not True
            or heard is None
            or heard <= since_s
            or current is None
            or applied is None
            or not math.isclose(current, applied, rel_tol=1e-9)
            or number(params.get(names.size(channel.topic))) != channel.size_bytes
            or optimized_key(channel.topic) not in seen
        ):
            return False
    return True


def wait_until(rig: Rig, predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Poll ``predicate`` every 50 ms for at most ``timeout_s``; a process exit fails at once."""
    deadline = time.monotonic() + timeout_s
    for _ in range(math.ceil(timeout_s / POLL_S) + 1):
        rig.fleet.check()
        if predicate():
            return True
        left = deadline - time.monotonic()
        if left <= 0:
            break
        time.sleep(min(POLL_S, left))
    return False


def hold(rig: Rig, seconds: float) -> None:
    """Let ``seconds`` pass, checking every 0.25 s that no process exited."""
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        rig.fleet.check()
        time.sleep(min(0.25, left))


def charged(
    arrivals: list[tuple[float, int]], budget: BudgetSchedule, reference_bps: float
) -> list[tuple[float, int]]:
    """Each arrival's bytes charged against the budget in force then, in ``reference`` bytes."""
    return [(t, round(n * reference_bps / budget.at(t))) for t, n in arrivals]


def wire_stats(
    rig: Rig,
    start_s: float,
    end_s: float,
    budget: BudgetSchedule,
    phases: dict[str, float] | None = None,
) -> tuple[dict[str, Any], int]:
    """The pass's windows; with ``phases`` (name -> start), also the worst inside each phase."""
    reference = budget.steps[0][1]
    arrivals = [a for a in rig.sniffer.arrivals(since_s=start_s) if a[0] <= end_s]
    weighted = charged(arrivals, budget, reference)
    stats = window_stats(weighted, limit_bytes=OVER_RATIO * reference)
    largest = max((n for _, n in arrivals), default=0)
    span_s = weighted[-1][0] - weighted[0][0] if len(weighted) > 1 else 0.0
    mean = sum(n for _, n in weighted[:-1]) / (reference * span_s) if span_s else 0.0
    document: dict[str, Any] = {
        "windows": stats.windows,
        "worst_ratio": round(stats.worst_bytes / reference, 4),
        "over_1_05_share": round(stats.over_share, 4),
        "mean_ratio": round(mean, 4),
    }
    if rig.ros2_sniffer is not None:
        # The same windows by when the sniffer's executor called back, and how late it was.
        called = rig.ros2_sniffer.arrivals(since_s=start_s, at_callback=True)
        late = window_stats(
            charged([a for a in called if a[0] <= end_s], budget, reference),
            limit_bytes=OVER_RATIO * reference,
        )
        document["worst_ratio_at_callback"] = round(late.worst_bytes / reference, 4)
        document.update(rig.ros2_sniffer.callback_lag_ms(start_s, end_s))
    if phases:
        bounds = sorted(phases.items(), key=lambda item: item[1])
        by_phase = {}
        for i, (name, begin_s) in enumerate(bounds):
            until_s = bounds[i + 1][1] if i + 1 < len(bounds) else math.inf
            inside = [a for a in weighted if begin_s <= a[0] < until_s]
            worst = window_stats(inside, limit_bytes=OVER_RATIO * reference).worst_bytes
            by_phase[name] = round(worst / reference, 4)
        document["worst_ratio_by_phase"] = by_phase
    return document, largest


def allocated_worst(
    rig: Rig, start_s: float, end_s: float, budget: BudgetSchedule
) -> dict[str, Any]:
    """The worst allocated sum / budget of the pass, when, and how long it was over.

    ``allocated_worst_at_s`` is seconds into the pass; ``allocated_over_s`` counts the 50-ms polls
    whose sum exceeded the budget in force.
    """
    worst, at_s, over = 0.0, None, 0
    for t, total in rig.poller.samples(start_s, end_s):
        limit = max(budget.at(t), budget.at(t - ALLOCATION_GRACE_S))
        over += total > limit
        if total / limit > worst:
            worst, at_s = total / limit, t - start_s
    return {
        "allocated_worst_ratio": round(worst, 4),
        "allocated_worst_at_s": None if at_s is None else round(at_s, 2),
        "allocated_over_s": round(over * POLL_S, 2),
    }


def steady_pass(rig: Rig, seconds: float) -> tuple[dict[str, Any], int]:
    budget = BudgetSchedule([(-math.inf, bytes_per_s(BUDGET_MBIT))])
    lost, duplicates = rig.gaps.lost(), rig.gaps.duplicates()
    start = time.monotonic()
    rig.sniffer.clear()
    hold(rig, seconds)
    end = time.monotonic()
    stats, largest = wire_stats(rig, start, end, budget)
    stats.update(allocated_worst(rig, start, end, budget))
    stats["sniffer_lost"] = rig.gaps.lost() - lost
    stats["sniffer_duplicates"] = rig.gaps.duplicates() - duplicates
    return stats, largest


def churn_plan(seconds: float) -> list[tuple[float, str]]:
    """The scheduled actions, ``(offset_s, action)`` in time order; events before a write."""
    plan = [(k / CHANGES_PER_S, "priority") for k in range(round(seconds * CHANGES_PER_S))]
    plan += [
        (STEP_AT * seconds, "step"),
        (JOIN_AT * seconds, "join"),
        (LEAVE_AT * seconds, "leave"),
    ]
    return sorted(plan, key=lambda item: (item[0], item[1] == "priority"))


def churn_pass(rig: Rig, seconds: float) -> tuple[dict[str, Any], int]:
    params = rig.transport.params
    budget = BudgetSchedule([(-math.inf, bytes_per_s(BUDGET_MBIT))])
    live = {c.topic for c in CHANNELS}
    leaving: threading.Thread | None = None
    writes = 0
    lag_s = 0.0
    join_s: float | None = None
    lost, duplicates = rig.gaps.lost(), rig.gaps.duplicates()
    if rig.hostile is not None:
        rig.hostile.start()
    rig.times.reset_peaks()
    start = time.monotonic()
    phases = {"before_step": start}
    rig.sniffer.clear()
    for offset, action in churn_plan(seconds):
        wait = start + offset - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        lag_s = max(lag_s, -wait)
        if lag_s > LATE_S:
            raise BenchError(f"the churn schedule fell {lag_s:.1f} s behind: host overloaded")
        rig.fleet.check()
        if action == "priority":
            topic = rig.rng.choice(sorted(live))
            params.set(names.priority(topic), rig.rng.random())
            writes += 1
        elif action == "step":
            phases["after_step"] = time.monotonic()
            budget.steps.append((phases["after_step"], bytes_per_s(STEP_MBIT)))
            params.set(names.BANDWIDTH, STEP_MBIT)
        elif action == "join":
            phases["after_join"] = join_s = time.monotonic()
            rig.fleet.start_publisher(JOINER)
            live.add(JOINER.topic)
        else:
            phases["after_leave"] = time.monotonic()
            live.discard(LEAVER.topic)
            leaving = threading.Thread(
                target=rig.fleet.end, args=(f"publish-{LEAVER.host}",), daemon=True
            )
            leaving.start()
    hold(rig, start + seconds - time.monotonic())
    end = time.monotonic()
    rig.note_shm()  # the joiner's too
    if rig.hostile is not None:
        stats_hostile: dict[str, Any] | None = rig.hostile.finish()
    else:
        stats_hostile = None
    if leaving is not None:
        leaving.join(timeout=STOP_S * 2)
    stats, largest = wire_stats(rig, start, end, budget, phases)
    stats.update(allocated_worst(rig, start, end, budget))
    heard = rig.times.at(names.current_value(JOINER.topic))
    stats.update(
        priority_changes=writes,
        schedule_lag_ms=round(lag_s * 1e3, 1),
        sniffer_lost=rig.gaps.lost() - lost,
        sniffer_duplicates=rig.gaps.duplicates() - duplicates,
        joiner_managed=bool(
            join_s is not None
            and params.get(names.managed(JOINER.topic)) is True
            and heard is not None
            and heard > join_s
        ),
    )
    stats["optimizer_ack_timeouts"] = rig.fleet.count("optimizer", ACK_TIMEOUT)
    if rig.ros2_sniffer is not None:
        stats.update(rig.ros2_sniffer.foreign(start, end))
    if stats_hostile is not None:
        # 16 Hz for the 84,000-B camera is 10.75 Mbit/s alone: no allocation within 11 Mbit/s
        # (the other channels at 1 Hz at least) ever gives it, a forged one does.
        peak = rig.times.peak(names.current_value(HOSTILE_FRAME.topic))
        stats_hostile[f"{HOSTILE_FRAME.topic}_current_value_peak_hz"] = peak
        stats_hostile["forged_allocation_applied"] = peak is not None and peak >= FORGED_HZ
        stats_hostile["invalid_priority_ignored_by"] = rig.fleet.logged(PRIORITY_REFUSAL)
        stats["hostile"] = stats_hostile
    return stats, largest


@contextlib.contextmanager
def environment(env: dict[str, str]) -> Iterator[None]:
    """``os.environ`` is ``env`` for the block (this process's rclpy reads it at its start)."""
    saved = dict(os.environ)
    os.environ.update(env)
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


@contextlib.contextmanager
def rig_for(
    run: int,
    seconds: float,
    workdir: Path,
    *,
    headroom: bool,
    transport_name: str = "zenoh",
    hostile: bool = True,
) -> Iterator[Rig]:
    config = workdir / "dbm.yaml"
    config.write_text(
        f"dbm:\n  max_bandwidth_in_mbit: {BUDGET_MBIT:g}\n"
        f"  optimization_rate_in_seconds: {PERIOD_S:g}\n"
        f"  frame_headroom: {'true' if headroom else 'false'}\n"
    )
    with contextlib.ExitStack() as stack:
        if transport_name == "zenoh":
            port = free_port()
            # This session first, so it holds the rendezvous for the whole run.
            transport: Transport = ZenohTransport(host="bench", port=port)
            stack.callback(transport.close)
            session = sniffer_session(port)
            stack.callback(session.close)
            sniffer: Sniffer = stack.enter_context(WireSniffer(session, "**/optimized"))
            zenoh_gaps = SequenceGaps(session, "**/optimized")
            stack.callback(zenoh_gaps.close)
            gaps: Gaps = zenoh_gaps
            env = dict(os.environ, DBML_ZENOH_PORT=str(port))
            transport_args: list[str] = []
            ros2_sniffer = None
            extra: dict[str, Any] = {}
        else:
            from dbml.transports.rclpy import RclpyTransport

            domain_id = stack.enter_context(claim_domain())
            env = ros2_child_env(domain_id=domain_id, log_dir=workdir / "ros-log")
            stack.enter_context(environment(env))  # this process's rclpy: the same logs, profile
            transport = RclpyTransport(host="bench", domain_id=domain_id)
            stack.callback(transport.close)
            ros2_sniffer = Ros2Sniffer(domain_id, [c.topic for c in (*CHANNELS, JOINER)])
            stack.callback(ros2_sniffer.close)
            sniffer = gaps = ros2_sniffer
            transport_args = ["--transport", "rclpy", "--domain-id", str(domain_id)]
            extra = {"domain_id": domain_id}
        times = ParamTimes(transport)
        stack.callback(times.close)
        poller = AllocationPoller(transport, bound_s=2 * READY_S + STEADY_S + seconds)
        stack.callback(poller.close)
        fleet = Fleet(env, transport_args, workdir)
        rig = Rig(
            fleet,
            transport,
            sniffer,
            gaps,
            poller,
            times,
            random.Random(SEED + run),
            ros2_sniffer,
            extra=extra,
        )
        if ros2_sniffer is not None:
            stack.callback(lambda: remove_fastdds_shm(sorted(rig.shm)))  # what a kill left
        stack.callback(fleet.stop)  # runs first: the processes end before the sessions close
        if ros2_sniffer is not None and hostile:
            rig.hostile = HostilePeer(env, [c.topic for c in CHANNELS], workdir)
            stack.callback(rig.hostile.stop)
        fleet.start("optimizer", "optimizer", "--config", str(config), "--host", "base")
        for channel in (*CHANNELS, JOINER):
            fleet.start(
                f"subscribe-{channel.host}", "subscribe", channel.topic, "--host", "operator"
            )
        for channel in CHANNELS:
            fleet.start_publisher(channel)
        yield rig


def measure_run(
    run: int,
    seconds: float,
    *,
    headroom: bool,
    transport_name: str = "zenoh",
    hostile: bool = True,
) -> dict[str, Any]:
    with (
        tempfile.TemporaryDirectory(prefix="dbml-budget-") as tmp,
        rig_for(
            run,
            seconds,
            Path(tmp),
            headroom=headroom,
            transport_name=transport_name,
            hostile=hostile,
        ) as rig,
    ):
        if not rig.transport.wait_for_peers(READY_S):
            raise BenchError(f"no dbml process reached\n{rig.fleet.logs()}")
        params = rig.transport.params
        for channel in CHANNELS:
            params.set(names.priority(channel.topic), rig.rng.random())
        since_s = time.monotonic()
        if not wait_until(rig, lambda: settled(rig, CHANNELS, since_s), READY_S):
            seen = json.dumps(params.snapshot("/robot"), sort_keys=True)
            raise BenchError(
                f"not every channel allocated within {READY_S:g} s\n"
                f"this process's view: {seen}\nseen on the wire: {sorted(rig.gaps.seen())}\n"
                f"{rig.fleet.logs()}"
            )
        rig.note_shm()
        if rig.hostile is not None:
            rig.hostile.wait_ready()
        steady, steady_largest = steady_pass(rig, min(STEADY_S, seconds))
        churn, churn_largest = churn_pass(rig, seconds)
    largest = max(steady_largest, churn_largest, 1)
    reference = bytes_per_s(BUDGET_MBIT)
    return {
        "windows": churn["windows"],
        "worst_ratio": churn["worst_ratio"],
        "over_1_05_share": churn["over_1_05_share"],
        "worst_ratio_by_phase": churn["worst_ratio_by_phase"],
        "mean_ratio": churn["mean_ratio"],
        "allocated_worst_ratio": churn["allocated_worst_ratio"],
        "allocated_worst_at_s": churn["allocated_worst_at_s"],
        "largest_message_bytes": largest,
        "target_ratio": round((reference + largest) / reference, 4),
        **{
            k: churn[k]
            for k in (
                "worst_ratio_at_callback",
                "callback_lag_p50_ms",
                "callback_lag_p99_ms",
                "callback_lag_max_ms",
            )
            if k in churn
        },
        "steady_worst_ratio": steady["worst_ratio"],
        **(
            {"steady_worst_ratio_at_callback": steady["worst_ratio_at_callback"]}
            if "worst_ratio_at_callback" in steady
            else {}
        ),
        "steady_windows": steady["windows"],
        "steady_over_1_05_share": steady["over_1_05_share"],
        "steady_mean_ratio": steady["mean_ratio"],
        "steady_allocated_worst_ratio": steady["allocated_worst_ratio"],
        "priority_changes": churn["priority_changes"],
        "joiner_managed": churn["joiner_managed"],
        "schedule_lag_ms": churn["schedule_lag_ms"],
        "allocated_over_s": churn["allocated_over_s"],
        "optimizer_ack_timeouts": churn["optimizer_ack_timeouts"],
        "sniffer_lost": churn["sniffer_lost"] + steady["sniffer_lost"],
        "sniffer_duplicates": churn["sniffer_duplicates"] + steady["sniffer_duplicates"],
        **{
            k: churn[k]
            for k in ("foreign_bytes", "foreign_messages", "unnamed_writer_bytes", "hostile")
            if k in churn
        },
        **rig.extra,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def measure(
    runs: int,
    seconds: float,
    *,
    headroom: bool = True,
    transport_name: str = "zenoh",
    hostile: bool = True,
) -> dict[str, Any]:
    results = [
        measure_run(run, seconds, headroom=headroom, transport_name=transport_name, hostile=hostile)
        for run in range(runs)
    ]
    document: dict[str, Any] = {
        "benchmark": "budget_integrity",
        "transport": transport_name,
        "frame_headroom": headroom,
        "runs": results,
        "windows": sum(r["windows"] for r in results),
        "worst_ratio": max(r["worst_ratio"] for r in results),
        "over_1_05_share": max(r["over_1_05_share"] for r in results),
        "allocated_worst_ratio": max(r["allocated_worst_ratio"] for r in results),
        "steady_worst_ratio": max(r["steady_worst_ratio"] for r in results),
        "target": TARGET,
        "met": all(r["worst_ratio"] <= r["target_ratio"] for r in results),
        "reference": REFERENCE,
        "scenario": {
            "seconds": seconds,
            "steady_seconds": min(STEADY_S, seconds),
            "budget_mbit": [BUDGET_MBIT, STEP_MBIT],
            "step_at_s": round(STEP_AT * seconds, 3),
            "join_at_s": round(JOIN_AT * seconds, 3),
            "leave_at_s": round(LEAVE_AT * seconds, 3),
            "changes_per_s": CHANGES_PER_S,
            "seed": SEED,
        },
    }
    if transport_name == "rclpy":
        document["hostile_peers"] = HOSTILE_PEERS if hostile else {}
        document["not_applicable"] = NOT_APPLICABLE
    return document


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--runs", type=int, default=3, help="runs (default 3)")
    parser.add_argument("--seconds", type=float, default=30.0, help="churn pass (default 30)")
    parser.add_argument(
        "--without-headroom",
        action="store_true",
        help="allocate the whole budget (dbm.frame_headroom false): whole-frame quantisation shows",
    )
    parser.add_argument(
        "--transport", choices=TRANSPORTS, default="zenoh", help="zenoh (default) or rclpy"
    )
    parser.add_argument(
        "--no-hostile", action="store_true", help="rclpy: no hostile peer during the churn pass"
    )
    parser.add_argument("--hostile-peer", metavar="TOPICS", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.hostile_peer is not None:
        run_hostile_peer([t for t in args.hostile_peer.split(",") if t])
        return
    if args.runs < 1:
        parser.error("--runs must be >= 1")
    if not 5 <= args.seconds <= 600:
        parser.error("--seconds must be 5-600")
    signal.signal(signal.SIGTERM, _interrupt)  # the same cleanup as Ctrl-C
    try:
        document = measure(
            args.runs,
            args.seconds,
            headroom=not args.without_headroom,
            transport_name=args.transport,
            hostile=not args.no_hostile,
        )
    except BenchError as err:
        raise SystemExit(f"budget_integrity: {err}") from None
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    if args.json:
        print(json.dumps(document))
        return

    title = "bytes on */optimized per 1-s window / budget, under churn"
    table = Table(title=f"{title} ({document['transport']}, one host)")
    columns = ("run", "windows", "worst", "steady worst", ">1.05", "allocated", "target", "lost")
    for name in columns:
        table.add_column(name, justify="right")
    for i, run in enumerate(document["runs"]):
        table.add_row(
            str(i),
            str(run["windows"]),
            f"{run['worst_ratio']:.3f}",
            f"{run['steady_worst_ratio']:.3f}",
            f"{run['over_1_05_share']:.1%}",
            f"{run['allocated_worst_ratio']:.3f}",
            f"{run['target_ratio']:.3f}",
            str(run["sniffer_lost"]),
        )
    table.caption = f"{TARGET}: {'met' if document['met'] else 'NOT met'}; reference: {REFERENCE}"
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
