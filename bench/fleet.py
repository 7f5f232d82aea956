"""Fleet: dbml's control plane at fleet size, R robots x C channels, as real processes.

As clients of one router (``dbml router``; ``--topology peer``: a private loopback zenoh mesh,
``DBML_ZENOH_PORT``), shared memory off: one optimizer
(``python -m dbml optimizer --config FILE --host base``), one operator process with a
``ManagedSubscriber`` per channel (host ``operator``, so every channel is managed), and robots,
each its own zenoh session and host (``r1``, ``r2``, ...) with C channels ``/rK/ch0..`` at
1-16 Hz (paced down past 40 robots in the site bench), up to 10 robots per worker process (this
script with ``--worker``), one pacing thread per robot, strategy ``paper``, ``frame_headroom``
on. A probe session (host ``bench``) reads the parameters. Two benches:

- the control plane at a site's scale (the default; 40, 80, 160 and 320 robots x 4): a shared
  budget of ``--budget-mbit`` (100 Mbit/s), the frames of 84,000 / 21,000 / 8,000 / 1,000 bytes
  (cycling) scaled down so that it is 60 % of the fleet's maxima, the rates paced down past 40
  robots (``SITE_PACED_ROBOTS``: 0.25-4 Hz at 160) so that the fleet sends as many frames a
  second at every size: the channels compete as in the paper, and this machine moves the frames
  without being what is measured;
- ``--heavy``: those frames as they are, the budget 60 % of the maxima (700 Mbit/s at 80 x 4),
  a router saturated with data, where control must keep its lead.

Per size:

- ``converge_s``: from the word that starts every robot (their worker processes spawned and
  their imports done before it: a robot's process is up before it joins a fleet) until
  ``/dbm/status`` is ``optimal`` and every channel is managed, has a ``current_value`` within 2 %
  of the fleet's ``allocate()`` and an ``applied_value`` equal to it (the publisher applied it);
  null if not within 60 s, and the rest is still measured.
- ``reaction_p50_ms`` / ``reaction_p99_ms``: 50 priority writes by the probe to random channels,
  each drawn to change that channel's allocated rate, timed from ``params.set`` to the arrival of
  that channel's ``applied_value`` at a new value; no ack within 2 s counts as 2000 ms (a lower
  bound). The fleet settles on the new allocation before the next change. A rise paid by many
  cuts may first go part of the way (the optimizer's ``STEP_SHARE``, at least half):
  ``reaction_whole_...`` times the arrival at the new rate itself (2 %), ``reaction_raised_...``
  the first response of the changes that raised their channel (``reaction_raised`` of them).
- ``control_msgs_per_s`` / ``control_bytes_per_s``: payloads on ``dbml/**`` (parameter writes and
  batches; liveliness and queries are not puts, not counted) over the steady state
  (``--seconds``, default 5, after convergence); ``optimizer_cpu_pct``: the optimizer's utime +
  stime over it (100 = one core), and ``optimizer_cpu_ms_per_round`` (a round a second);
  ``cpu_pct_by_role``: the same for the bench's own process, the router, the optimizer, the
  operator and the robots' workers together; ``fleet_cpu_pct`` / ``host_cpu_pct``: every process
  of the run / the whole machine (other workloads included); ``host_steal_pct``: of that, what a
  virtual machine's hypervisor took for others (the same code reads slower when it is high).
- ``join_cpu_s_by_role``: CPU-seconds each role spent from the word that starts every robot to
  convergence (or its timeout); ``join_cpu_ms_per_robot``: every process's, per robot (flat if
  a robot's join costs the same whatever the fleet); ``join_host_cpu_pct``: the machine's busy
  share meanwhile (200 on two cores: the join went as fast as the machine allows).
- ``delivered_over_budget``: the worst sliding 1-s window of ``**/optimized`` payload bytes (a
  ``WireSniffer`` in the operator's session) over the budget, from convergence to the end of the
  reactions; ``..._steady`` over the steady state only; ``delivered_mean_over_budget``: its mean;
  ``delivered_ideal_over_budget``: the same window over perfectly periodic publishers at the
  allocated rates, which reads above 1 too (a window holds whole messages): the metric's floor;
  ``sent_over_budget``: the worst window by the messages' send times (their metadata), the same
  span, so a receiver that stalled and took a burst late does not read as overspend.
- ``failsafe_events``: warnings containing ``fail-safe`` logged in the robot processes, from start
  to teardown. ``sessions``: robots + operator + optimizer + probe.
- ``robot_control_msgs_per_s``: parameter writes and batches delivered to the robots' sessions,
  per robot per second in the steady state (the heartbeat); ``robot_control_msgs_per_change``:
  per robot per priority change over the reactions, ``..._net`` less the heartbeats meanwhile;
  ``robot_control_bytes_per_s`` and ``robot_control_bytes_per_change_net``: their payloads'
  bytes. What a change costs a robot it does not concern should not grow with the fleet: the
  document's ``flat`` compares the smallest size's messages per change with the largest's.

The processes are ``dbml.harness``'s: started, read and ended by PID by a ``Supervisor`` (also
on Ctrl-C and SIGTERM), the workers report JSON lines and read their commands as roles do.

    python bench/fleet.py [--robots R] [--channels C] [--budget-mbit M] [--seconds S]
                          [--topology T] [--json]
    python bench/fleet.py --heavy [--robots R]          # 80 x 4 by default
    python bench/fleet.py --sweep [--plot FILE.png]    # 10, 20, 40, 80 robots: the curve

Targets by mode and size in ``TARGETS``; ``--logs DIR`` keeps every process's stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import queue
import random
import signal
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from rich.console import Console
from rich.table import Table

from dbml import ChannelSpec, Problem, allocate
from dbml.core.allocation import Status
from dbml.experiment.runner import sigterm_as_interrupt
from dbml.harness.child import Control, Emit, emit_json, stop_on_signals
from dbml.harness.processes import free_port
from dbml.harness.sniffer import WireSniffer, window_stats
from dbml.harness.supervisor import Supervisor
from dbml.protocol import names
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports.base import Handle, ParamValue, Sample
from dbml.transports.zenoh import ZenohTransport

SIZES_BYTES = (84_000, 21_000, 8_000, 1_000)
MIN_HZ, MAX_HZ = 1.0, 16.0
BUDGET_SHARE = 0.6
"""Of the sum of max rate x size: the floors fit and the big channels compete."""
SITE_BUDGET_MBIT = 100.0
"""The control-plane bench's shared budget (``--budget-mbit``): a site's uplink. The frames are
scaled down so that it is ``BUDGET_SHARE`` of the fleet's maxima, so the channels still compete
and this machine moves the data without the data being what it measures."""
STRATEGY = "paper"
TOPOLOGIES = ("router", "peer")
DEFAULT_TOPOLOGY = "router"
"""A fleet's sessions as clients of one router, one link each (a zenoh client opens one, whatever
``priority_links`` asks). ``peer``, a loopback mesh, is what dbml
does with no flags; at 83 sessions the mesh never completes on this machine (robots with 0 to 74
of their 82 links after 60 s), and zenoh peers send only over direct links."""
CLIENT_CONFIG = '{mode: "client"}\n'
"""The sessions' zenoh config with ``--topology router``: each reaches the others through the
run's router (``dbml router``)."""
SITE_PACED_ROBOTS = 40
"""The control-plane bench's channels run at ``MIN_HZ``-``MAX_HZ`` up to this many robots; a
larger fleet's are paced by this share of its robots (0.25-4 Hz at 160), its frames scaled as at
this size: the fleet sends as many frames a second at every size, so what grows with it is the
control plane, not this machine's work of moving frames (160 x 4 at the full rates kept the
host's two cores 77-98 % busy)."""
SITE_SIZES = ((40, 4), (80, 4), (160, 4), (320, 4))
"""The control-plane bench's sizes, robots x channels."""
HEAVY_SIZES = ((80, 4),)
"""``--heavy``: the paper's frames at 60 % of the fleet's maxima (700 Mbit/s at 80 x 4), a
saturated router, where control must keep its lead over data."""
ROBOTS_PER_WORKER = 10
STEADY_S = 5.0
CHANGES = 50
PRIORITY_STEPS = (0.0, 0.25, 0.5, 0.75, 1.0)
DRAWS = 1000
"""Bound on the random draws looking for a priority change that changes the allocation."""
SEED = 1
PERIOD_S = 1.0
"""The optimizer's period in the runs' config (``optimization_rate_in_seconds``)."""
HEARTBEATS_KEPT = 10_000
"""Each robot keeps the delays of at most this many heartbeats (a run hears a few hundred)."""

RATE_TOL = 0.02
CONVERGE_S = 60.0
READY_S = 60.0
"""Each robot's session and publishers are set up within this."""
OPERATOR_READY_S = 120.0
"""The operator's subscribers (one per channel) are set up within this."""
CHANGE_TIMEOUT_S = 2.0
SETTLE_S = 5.0
REACTIONS_S = 120.0
"""Wall-clock bound on the whole series of changes."""
PEER_WAIT_S = 2.0
"""As ``dbml publish`` / ``dbml subscribe`` wait for a peer before declaring anything."""
POLL_S = 0.05
"""Longest a pacing thread or a waiter sleeps before looking again (as ``Rate`` polls)."""
CHECK_S = 0.02
"""Shortest interval between two evaluations of a whole-fleet predicate."""
STOP_S = 10.0

TARGET_SIZE = (40, 4)
SWEEP_ROBOTS = (10, 20, 40, 80)
"""``--sweep``: the scaling curve's sizes (robots, with ``--channels`` each, default 4), in the
mode asked for; the default run's sizes draw the curve as well (``--plot``)."""


def _site_target(converge_s: float) -> dict[str, Any]:
    return {
        "converge_s_max": converge_s,
        "reaction_p99_ms_max": 100.0,
        "failsafe_events_max": 0,
        "every_channel_allocated": True,
        "delivered_over_budget_max": "1 + one largest message",
    }


SITE_TARGETS: dict[str, dict[str, Any]] = {
    "40x4": _site_target(5.0),
    "80x4": _site_target(5.0),
    "160x4": _site_target(10.0),
    "320x4": _site_target(20.0),
}
"""Issue 33's targets for the control plane at a site's budget, by size (3 runs each); the
robot's control messages per change must not grow from 40 to 320 (``document["flat"]``)."""
HEAVY_TARGETS: dict[str, dict[str, Any]] = {
    "80x4": {
        "converge_s_max": 10.0,
        "reaction_p99_ms_max": 100.0,
        "failsafe_events_max": 0,
        "every_channel_allocated": True,
        "heartbeat_p99_ms_max": PERIOD_S * 1e3,
    },
}
"""``--heavy``'s: issue 21's 80 x 4 targets, which issue 33 keeps, and every robot's heartbeats
within a period at p99 (from its start: the data's ramp included). Before issue 21 (a fresh
clone): 80x4 never converged (276 of 320 channels ever allocated in 60 s, 859 fail-safe
events)."""
TARGETS = {"site": SITE_TARGETS, "heavy": HEAVY_TARGETS}
FLAT_SLACK = 0.1
"""A robot's control messages per change 'do not grow' within this share."""
FAILSAFE_SHOWN = 5
"""The first fail-safe warnings of a size are shown in the progress log."""
FAILSAFE_TEXT = "fail-safe"
"""In the publisher's warning: 'no allocation heard for ... ; fail-safe: minimum ... Hz'."""

_started = time.monotonic()


def note(message: str) -> None:
    """Progress on stderr, so ``--json`` keeps stdout to the document."""
    print(f"[fleet {time.monotonic() - _started:7.1f}s] {message}", file=sys.stderr, flush=True)


class Channel(NamedTuple):
    topic: str
    size_bytes: int
    host: str
    min_hz: float = MIN_HZ
    max_hz: float = MAX_HZ


def fleet_channels(
    robots: int, channels: int, *, scale: float = 1.0, pace: float = 1.0
) -> list[Channel]:
    """Robot ``K``'s channels ``/rK/ch0..``: ``SIZES_BYTES`` (cycling) times ``scale``.

    At ``MIN_HZ``-``MAX_HZ`` times ``pace``.
    """
    return [
        Channel(
            f"/r{r}/ch{c}",
            max(1, round(SIZES_BYTES[c % len(SIZES_BYTES)] * scale)),
            f"r{r}",
            MIN_HZ * pace,
            MAX_HZ * pace,
        )
        for r in range(1, robots + 1)
        for c in range(channels)
    ]


def plan(
    robots: int, channels: int, *, budget_mbit: float | None, budget_share: float
) -> tuple[list[Channel], float]:
    """The fleet's channels and its budget in bytes/s.

    ``budget_mbit`` None (``--heavy``): the paper's frames and rates, the budget
    ``budget_share`` of the fleet's maxima. Else that budget, the rates paced down past
    ``SITE_PACED_ROBOTS`` robots, and frames scaled down (never up) so that the budget is that
    share of the maxima: a small fleet that cannot fill it gets its share, as with ``--heavy``.
    """
    full = fleet_channels(robots, channels)
    if budget_mbit is None:
        return full, budget_share * sum(c.max_hz * c.size_bytes for c in full)
    pace = min(1.0, SITE_PACED_ROBOTS / robots)
    paced = fleet_channels(robots, channels, pace=pace)
    share_bps = budget_share * sum(c.max_hz * c.size_bytes for c in paced)
    budget_bps = budget_mbit * 1e6 / 8
    if budget_bps >= share_bps:
        return paced, share_bps
    return fleet_channels(robots, channels, scale=budget_bps / share_bps, pace=pace), budget_bps


def expected_rates(
    channels: list[Channel], priorities: dict[str, float], budget_mbit: float
) -> dict[str, float] | None:
    """The optimizer's allocation for these priorities; None when infeasible.

    The optimizer declares its channels by topic, and the ``paper`` strategy gives ties (equal
    size and priority) in declaration order: so do we, or /r10/ch0 and /r2/ch0 swap rates.
    """
    specs = tuple(
        ChannelSpec(c.topic, c.min_hz, c.max_hz, float(c.size_bytes), priorities.get(c.topic, 0.0))
        for c in sorted(channels)
    )
    problem = Problem(specs, bandwidth_mbit=budget_mbit, frame_headroom=True)
    allocation = allocate(problem, strategy=STRATEGY)
    if allocation.status is not Status.OPTIMAL:
        return None
    return allocation.rates_by_topic()


def close_to(value: ParamValue, rate_hz: float) -> bool:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    return math.isclose(value, rate_hz, rel_tol=RATE_TOL)


def cpu_ticks(pid: int) -> int | None:
    """The user + system CPU time of ``pid`` in clock ticks; None once it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # after "pid (comm)": state is field 3
    return int(fields[11]) + int(fields[12])  # fields 14 and 15


def host_busy_ticks() -> tuple[int, int, int]:
    """All cores' busy, total and stolen clock ticks so far (``/proc/stat``).

    Stolen: what a virtual machine's hypervisor gave to others, counted busy (it was not ours).
    """
    fields = [int(f) for f in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    total = sum(fields[:8])  # user nice system idle iowait irq softirq steal (guest is in user)
    return total - fields[3] - fields[4], total, fields[7]


def ideal_delivered(
    channels: list[Channel], rates_hz: dict[str, float], budget_bps: float, seconds: float
) -> float:
    """The worst 1-s window over the budget for perfectly periodic publishers at ``rates_hz``.

    Random phases, no jitter, no overspend: what the window metric reads anyway, because a
    window holds whole messages (a 7.3 Hz channel puts 8 of them in some windows).
    """
    rng = random.Random(SEED)
    arrivals = []
    for channel in channels:
        period = 1.0 / rates_hz[channel.topic]
        first = rng.uniform(0.0, period)
        count = int((max(seconds, 2.0) - first) / period) + 1
        arrivals += [(first + k * period, channel.size_bytes) for k in range(count)]
    return round(window_stats(arrivals, limit_bytes=budget_bps).worst_bytes / budget_bps, 4)


def percentile(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 3) if values else None


# -- worker processes (robots, operator) ------------------------------------------------------


def open_session(
    host: str, net: dict[str, Any], *, follow_all_params: bool = True
) -> ZenohTransport:
    """A session of the run: a peer of the loopback mesh, or a client of the run's router."""
    router = net.get("router")
    if router is None:
        return ZenohTransport(host=host, port=net["port"], follow_all_params=follow_all_params)
    return ZenohTransport(
        host=host,
        connect=[router],
        config_file=net["client_config"],
        follow_all_params=follow_all_params,
    )


def report(message: dict[str, Any]) -> None:
    """A worker's report (from any thread); dropped once the bench is gone."""
    with contextlib.suppress(OSError, ValueError):
        emit_json(message)


class FailsafeCounter(logging.Handler):
    """Reports each fail-safe warning as it is logged (the pacing threads log it)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if FAILSAFE_TEXT in message:
            report({"type": "failsafe", "message": message})


def ignore_sample(_sample: Sample) -> None:
    """The operator keeps nothing: the operator's sniffer counts the bytes."""


def run_operator(
    spec: dict[str, Any], emit: Emit, commands: queue.Queue[str], stop: threading.Event
) -> int:
    # It subscribes and needs no parameter: a session that follows them all must keep up with
    # every robot's writes (reliable, routed in order), and this one is busy with every frame.
    transport = open_session("operator", spec["net"], follow_all_params=False)
    subscribers: list[ManagedSubscriber] = []
    sniffer: WireSniffer | None = None
    try:
        transport.wait_for_peers(PEER_WAIT_S)
        sniffer = WireSniffer(transport.session, "**/optimized")
        for topic in spec["topics"]:
            if stop.is_set():
                return 0
            subscribers.append(ManagedSubscriber(transport, topic, ignore_sample))
        emit({"type": "ready", "subscribers": len(subscribers)})
        while not stop.is_set():
            try:
                command = commands.get(timeout=POLL_S * 10)
            except queue.Empty:
                continue
            words = command.split()
            if words[:1] == ["stats"] and len(words) == 4:
                since_s, until_s, limit = (float(w) for w in words[1:])
                arrivals = [a for a in sniffer.arrivals(since_s=since_s) if a[0] <= until_s]
                stats = window_stats(arrivals, limit_bytes=limit)
                wall = time.time() - time.monotonic()  # the send times are wall clock
                sent = [s for s in sniffer.sent(since_s=since_s + wall) if s[0] <= until_s + wall]
                by_send_time = window_stats(sent, limit_bytes=limit)
                emit(
                    {
                        "type": "stats",
                        "samples": len(arrivals),
                        "bytes": sum(n for _, n in arrivals),
                        "windows": stats.windows,
                        "worst_bytes": stats.worst_bytes,
                        "over_share": stats.over_share,
                        "worst_sent_bytes": by_send_time.worst_bytes,
                    }
                )
    finally:
        for subscriber in subscribers:
            subscriber.close()
        if sniffer is not None:
            sniffer.close()
        transport.close()
    return 0


class Robot(threading.Thread):
    """One robot: its own session and host, its channels paced from this one thread.

    Each channel is published when one period of its current rate has passed since its last
    tick (``Rate.sleep``'s schedule, for several channels at once: a new rate applies within
    ``POLL_S``); ``publish`` then rate-limits ``[topic]/optimized`` itself.
    """

    def __init__(
        self,
        host: str,
        channels: list[tuple[str, int, float, float]],
        net: dict[str, Any],
        stop: threading.Event,
        done: Callable[[str, str | None], None],
    ) -> None:
        super().__init__(name=f"robot-{host}", daemon=True)
        self.host = host
        self._channels = channels
        self._net = net
        self._stop_event = stop
        self._done = done
        self.transport: ZenohTransport | None = None
        self.heartbeats = Heartbeats(self)

    def run(self) -> None:
        try:
            transport = self.transport = open_session(self.host, self._net, follow_all_params=False)
        except Exception as err:
            self._done(self.host, f"session: {err}")
            return
        publishers: list[ManagedPublisher] = []
        watching: Handle | None = None
        try:
            watching = transport.params.watch(self.heartbeats.on_param)
            transport.wait_for_peers(PEER_WAIT_S)
            payloads = [bytes(size) for _, size, _, _ in self._channels]
            for topic, _, min_hz, max_hz in self._channels:
                publishers.append(
                    ManagedPublisher(transport, topic, min_rate_hz=min_hz, max_rate_hz=max_hz)
                )
            self._done(self.host, None)
            self._pace(publishers, payloads)
        except Exception as err:
            logging.getLogger("fleet").exception("robot %s failed", self.host)
            self._done(self.host, f"{type(err).__name__}: {err}")
        finally:
            for publisher in publishers:
                with contextlib.suppress(Exception):
                    publisher.close()
            if watching is not None:
                watching.close()
            transport.close()

    def _pace(self, publishers: list[ManagedPublisher], payloads: list[bytes]) -> None:
        last: list[float | None] = [None] * len(publishers)
        stop = self._stop_event
        while not stop.is_set():
            now = time.monotonic()
            next_s = now + POLL_S
            for i, publisher in enumerate(publishers):
                period = 1.0 / publisher.current_rate_hz()
                tick = last[i]
                due = now if tick is None else tick + period
                if now >= due:
                    publisher.publish(payloads[i])
                    # On schedule, unless behind by a period or more: then restart from now.
                    tick = due if tick is not None and now - due < period else now
                    last[i] = tick
                    due = tick + period
                next_s = min(next_s, due)
            stop.wait(max(0.0, next_s - time.monotonic()))


class Heartbeats:
    """How late each of the optimizer's heartbeats (``/dbm/round``) reached one robot's session.

    The delay is the batch's stamp (the optimizer's wall clock) to its arrival here (this host's):
    one clock, on one machine. Called on the session's thread: it only appends.
    """

    def __init__(self, robot: Robot) -> None:
        self._robot = robot
        self._lock = threading.Lock()
        self._delays_ms: deque[float] = deque(maxlen=HEARTBEATS_KEPT)
        self._first = True

    def on_param(self, name: str, _value: ParamValue) -> None:
        transport = self._robot.transport
        if name != names.ROUND or transport is None:
            return
        stamp = transport.param_stamp_ns(name)
        if stamp is None:
            return
        with self._lock:
            if self._first:  # what the session fetched as it met the fleet: not a delivery
                self._first = False
                return
            self._delays_ms.append((time.time_ns() - stamp) / 1e6)

    def summary(self) -> list[float]:
        """[heartbeats heard, p99 ms, max ms] (zeros if none was)."""
        with self._lock:
            delays = list(self._delays_ms)
        if not delays:
            return [0, 0.0, 0.0]
        return [len(delays), float(np.percentile(delays, 99)), max(delays)]


def run_robots(
    spec: dict[str, Any], emit: Emit, commands: queue.Queue[str], stop: threading.Event
) -> int:
    cond = threading.Condition()
    outcomes: dict[str, str | None] = {}

    def done(host: str, failure: str | None) -> None:
        with cond:
            outcomes.setdefault(host, failure)
            cond.notify_all()

    robots = [
        Robot(
            r["host"],
            [(t, int(s), float(lo), float(hi)) for t, s, lo, hi in r["channels"]],
            spec["net"],
            stop,
            done,
        )
        for r in spec["robots"]
    ]
    # Loaded (Python and dbml imported): the robots start together on the bench's word, so the
    # time to converge counts the fleet meeting the optimizer, not 8 interpreters importing.
    emit({"type": "loaded"})
    while not stop.is_set():
        with contextlib.suppress(queue.Empty):
            if commands.get(timeout=POLL_S * 10).split()[:1] == ["start"]:
                break
    for robot in robots:
        robot.start()
    with cond:
        cond.wait_for(lambda: len(outcomes) == len(robots) or stop.is_set(), timeout=READY_S)
        failed = {h: f for h, f in outcomes.items() if f is not None}
        missing = [r.host for r in robots if r.host not in outcomes]
    emit({"type": "ready", "robots": len(robots), "failed": failed, "not_ready": missing})
    while not stop.is_set():
        try:
            command = commands.get(timeout=POLL_S * 10)
        except queue.Empty:
            continue
        if command.split()[:1] == ["count"]:  # the control messages its robots received
            sessions = [r.transport for r in robots if r.transport is not None]
            received = sum(t.control_messages_received for t in sessions)
            size = sum(t.control_bytes_received for t in sessions)
            emit({"type": "count", "received": received, "bytes": size})
        elif command.split()[:1] == ["heartbeats"]:  # each robot's: heard, p99, max
            emit({"type": "heartbeats", "robots": {r.host: r.heartbeats.summary() for r in robots}})
    deadline = time.monotonic() + STOP_S / 2
    for robot in robots:
        robot.join(timeout=max(0.0, deadline - time.monotonic()))
    return 0


def worker_main(spec_text: str) -> int:
    spec: dict[str, Any] = json.loads(spec_text)
    logging.basicConfig(
        level=logging.WARNING,
        format="%(asctime)s %(threadName)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    logging.getLogger().addHandler(FailsafeCounter())
    with stop_on_signals() as stop:
        commands = Control(stop, name="commands").start().commands
        if spec["role"] == "operator":
            return run_operator(spec, report, commands, stop)
        return run_robots(spec, report, commands, stop)


# -- the bench's side -------------------------------------------------------------------------


class Fleet:
    """The processes of one size, each ended by its PID, and what they report."""

    def __init__(self, port: int, *, logs: Path | None = None) -> None:
        self._env = dict(os.environ, DBML_ZENOH_PORT=str(port))
        self.children = Supervisor(logs=logs)
        self._cond = threading.Condition()
        self.ready: dict[str, dict[str, Any]] = {}
        self.loaded: set[str] = set()
        self.ended: set[str] = set()
        self._failsafe = 0
        self._counting = True
        self.stats: queue.Queue[dict[str, Any]] = queue.Queue()
        self.counts: queue.Queue[tuple[str, Received]] = queue.Queue()
        self.heartbeats: queue.Queue[dict[str, list[float]]] = queue.Queue()
        self._closing = threading.Event()
        self._inbox = threading.Thread(target=self._pump, name="inbox", daemon=True)
        self._inbox.start()

    def _pump(self) -> None:
        while not self._closing.is_set():
            line = self.children.next(timeout_s=POLL_S * 4)
            if line is None:
                continue
            role, message = line.child, line.report
            with self._cond:
                if line.ended:
                    self.ended.add(role)
                elif message is None:
                    pass  # not a report
                elif message.get("type") == "ready":
                    self.ready[role] = message
                elif message.get("type") == "loaded":
                    self.loaded.add(role)
                elif message.get("type") == "failsafe" and self._counting:
                    self._failsafe += 1
                    if self._failsafe <= FAILSAFE_SHOWN:
                        note(f"{role}: {message.get('message')}")
                elif message.get("type") == "stats":
                    self.stats.put(message)
                elif message.get("type") == "heartbeats":
                    self.heartbeats.put(message["robots"])
                elif message.get("type") == "count":
                    self.counts.put(
                        (role, Received(int(message["received"]), int(message["bytes"])))
                    )
                self._cond.notify_all()

    def start_router(self, endpoint: str) -> None:
        argv = [sys.executable, "-m", "dbml", "router", "--listen", endpoint]
        self.children.start("router", argv, env=self._env, stop_signal=signal.SIGTERM)

    def start_optimizer(self, config: Path, net: dict[str, Any]) -> None:
        argv = [sys.executable, "-m", "dbml", "optimizer", "--config", str(config)]
        if net.get("router") is not None:
            argv += ["--connect", net["router"], "--zenoh-config", net["client_config"]]
        self.children.start(
            "optimizer", [*argv, "--host", "base"], env=self._env, stop_signal=signal.SIGTERM
        )

    @property
    def optimizer_pid(self) -> int:
        return self.children.process("optimizer").pid

    def spawn(self, role: str, spec: dict[str, Any]) -> None:
        argv = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)]
        self.children.start(role, argv, env=self._env)

    def wait_ready(self, roles: list[str], timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(
                lambda: all(r in self.ready or r in self.ended for r in roles), timeout=timeout_s
            ) and all(r in self.ready for r in roles)

    def wait_loaded(self, roles: list[str], timeout_s: float) -> bool:
        """Whether every one of ``roles`` has loaded (imported) within ``timeout_s``."""
        with self._cond:
            return self._cond.wait_for(
                lambda: all(r in self.loaded or r in self.ended for r in roles), timeout=timeout_s
            ) and all(r in self.loaded for r in roles)

    def dead(self) -> list[str]:
        """The processes that ended (none should before teardown)."""
        with self._cond:
            gone = sorted(self.ended - {"optimizer"})
        optimizer = self.children.children.get("optimizer")
        if optimizer is not None and (code := optimizer.poll()) is not None:
            gone.append(f"optimizer (exit {code})")
        return gone

    def watch_window(self, seconds: float) -> None:
        """Let ``seconds`` pass, or less if a process ends."""
        deadline = time.monotonic() + seconds
        with self._cond:
            while (left := deadline - time.monotonic()) > 0 and not self.dead():
                self._cond.wait(timeout=min(left, POLL_S * 4))

    def failsafe_events(self, *, freeze: bool = False) -> int:
        with self._cond:
            if freeze:
                self._counting = False
            return self._failsafe

    def operator_stats(self, since_s: float, until_s: float, limit: float) -> dict[str, Any] | None:
        with contextlib.suppress(queue.Empty):
            while True:
                self.stats.get_nowait()  # a late answer to an earlier question
        child = self.children.children.get("operator")
        if child is None or child.poll() is not None:
            return None
        self.children.send(f"stats {since_s!r} {until_s!r} {limit!r}", to="operator")
        deadline = time.monotonic() + STOP_S
        while child.poll() is None and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):
                return self.stats.get(timeout=POLL_S * 4)
        return None

    def control_received(self, workers: list[str]) -> Received | None:
        """The control messages every robot session received so far (None: a worker is gone)."""
        with contextlib.suppress(queue.Empty):
            while True:
                self.counts.get_nowait()  # a late answer to an earlier question
        for worker in workers:
            self.children.send("count", to=worker)
        answered: dict[str, Received] = {}
        deadline = time.monotonic() + STOP_S
        while len(answered) < len(workers) and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):
                role, received = self.counts.get(timeout=POLL_S * 4)
                answered[role] = received
        if len(answered) < len(workers):
            return None
        return Received(
            sum(r.messages for r in answered.values()), sum(r.size_bytes for r in answered.values())
        )

    def heartbeat_delays(self, workers: list[str]) -> dict[str, list[float]] | None:
        """Each robot's [heartbeats heard, p99 ms, max ms] so far (None: a worker is gone)."""
        with contextlib.suppress(queue.Empty):
            while True:
                self.heartbeats.get_nowait()  # a late answer to an earlier question
        for worker in workers:
            self.children.send("heartbeats", to=worker)
        robots: dict[str, list[float]] = {}
        answered = 0
        deadline = time.monotonic() + STOP_S
        while answered < len(workers) and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):
                robots |= self.heartbeats.get(timeout=POLL_S * 4)
                answered += 1
        return robots if answered == len(workers) else None

    def pids(self) -> list[int]:
        """This process and every process started here."""
        return [os.getpid(), *self.children.pids()]

    def pids_by_role(self) -> dict[str, list[int]]:
        """The run's processes by what they do: the robots' workers together."""
        roles: dict[str, list[int]] = {"bench": [os.getpid()]}
        for name in self.children.children:
            role = "robots" if name.startswith("robots-") else name
            roles.setdefault(role, []).append(self.children.process(name).pid)
        return roles

    def robot_failures(self, workers: list[str], robots: int) -> int:
        """Robots whose session or publishers were not set up (all of a silent worker's)."""
        with self._cond:
            reports = [self.ready.get(w) for w in workers]
        up = sum(int(r["robots"]) - len(r["failed"]) - len(r["not_ready"]) for r in reports if r)
        return robots - up

    def close(self) -> None:
        try:
            # Stop (the optimizer and router: SIGTERM), then SIGTERM, then SIGKILL: by PID.
            self.children.close()
        finally:
            self._closing.set()
            self._inbox.join(timeout=STOP_S)


class Probe:
    """The bench's session: every parameter change wakes waiters; stamps awaited acks."""

    def __init__(self, transport: ZenohTransport) -> None:
        self.params = transport.params
        self._cond = threading.Condition()
        self._version = 0
        self._awaited: str | None = None
        self._before: ParamValue = None
        self._arrived: tuple[float, ParamValue] | None = None
        self._target = math.nan
        self._reached: float | None = None
        self._handle = transport.params.watch(self._on_param)

    def _on_param(self, name: str, value: ParamValue) -> None:
        now = time.perf_counter()
        with self._cond:
            self._version += 1
            if name == self._awaited and self._arrived is None and value != self._before:
                self._arrived = (now, value)
            if name == self._awaited and self._reached is None and close_to(value, self._target):
                self._reached = now
            self._cond.notify_all()

    def arm(self, name: str, target: float) -> None:
        """Stamp ``name``'s next new value, and its arrival at ``target`` (2 %)."""
        before = self.params.get(name)  # outside our lock: the store may call us under its own
        with self._cond:
            self._awaited, self._before, self._arrived = name, before, None
            self._target, self._reached = target, None

    def arrival(self, timeout_s: float) -> tuple[float, ParamValue] | None:
        """When the armed parameter took a new value (perf_counter) and that value."""
        with self._cond:
            self._cond.wait_for(lambda: self._arrived is not None, timeout=timeout_s)
            return self._arrived

    def reached(self, timeout_s: float) -> float | None:
        """When the armed parameter reached its target (perf_counter); then disarmed."""
        with self._cond:
            self._cond.wait_for(lambda: self._reached is not None, timeout=timeout_s)
            self._awaited = None
            return self._reached

    def wait_until(
        self, predicate: Callable[[], bool], timeout_s: float, abort: Callable[[], bool]
    ) -> bool:
        """Evaluate ``predicate`` after parameter changes (at most every ``CHECK_S``)."""
        deadline = time.monotonic() + timeout_s
        seen, checked = -1, 0.0
        while True:
            with self._cond:
                version = self._version
            if version != seen:
                seen = version
                checked = time.monotonic()
                if predicate():
                    return True
            if abort():
                return False
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            with self._cond:
                self._cond.wait_for(partial(self._changed, seen), timeout=min(left, POLL_S))
            pause = CHECK_S - (time.monotonic() - checked)
            if pause > 0:
                time.sleep(min(pause, max(0.0, deadline - time.monotonic())))

    def settled_count(self, expected: dict[str, float]) -> int:
        """Channels managed, allocated ``expected`` (2 %) and acknowledged by the publisher."""
        get = self.params.get
        count = 0
        for topic, rate in expected.items():
            current = get(names.current_value(topic))
            count += (
                get(names.managed(topic)) is True
                and close_to(current, rate)
                and get(names.applied(topic)) == current
            )
        return count

    def unsettled(self, expected: dict[str, float], shown: int = 5) -> list[str]:
        """What the first ``shown`` unsettled channels hold, for a diagnostic."""
        get = self.params.get
        found = []
        for topic, rate in expected.items():
            held = [get(names.managed(topic)), get(names.current_value(topic))]
            held.append(get(names.applied(topic)))
            if not (held[0] is True and close_to(held[1], rate) and held[2] == held[1]):
                found.append(f"{topic} managed/current/applied={held} expected {rate:.4g}")
        return found[:shown]

    def settled(self, expected: dict[str, float]) -> bool:
        if self.params.get(names.STATUS) != Status.OPTIMAL.value:
            return False
        return self.settled_count(expected) == len(expected)

    def _changed(self, seen: int) -> bool:
        return self._version != seen

    def close(self) -> None:
        self._handle.close()


def draw_change(
    rng: random.Random,
    channels: list[Channel],
    priorities: dict[str, float],
    budget_mbit: float,
    expected: dict[str, float],
) -> tuple[str, float, dict[str, float]] | None:
    """A channel and a priority that change that channel's allocated rate (and stay feasible)."""
    for _ in range(DRAWS):
        channel = rng.choice(channels)
        priority = rng.choice(PRIORITY_STEPS)
        if priority == priorities[channel.topic]:
            continue
        rates = expected_rates(channels, {**priorities, channel.topic: priority}, budget_mbit)
        old = expected[channel.topic]
        if rates is not None and not math.isclose(rates[channel.topic], old, rel_tol=RATE_TOL):
            return channel.topic, priority, rates
    return None


def empty_row(
    robots: int, channels: int, budget_bytes_per_s: float, budget_share: float
) -> dict[str, Any]:
    return {
        "robots": robots,
        "channels": channels,
        "sessions": robots + 3,
        "budget_bytes_per_s": round(budget_bytes_per_s),
        "budget_share": budget_share,
        "sizes_bytes": None,
        "rates_hz": None,
        "converge_s": None,
        "reaction_p50_ms": None,
        "reaction_p99_ms": None,
        "control_msgs_per_s": None,
        "control_bytes_per_s": None,
        "delivered_over_budget": None,
        "join_cpu_s_by_role": None,
        "join_cpu_ms_per_robot": None,
        "join_host_cpu_pct": None,
        "optimizer_cpu_pct": None,
        "failsafe_events": None,
        "delivered_over_budget_steady": None,
        "delivered_mean_over_budget": None,
        "delivered_ideal_over_budget": None,
        "sent_over_budget": None,
        "fleet_cpu_pct": None,
        "host_cpu_pct": None,
        "host_steal_pct": None,
        "cpu_pct_by_role": None,
        "optimizer_cpu_ms_per_round": None,
        "robot_control_msgs_per_s": None,
        "robot_control_msgs_per_change": None,
        "robot_control_msgs_per_change_net": None,
        "robot_control_bytes_per_s": None,
        "heartbeat_p99_ms": None,
        "heartbeat_max_ms": None,
        "heartbeat_late_robots": None,
        "robot_control_bytes_per_change_net": None,
        "settled_channels": 0,
        "reaction_changes": 0,
        "reaction_misses": 0,
        "reaction_whole_p50_ms": None,
        "reaction_whole_p99_ms": None,
        "reaction_raised": 0,
        "reaction_raised_p50_ms": None,
        "reaction_raised_p99_ms": None,
        "reaction_unsettled": 0,
        "robot_failures": 0,
        "error": None,
    }


class Received(NamedTuple):
    """Control messages the robots' sessions received, and their payloads' bytes."""

    messages: int
    size_bytes: int


class Run(NamedTuple):
    net: dict[str, Any]
    """``port`` (the loopback mesh's), and with a router its ``router`` endpoint and the
    sessions' ``client_config`` file."""
    config: Path
    channels: list[Channel]
    budget_mbit: float
    steady_s: float


def measure_size(
    robots: int,
    per_robot: int,
    seconds: float,
    *,
    budget_mbit: float | None = SITE_BUDGET_MBIT,
    budget_share: float = BUDGET_SHARE,
    topology: str = DEFAULT_TOPOLOGY,
    logs: Path | None = None,
) -> dict[str, Any]:
    """One size: a row with what could be measured (and ``error`` saying what could not).

    ``budget_mbit`` None: the heavy run (``plan``).
    """
    channels, budget_bps = plan(
        robots, per_robot, budget_mbit=budget_mbit, budget_share=budget_share
    )
    budget_mbit = budget_bps * 8 / 1e6
    if expected_rates(channels, {}, budget_mbit) is None:
        raise SystemExit(f"{robots}x{per_robot}: the floors do not fit the budget")
    row = empty_row(robots, per_robot, budget_bps, budget_share)
    row["sizes_bytes"] = sorted({c.size_bytes for c in channels}, reverse=True)
    row["rates_hz"] = [channels[0].min_hz, channels[0].max_hz]
    row["topology"] = topology
    port = free_port()
    note(f"{robots}x{per_robot}: {len(channels)} channels, port {port}, {budget_mbit:.1f} Mbit/s")
    with contextlib.ExitStack() as stack:
        workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="dbml-fleet-")))
        config = workdir / "dbm.yaml"
        config.write_text(
            f"dbm:\n  max_bandwidth_in_mbit: {budget_mbit!r}\n"
            f"  optimization_rate_in_seconds: {PERIOD_S:g}\n  strategy: {STRATEGY}\n"
            "  frame_headroom: true\n"
        )
        net: dict[str, Any] = {"port": port}
        if topology == "router":
            client_config = workdir / "client.json5"
            client_config.write_text(CLIENT_CONFIG)
            net |= {"router": f"tcp/127.0.0.1:{port}", "client_config": str(client_config)}
        try:
            size_logs = None if logs is None else logs / f"{robots}x{per_robot}"
            if size_logs is not None:
                size_logs.mkdir(parents=True, exist_ok=True)
            fleet = Fleet(port, logs=size_logs)
            stack.callback(fleet.close)
            if topology == "router":
                fleet.start_router(net["router"])
            # This session before the others: on the mesh it holds the rendezvous for the run.
            transport = open_session("bench", net)
            stack.callback(transport.close)
            control = WireSniffer(transport.session, "dbml/**")
            stack.callback(control.close)
            probe = Probe(transport)
            stack.callback(probe.close)
            try:
                run_size(
                    fleet, probe, control, Run(net, config, channels, budget_mbit, seconds), row
                )
            finally:
                row["failsafe_events"] = fleet.failsafe_events(freeze=True)
                if row["error"] is not None:
                    for role, child in sorted(fleet.children.children.items()):
                        tail = child.log_tail().strip().splitlines()[-5:]
                        if tail:
                            note(f"--- {role} ---\n" + "\n".join(tail))
                note(f"{robots}x{per_robot}: stopping")
        except Exception as err:  # a runtime that fails at this size: report it, go on
            row["error"] = f"{type(err).__name__}: {err}"
            note(f"{robots}x{per_robot}: {row['error']}")
    note(f"{robots}x{per_robot}: {json.dumps(row)}")
    return row


def run_size(
    fleet: Fleet, probe: Probe, control: WireSniffer, run: Run, row: dict[str, Any]
) -> None:
    channels = run.channels
    budget_bps = run.budget_mbit * 1e6 / 8
    expected = expected_rates(channels, {}, run.budget_mbit)
    assert expected is not None
    fleet.start_optimizer(run.config, run.net)
    topics = [c.topic for c in channels]
    fleet.spawn("operator", {"role": "operator", "net": run.net, "topics": topics})
    if not fleet.wait_ready(["operator"], OPERATOR_READY_S):
        dead = fleet.dead() or "none"
        row["error"] = f"operator not ready within {OPERATOR_READY_S:g} s (ended: {dead})"
        return
    note("operator ready; starting the robots")
    hosts = list(dict.fromkeys(c.host for c in channels))
    workers = []
    for first in range(0, len(hosts), ROBOTS_PER_WORKER):
        group = hosts[first : first + ROBOTS_PER_WORKER]
        role = f"robots-{group[0]}-{group[-1]}"
        robots = [
            {
                "host": h,
                "channels": [
                    [c.topic, c.size_bytes, c.min_hz, c.max_hz] for c in channels if c.host == h
                ],
            }
            for h in group
        ]
        fleet.spawn(role, {"role": "robots", "net": run.net, "robots": robots})
        workers.append(role)
    if not fleet.wait_loaded(workers, READY_S):
        row["error"] = f"robots' workers not loaded within {READY_S:g} s (ended: {fleet.dead()})"
        return
    join_roles = fleet.pids_by_role()
    join_start = CpuReading.now(join_roles)
    for worker in workers:
        fleet.children.send("start", to=worker)
    t0 = time.monotonic()

    def abort() -> bool:
        return bool(fleet.dead())

    converged = probe.wait_until(lambda: probe.settled(expected), CONVERGE_S, abort)
    if converged:
        row["converge_s"] = round(time.monotonic() - t0, 3)
        note(f"converged in {row['converge_s']} s")
    else:
        dead = fleet.dead()
        row["error"] = f"not converged within {CONVERGE_S:g} s" + (
            f" (ended: {dead})" if dead else ""
        )
        status = probe.params.get(names.STATUS)
        note(f"{row['error']}; status {status!r}; " + "; ".join(probe.unsettled(expected)))
    _join_cpu(row, CpuReading.now(join_roles).since(join_start), robots=len(hosts))
    row["settled_channels"] = probe.settled_count(expected)
    row["robot_failures"] = fleet.robot_failures(workers, len(hosts))

    # Steady state: control traffic and what each role spent.
    roles = fleet.pids_by_role()
    received_a = fleet.control_received(workers)
    t_a, cpu_a = time.monotonic(), CpuReading.now(roles)
    fleet.watch_window(run.steady_s)
    t_b, cpu_b = time.monotonic(), CpuReading.now(roles)
    received_b = fleet.control_received(workers)
    span_s = t_b - t_a
    spent = cpu_b.since(cpu_a)
    by_role = {role: round(100 * s / span_s, 1) for role, s in spent.cpu_s_by_role.items()}
    row["cpu_pct_by_role"] = by_role
    row["fleet_cpu_pct"] = round(sum(by_role.values()), 1)
    row["optimizer_cpu_pct"] = by_role.get("optimizer")
    if row["optimizer_cpu_pct"] is not None:  # one round a second (the config's period)
        row["optimizer_cpu_ms_per_round"] = round(10 * row["optimizer_cpu_pct"] * PERIOD_S, 1)
    if spent.host_busy_pct is not None:
        row["host_cpu_pct"] = round(spent.host_busy_pct, 1)
    if spent.host_steal_pct is not None:
        row["host_steal_pct"] = round(spent.host_steal_pct, 1)
    arrivals = [a for a in control.arrivals(since_s=t_a) if a[0] <= t_b]
    row["control_msgs_per_s"] = round(len(arrivals) / span_s, 2)
    steady: Received | None = None
    if received_a is not None and received_b is not None:
        steady = Received(
            received_b.messages - received_a.messages, received_b.size_bytes - received_a.size_bytes
        )
        row["robot_control_msgs_per_s"] = round(steady.messages / len(hosts) / span_s, 3)
        row["robot_control_bytes_per_s"] = round(steady.size_bytes / len(hosts) / span_s, 1)
    row["control_bytes_per_s"] = round(sum(n for _, n in arrivals) / span_s, 1)

    row["delivered_ideal_over_budget"] = ideal_delivered(
        channels, expected, budget_bps, run.steady_s
    )
    stats = fleet.operator_stats(t_a, t_b, budget_bps)
    if stats is not None and stats["windows"]:
        row["delivered_over_budget_steady"] = round(stats["worst_bytes"] / budget_bps, 4)
        row["delivered_mean_over_budget"] = round(stats["bytes"] / span_s / budget_bps, 4)
    if converged:
        before, started = fleet.control_received(workers), time.monotonic()
        react(probe, channels, expected, run.budget_mbit, row=row, abort=abort)
        after, react_s = fleet.control_received(workers), time.monotonic() - started
        changes = row["reaction_changes"]
        if before is not None and after is not None and changes:
            per_change = (after.messages - before.messages) / len(hosts) / changes
            row["robot_control_msgs_per_change"] = round(per_change, 3)
            if steady is not None:  # less the heartbeats meanwhile
                share = react_s / span_s / changes / len(hosts)
                row["robot_control_msgs_per_change_net"] = round(
                    per_change - steady.messages * share, 3
                )
                bytes_per_change = (after.size_bytes - before.size_bytes) / len(hosts) / changes
                row["robot_control_bytes_per_change_net"] = round(
                    bytes_per_change - steady.size_bytes * share, 1
                )
    heard = fleet.heartbeat_delays(workers)
    if heard:  # from each robot's start: its ramp, the steady state and the reactions
        row["heartbeat_p99_ms"] = round(max(p99 for _, p99, _ in heard.values()), 1)
        row["heartbeat_max_ms"] = round(max(most for _, _, most in heard.values()), 1)
        row["heartbeat_late_robots"] = sum(
            1 for count, p99, _ in heard.values() if not count or p99 > PERIOD_S * 1e3
        )
    stats = fleet.operator_stats(t_a, time.monotonic(), budget_bps)
    if stats is not None and stats["windows"]:
        row["delivered_over_budget"] = round(stats["worst_bytes"] / budget_bps, 4)
        row["sent_over_budget"] = round(stats["worst_sent_bytes"] / budget_bps, 4)
    if fleet.dead() and row["error"] is None:
        row["error"] = f"ended before the teardown: {fleet.dead()}"


class CpuSpent(NamedTuple):
    """What the run's processes and the host spent between two ``CpuReading``s."""

    cpu_s_by_role: dict[str, float]
    host_busy_pct: float | None
    """Of one core (200 on two cores busy); None when no tick passed."""
    host_steal_pct: float | None
    """Of that, what a virtual machine's hypervisor took for others."""


class CpuReading(NamedTuple):
    """Every role's processes' CPU clock ticks (None: one gone) and the host's, at one moment."""

    roles: dict[str, list[int | None]]
    host: tuple[int, int, int]

    @classmethod
    def now(cls, roles: dict[str, list[int]]) -> CpuReading:
        ticks = {role: [cpu_ticks(p) for p in pids] for role, pids in roles.items()}
        return cls(ticks, host_busy_ticks())

    def since(self, before: CpuReading) -> CpuSpent:
        hz = os.sysconf("SC_CLK_TCK")
        by_role = {
            role: _spent(before.roles[role], ticks) / hz for role, ticks in self.roles.items()
        }
        total = self.host[1] - before.host[1]
        if total <= 0:
            return CpuSpent(by_role, None, None)
        cores = 100 * (os.cpu_count() or 1)
        busy = cores * (self.host[0] - before.host[0]) / total
        return CpuSpent(by_role, busy, cores * (self.host[2] - before.host[2]) / total)


def _join_cpu(row: dict[str, Any], spent: CpuSpent, *, robots: int) -> None:
    """What the join cost, from the word that starts every robot to convergence (or its timeout).

    Per role in CPU-seconds, per robot in CPU-ms (every process of the run), and the host's
    busy share meanwhile: a join that keeps both cores busy is as fast as this machine allows.
    """
    row["join_cpu_s_by_role"] = {role: round(s, 2) for role, s in spent.cpu_s_by_role.items()}
    row["join_cpu_ms_per_robot"] = round(1e3 * sum(spent.cpu_s_by_role.values()) / robots, 1)
    if spent.host_busy_pct is not None:
        row["join_host_cpu_pct"] = round(spent.host_busy_pct, 1)


def _spent(before: list[int | None], after: list[int | None]) -> int:
    """Clock ticks spent between two readings of the same processes (one gone: not counted)."""
    return sum(b - a for a, b in zip(before, after, strict=True) if a is not None and b is not None)


def react(
    probe: Probe,
    channels: list[Channel],
    expected: dict[str, float],
    budget_mbit: float,
    *,
    row: dict[str, Any],
    abort: Callable[[], bool],
) -> None:
    rng = random.Random(SEED)
    priorities = {c.topic: 0.0 for c in channels}
    latencies_ms: list[float] = []
    raised_ms: list[float] = []  # the changes that raised their channel: they wait for room
    whole_ms: list[float] = []  # to the new rate itself, not a step on the way
    misses = unsettled = 0
    deadline = time.monotonic() + REACTIONS_S
    for _ in range(CHANGES):
        if time.monotonic() >= deadline or abort():
            break
        change = draw_change(rng, channels, priorities, budget_mbit, expected)
        if change is None:
            break
        raised = change[2][change[0]] > expected[change[0]]
        topic, priority, expected = change
        priorities[topic] = priority
        probe.arm(names.applied(topic), expected[topic])
        start = time.perf_counter()
        probe.params.set(names.priority(topic), priority)
        arrived = probe.arrival(CHANGE_TIMEOUT_S)
        if arrived is None:
            misses += 1
            latencies_ms.append(CHANGE_TIMEOUT_S * 1e3)
        else:
            latencies_ms.append((arrived[0] - start) * 1e3)
        reached = probe.reached(CHANGE_TIMEOUT_S)
        whole_ms.append(CHANGE_TIMEOUT_S * 1e3 if reached is None else (reached - start) * 1e3)
        if raised:
            raised_ms.append(latencies_ms[-1])
        if not probe.wait_until(partial(probe.settled, expected), SETTLE_S, abort):
            unsettled += 1
    row["reaction_changes"] = len(latencies_ms)
    row["reaction_misses"] = misses
    row["reaction_unsettled"] = unsettled
    row["reaction_p50_ms"] = percentile(latencies_ms, 50)
    row["reaction_p99_ms"] = percentile(latencies_ms, 99)
    row["reaction_whole_p50_ms"] = percentile(whole_ms, 50)
    row["reaction_whole_p99_ms"] = percentile(whole_ms, 99)
    row["reaction_raised"] = len(raised_ms)
    row["reaction_raised_p50_ms"] = percentile(raised_ms, 50)
    row["reaction_raised_p99_ms"] = percentile(raised_ms, 99)


def judge(row: dict[str, Any], by_size: dict[str, dict[str, Any]]) -> dict[str, bool]:
    """Which of its size's targets this row meets; an unmeasured value meets none.

    A size without targets (in ``by_size``) meets none and misses none: it is reported as it
    stands.
    """
    targets = by_size.get(f"{row['robots']}x{row['channels']}", {})

    def at_most(value: float | None, limit: float) -> bool:
        return value is not None and value <= limit

    met: dict[str, bool] = {}
    if "converge_s_max" in targets:
        met["converge"] = at_most(row["converge_s"], targets["converge_s_max"])
    if "reaction_p99_ms_max" in targets:
        met["reaction"] = at_most(row["reaction_p99_ms"], targets["reaction_p99_ms_max"])
    if "heartbeat_p99_ms_max" in targets:
        met["heartbeat"] = at_most(row["heartbeat_p99_ms"], targets["heartbeat_p99_ms_max"])
    if "failsafe_events_max" in targets:
        met["failsafe"] = at_most(row["failsafe_events"], targets["failsafe_events_max"])
    if "delivered_over_budget_max" in targets:  # whole frames: one largest message over
        limit = 1.0 + max(row["sizes_bytes"]) / row["budget_bytes_per_s"]
        met["delivered"] = at_most(row["delivered_over_budget"], limit)
    if "control_share_of_budget_max" in targets:
        control = row["control_bytes_per_s"]
        met["control"] = at_most(
            None if control is None else control / row["budget_bytes_per_s"],
            targets["control_share_of_budget_max"],
        )
    if targets.get("every_channel_allocated"):
        met["allocated"] = row["settled_channels"] == row["robots"] * row["channels"]
    return met


def flat(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Whether a robot's control messages per change grew from the smallest fleet to the largest.

    Within ``FLAT_SLACK`` it did not; None with fewer than two sizes measured.
    """
    measured = sorted(
        (r["robots"], r["robot_control_msgs_per_change_net"])
        for r in rows
        if r["robot_control_msgs_per_change_net"] is not None
    )
    if len({robots for robots, _ in measured}) < 2:
        return None
    (small, first), (large, last) = measured[0], measured[-1]
    return {
        "from_robots": small,
        "to_robots": large,
        "from_msgs": first,
        "to_msgs": last,
        "ok": last <= first * (1 + FLAT_SLACK),
    }


def render(document: dict[str, Any]) -> None:
    def show(value: Any) -> str:
        return "-" if value is None else f"{value:,}" if isinstance(value, int) else f"{value:g}"

    heavy = document["mode"] == "heavy"
    title = "heavy: saturated router" if heavy else "site budget"
    table = Table(
        title=f"dbml control plane at fleet size, {title} (loopback zenoh, separate processes)"
    )
    columns = {
        "size": None,
        "converge s": "converge_s",
        "allocated": "settled_channels",
        "react p50 ms": "reaction_p50_ms",
        "react p99 ms": "reaction_p99_ms",
        "heartbeat p99 ms": "heartbeat_p99_ms",
        "robot ctl msg/change": "robot_control_msgs_per_change_net",
        "robot ctl B/s": "robot_control_bytes_per_s",
        "ctl B/s": "control_bytes_per_s",
        "delivered/budget": "delivered_over_budget",
        "fail-safe": "failsafe_events",
        "opt CPU %": "optimizer_cpu_pct",
        "robots CPU %": None,
        "host CPU %": "host_cpu_pct",
        "join CPU ms/robot": "join_cpu_ms_per_robot",
        "join host CPU %": "join_host_cpu_pct",
        "targets": None,
    }
    for name in columns:
        table.add_column(name, justify="right")
    for row in document["results"]:
        cells = [f"{row['robots']}x{row['channels']}"]
        by_role = row["cpu_pct_by_role"] or {}
        cells += [
            show(by_role.get("robots") if key is None else row[key])
            for key in list(columns.values())[1:-1]
        ]
        missed = [k for k, ok in row["meets_targets"].items() if not ok]
        met = "met" if not missed else "missed: " + ", ".join(missed)
        cells.append(met if row["meets_targets"] else "-")
        table.add_row(*cells)
    table.caption = "targets: " + "; ".join(
        f"{size}: " + ", ".join(f"{k}={v}" for k, v in t.items())
        for size, t in document["targets"].items()
    )
    if document["flat"] is not None:
        f = document["flat"]
        table.caption += (
            f"; robot ctl msgs per change {f['from_msgs']:g} at {f['from_robots']} robots, "
            f"{f['to_msgs']:g} at {f['to_robots']}: {'flat' if f['ok'] else 'GROWS'}"
        )
    console = Console()
    if not console.is_terminal:
        console = Console(width=170)
    console.print(table)


def plot(document: dict[str, Any], path: Path) -> None:
    """The scaling curve: convergence, reaction, control per robot and CPU by size.

    Every run is a point; the line joins each size's median.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted(document["results"], key=lambda r: r["robots"])
    sizes = sorted({r["robots"] for r in rows})

    def value(row: dict[str, Any], key: str) -> float:
        roles = row["cpu_pct_by_role"] or {}
        found = roles.get(key[4:]) if key.startswith("cpu:") else row[key]
        return math.nan if found is None else float(found)

    def medians(key: str) -> list[float]:
        out = []
        for size in sizes:
            values = [v for r in rows if r["robots"] == size if not math.isnan(v := value(r, key))]
            out.append(float(np.median(values)) if values else math.nan)
        return out

    figure, axes = plt.subplots(2, 3, figsize=(14, 7), sharex=True)
    panels = [
        (axes[0][0], "convergence (s)", [("converge_s", "converge")]),
        (axes[0][1], "reaction (ms)", [("reaction_p50_ms", "p50"), ("reaction_p99_ms", "p99")]),
        (
            axes[0][2],
            "CPU (% of one core)",
            [
                ("cpu:optimizer", "optimizer"),
                ("cpu:router", "router"),
                ("cpu:robots", "robots"),
                ("host_cpu_pct", "host"),
            ],
        ),
        (
            axes[1][0],
            "control messages per robot",
            [
                ("robot_control_msgs_per_change_net", "per change"),
                ("robot_control_msgs_per_s", "per second, steady"),
            ],
        ),
        (
            axes[1][1],
            "control bytes per robot",
            [
                ("robot_control_bytes_per_change_net", "per change"),
                ("robot_control_bytes_per_s", "per second, steady"),
            ],
        ),
        (axes[1][2], "optimizer CPU per round (ms)", [("optimizer_cpu_ms_per_round", "round")]),
    ]
    for axis, title, lines in panels:
        for key, label in lines:
            (line,) = axis.plot(sizes, medians(key), marker="o", label=label)
            axis.scatter(
                [r["robots"] for r in rows],
                [value(r, key) for r in rows],
                s=12,
                alpha=0.5,
                color=line.get_color(),
            )
        axis.set_title(title)
        axis.grid(True, alpha=0.3)
        axis.legend()
    for axis in axes[1]:
        axis.set_xlabel(f"robots ({rows[0]['channels']} channels each)" if rows else "robots")
    mode = "heavy" if document["mode"] == "heavy" else "site budget"
    figure.suptitle(f"dbml control plane by fleet size, {mode} (bench/fleet.py)")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, help="one size: this many robots")
    parser.add_argument("--channels", type=int, help="one size: channels per robot (default 4)")
    parser.add_argument(
        "--seconds", type=float, default=STEADY_S, help=f"steady state (default {STEADY_S:g})"
    )
    parser.add_argument(
        "--budget-mbit",
        type=float,
        default=SITE_BUDGET_MBIT,
        help=f"the fleet's shared budget; frames scaled to it (default {SITE_BUDGET_MBIT:g})",
    )
    parser.add_argument(
        "--heavy",
        action="store_true",
        help="the paper's frames at --budget-share of the maxima: a saturated router (80 x 4)",
    )
    parser.add_argument(
        "--budget-share",
        type=float,
        default=BUDGET_SHARE,
        help=f"budget as a share of the sum of max rate x size (default {BUDGET_SHARE:g})",
    )
    parser.add_argument(
        "--sweep",
        action="store_true",
        help=f"the scaling curve: {', '.join(map(str, SWEEP_ROBOTS))} robots",
    )
    parser.add_argument("--runs", type=int, default=1, help="runs of each size (default 1)")
    parser.add_argument("--plot", type=Path, help="write the sizes' curve as a PNG to FILE")
    parser.add_argument(
        "--topology",
        choices=TOPOLOGIES,
        default=DEFAULT_TOPOLOGY,
        help="router (default): each session is a client of one router; peer: a loopback mesh",
    )
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument(
        "--logs", type=Path, help="keep every process's whole stderr in DIR/<size>/<role>.log"
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker is not None:
        raise SystemExit(worker_main(args.worker))
    if args.robots is not None and args.robots < 1:
        parser.error("--robots must be >= 1")
    if args.channels is not None and args.channels < 1:
        parser.error("--channels must be >= 1")
    if not args.seconds > 0:
        parser.error("--seconds must be > 0")
    if args.runs < 1:
        parser.error(f"--runs must be >= 1, got {args.runs!r}")
    if not 0 < args.budget_share <= 1:
        parser.error(f"--budget-share must be in (0, 1], got {args.budget_share!r}")
    if not (math.isfinite(args.budget_mbit) and args.budget_mbit > 0):
        parser.error(f"--budget-mbit must be a number > 0, got {args.budget_mbit!r}")
    mode = "heavy" if args.heavy else "site"
    if args.sweep:
        if args.robots is not None:
            parser.error("--sweep runs its own sizes: no --robots")
        sizes = [(robots, args.channels or TARGET_SIZE[1]) for robots in SWEEP_ROBOTS]
    elif args.robots is None and args.channels is None:
        sizes = list(HEAVY_SIZES if args.heavy else SITE_SIZES)
    else:
        sizes = [(args.robots or TARGET_SIZE[0], args.channels or TARGET_SIZE[1])]
    results = []
    try:
        with sigterm_as_interrupt():  # SIGTERM too ends every process started here
            for robots, channels in (size for size in sizes for _ in range(args.runs)):
                row = measure_size(
                    robots,
                    channels,
                    args.seconds,
                    budget_mbit=None if args.heavy else args.budget_mbit,
                    budget_share=args.budget_share,
                    topology=args.topology,
                    logs=args.logs,
                )
                row["mode"] = mode
                row["meets_targets"] = judge(row, TARGETS[mode])
                row["ok"] = all(row["meets_targets"].values())
                results.append(row)
    except KeyboardInterrupt:
        note("interrupted; every process started here was ended")
        raise SystemExit(130) from None
    document = {
        "benchmark": "fleet",
        "mode": mode,
        "results": results,
        "targets": TARGETS[mode],
        "flat": flat(results),
    }
    if args.plot is not None:
        plot(document, args.plot)
        note(f"curve written to {args.plot}")
    if not args.json:
        render(document)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
