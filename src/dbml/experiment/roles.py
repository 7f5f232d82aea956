"""The roles of the teleoperation experiment: one set for the demo and the testbed.

- ``optimizer``: the optimizer node with the scenario's budget (the testbed's links and
  estimator when asked for).
- ``r1``/``r2``: a robot publishing its camera's frames. Managed, through a publisher whose
  priority follows Table 2's replayed events (eq. 6-7); unmanaged (the testbed's baseline), a
  plain publisher at the camera's maximum rate, as without dbml.
- ``operator``: receives both cameras (managed subscribers, or plain ones when unmanaged) and
  reports, every ``TICK_S``, the frames that arrived (robot, sequence number, send and arrival
  time, size, the rate the publisher applied) and the parameters in force (allocation, budget,
  estimate, the variant each subscriber takes): an ``OperatorReport``. The runner analyses
  them.

As a process (``python -m dbml.experiment.roles ROLE SPEC_JSON``) a role opens its transport,
prints ``{"type": "ready"}``, waits for ``start <t0>`` on stdin and ends at the last step, on
``stop``, stdin EOF, SIGINT or SIGTERM. Over the memory transport the runner calls
:func:`run_role` in a thread instead.

A role whose process loses a dbml thread meanwhile (its own, a node's, the transport's) would go
on reporting a run that is not the one measured: it ends early, without ``done``, and its
process exits 1, so the runner fails the run naming it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from dbml.core.allocation import Strategy
from dbml.core.config import DbmSettings
from dbml.core.errors import DbmlError, SpecError, TransportError
from dbml.core.estimator import EstimatorState
from dbml.core.spec import LinkSpec
from dbml.experiment.analysis import Arrival, Tick
from dbml.experiment.report import OperatorReport
from dbml.harness.processes import Emit, emit_json, serve_role, stop_on_signals
from dbml.protocol import names
from dbml.protocol.metadata import MessageMeta, pack_meta
from dbml.protocol.schema import Writer
from dbml.runtime.params import ParamView
from dbml.runtime.priority import collision_priority_source
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.rate import Rate
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.serve import Lifetime, run_optimizer
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.scenarios.fleet import fleet_cameras, fleet_steps
from dbml.scenarios.teleop import LINK_MBIT, MAX_RATE_HZ, MIN_RATE_HZ, ROBOTS, STEPS, RobotCamera
from dbml.transports.base import Handle, Sample, Transport, Variant
from dbml.transports.registry import camera_frame, open_transport
from dbml.transports.worker import BackgroundThread
from dbml.view.live import LiveView, open_view
from dbml.view.target import ViewTarget

__all__ = [
    "HOSTS",
    "ROLES",
    "TAIL_S",
    "TICK_S",
    "URGENT_RATE_HZ",
    "URGENT_SIZE_BYTES",
    "URGENT_STREAMS",
    "RoleSpec",
    "UrgentStream",
    "fleet_phase_s",
    "main",
    "operator_tick",
    "robot_index",
    "run_role",
    "wait_until",
]

log = logging.getLogger("dbml.experiment")

ROLES = ("operator", "optimizer", *(camera.robot.lower() for camera in ROBOTS))
"""Every role, in the order they start: listeners before those that connect to them."""
HOSTS = {"operator": "operator", "optimizer": "base-station", "r1": "robot-r1", "r2": "robot-r2"}
"""Each role's host identity: four hosts, so every robot-to-operator stream is managed."""
TICK_S = 0.2
"""How often the operator reports what arrived."""
TAIL_S = 1.0
"""The operator and optimizer run this long after the last step, for frames still in flight."""
PERIOD_S = 1.0
"""The optimisation period (the paper's 1 s): the publishers' heartbeat."""
PEER_WAIT_S = 10.0
"""How long a role waits to reach the others before it reports ready."""
_OPERATOR = frozenset({Writer.OPERATOR})
"""The operator's view sets what an operator writes: the budget and priorities."""
_URGENT_JOIN_S = 5.0
"""How long robot R1 waits for its urgent streams' last tick (a send in progress)."""


URGENT_SIZE_BYTES = 1_000
"""The urgent stream's message: a command or an alarm, small next to a camera frame."""
URGENT_RATE_HZ = 20.0
URGENT_PRIORITY = 1.0
"""The urgent stream's raw priority: the most urgent there is."""


@dataclass(frozen=True, slots=True)
class UrgentStream:
    """A small urgent channel on robot R1, beside its camera: with or without the class mapping."""

    topic: str
    mapped: bool
    """True: its priority picks its transport class; False: zenoh's default, as before."""


URGENT_STREAMS = (
    UrgentStream("/r1/urgent/mapped", mapped=True),
    UrgentStream("/r1/urgent/unmapped", mapped=False),
)
"""Two copies of one stream at the same moment on the same link, so the mapping is the only
difference. The operator reports their arrivals as robots ``len(ROBOTS) + k``."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RoleSpec:
    """Everything a role needs, passed to a role process as one JSON argument."""

    step_s: float
    transport: str = "zenoh"
    host: str | None = None
    """The zenoh or memory host identity (ROS 1 takes ROS_IP/ROS_HOSTNAME)."""
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    managed: bool = True
    """False: the robots publish at their maximum and no optimizer runs (the testbed's baseline)."""
    link_mbit: float = LINK_MBIT
    utilization: float = 1.0
    strategy: str = Strategy.PAPER.value
    estimate: bool = False
    uplinks_mbit: dict[str, float] = field(default_factory=dict)
    peer_wait_s: float = PEER_WAIT_S
    urgent_stream: bool = False
    """R1 also sends ``URGENT_STREAMS``, over zenoh priority links (the testbed's comparison)."""
    robots: int = len(ROBOTS)
    """The fleet's size: robots ``r1``..``rN`` with ``fleet_cameras`` and ``fleet_steps``."""
    config_file: str | None = None
    """A zenoh config file (the testbed's router topology: ``mode: "client"``)."""
    domain_id: int | None = None
    """The ROS 2 domain of the ``ros2`` and ``rclpy`` roles (None: ``ROS_DOMAIN_ID``)."""
    foxglove: str | None = None
    """The operator's live view: its Foxglove server's ``HOST:PORT`` (``--foxglove``)."""
    record: str | None = None
    """The operator's live view: its MCAP recording (``--record``)."""

    def to_json(self) -> str:
        """The spec as one JSON object (the role process's argument)."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> RoleSpec:
        """The spec ``to_json`` wrote."""
        document: dict[str, Any] = json.loads(text)
        document["listen"] = tuple(document.get("listen", ()))
        document["connect"] = tuple(document.get("connect", ()))
        return cls(**document)

    @property
    def duration_s(self) -> float:
        """All steps, from step 1's start."""
        return len(STEPS) * self.step_s


_ROBOT_ROLE = re.compile(r"r([1-9][0-9]*)")


def robot_index(role: str) -> int:
    """The camera of a robot role (``"r2"`` -> 1, ``"r8"`` -> 7)."""
    match = _ROBOT_ROLE.fullmatch(role)
    if match is None:
        raise ValueError(f"role={role!r} is not a robot (r1, r2, ...)")
    return int(match.group(1)) - 1


def fleet_phase_s(index: int, robots: int) -> float:
    """When robot ``index`` starts sending after step 1 starts: a fleet's robots spread.

    Robots are not clock-synchronised; started in one instant, a fleet's 1 Hz frames would
    leave together every second (8 robots: 420 KB, a 300 ms queue on 11 Mbit/s). The paper's
    two robots start together, as before.
    """
    return 0.0 if robots <= len(ROBOTS) else index / robots / MIN_RATE_HZ


def wait_until(wall_s: float, stop: threading.Event) -> bool:
    """Sleep until a wall-clock time; False if ``stop`` was set first."""
    return not stop.wait(max(0.0, wall_s - time.time()))


def _optimizer(transport: Transport, t0: float, spec: RoleSpec, stop: threading.Event) -> int:
    settings = DbmSettings(spec.link_mbit, spec.utilization, PERIOD_S, Strategy(spec.strategy))
    topics = {camera.robot: camera.topic for camera in fleet_cameras(spec.robots)}
    links = tuple(
        LinkSpec(f"uplink-{robot}", mbit, (topics[robot],))
        for robot, mbit in sorted(spec.uplinks_mbit.items())
    )
    return run_optimizer(
        transport,
        settings=settings,
        links=links,
        stop=stop,
        duration_s=t0 + spec.duration_s + TAIL_S - time.time(),
        estimate=spec.estimate,
    )


def _managed_robot(
    transport: Transport,
    index: int,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
) -> None:
    camera = fleet_cameras(spec.robots)[index]
    frame = camera_frame(transport, spec.transport, camera.topic, camera.size_bytes)  # types it
    publisher = ManagedPublisher(
        transport, camera.topic, min_rate_hz=MIN_RATE_HZ, max_rate_hz=MAX_RATE_HZ
    )
    priority = collision_priority_source(transport, camera.topic)
    # The robot's own end, not ``stop``: threads over the memory transport share ``stop``, and a
    # robot done with its last frame must not end the operator before its last report.
    finished = threading.Event()

    def replay_events() -> None:
        for k, step in enumerate(fleet_steps(spec.robots)):
            if not wait_until(t0 + k * spec.step_s, finished) or stop.is_set():
                return
            event = step.events[index]
            priority.update(event.distance_m, event.speed_m_per_s)

    events = BackgroundThread(replay_events, name=f"events-{camera.robot}", log=log)
    try:
        publisher.publish(frame)  # the first frame makes the size known before step 1
        events.start()
        wait_until(t0 + fleet_phase_s(index, spec.robots), stop)
        publisher.rate.reset()
        while not life.over() and time.time() < t0 + spec.duration_s:
            publisher.rate.sleep()
            publisher.publish(frame)
    finally:
        finished.set()
        events.join(2.0)
        publisher.close()


def _unmanaged_robot(
    transport: Transport,
    index: int,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
) -> None:
    """What a robot does without dbml: publish every frame at the camera's maximum rate."""
    camera = fleet_cameras(spec.robots)[index]
    frame = camera_frame(transport, spec.transport, camera.topic, camera.size_bytes)
    publisher = transport.declare_publisher(camera.topic, Variant.FULL)
    rate = Rate(lambda: MAX_RATE_HZ)
    seq = 0
    try:
        wait_until(t0, stop)
        rate.reset()
        while not life.over() and time.time() < t0 + spec.duration_s:
            rate.sleep()
            publisher.put(frame, attachment=pack_meta(seq, time.time_ns(), MAX_RATE_HZ))
            seq += 1
    finally:
        publisher.close()


def _urgent_streams(
    transport: Transport, t0: float, spec: RoleSpec, stop: threading.Event, *, life: Lifetime
) -> None:
    """Publish ``URGENT_STREAMS`` at ``URGENT_RATE_HZ``, both at one moment each tick."""
    payload = bytes(URGENT_SIZE_BYTES)
    publishers = [
        ManagedPublisher(
            transport,
            stream.topic,
            min_rate_hz=URGENT_RATE_HZ,
            max_rate_hz=URGENT_RATE_HZ,
            priority=URGENT_PRIORITY,
            map_transport_priority=stream.mapped,
        )
        for stream in URGENT_STREAMS
    ]
    try:
        for publisher in publishers:  # the size is known (and the class chosen) before step 1
            publisher.publish(payload)
        wait_until(t0, stop)
        pace = Rate(lambda: URGENT_RATE_HZ)
        while not life.over() and time.time() < t0 + spec.duration_s:
            pace.sleep()
            for publisher in publishers:
                publisher.publish(payload)
    finally:
        for publisher in publishers:
            publisher.close()


def operator_tick(
    view: ParamView,
    frames: Sequence[Arrival],
    variants: Sequence[str],
    *,
    cameras: Sequence[RobotCamera] = ROBOTS,
) -> OperatorReport:
    """The operator's report: ``frames`` that arrived and the parameters in force now.

    One function for every operator (dbml's own and the plain ROS 2 one of ``ros2peers``), so
    the runner and the analysis read one format; ``cameras`` are the fleet's, in robot order.
    """
    dbm = view.dbm()
    tick = Tick(
        t_s=time.time(),
        allocated_hz=tuple(view.channel(c.topic).current_rate_hz for c in cameras),
        budget_mbit=dbm.budget_mbit,
        estimate_mbit=dbm.estimate_mbit,
        estimator=_estimator_state(view.get(names.ESTIMATOR_STATE)),
        variants=tuple(variants),
    )
    return OperatorReport(tick, tuple(frames))


def _estimator_state(value: object) -> EstimatorState | None:
    """The estimator's state in force; None when none runs or a peer wrote a malformed one."""
    if not isinstance(value, str):
        return None
    try:
        return EstimatorState.decode(value)
    except SpecError as err:
        log.debug("%s", err)
        return None


def _operator(
    transport: Transport,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    emit: Emit,
    live: LiveView | None = None,
) -> None:
    lock = threading.Lock()
    rows: list[Arrival] = []
    cameras = fleet_cameras(spec.robots)

    def receiver(index: int) -> Callable[[Sample], None]:
        shown = cameras[index].topic if live is not None and index < len(cameras) else None

        def on_sample(sample: Sample) -> None:
            arrival_s = time.time()
            if shown is not None and live is not None:
                live.frame(shown, sample.payload)
            try:
                meta: MessageMeta | None = MessageMeta.decode(sample.attachment)
            except TransportError:
                meta = None  # no metadata (ROS 1 messages carry none)
            row = Arrival(
                robot=index,
                seq=None if meta is None else meta.seq,
                sent_s=None if meta is None else meta.sent_ns / 1e9,
                arrival_s=arrival_s,
                size_bytes=len(sample.payload),
                rate_hz=None if meta is None or math.isnan(meta.rate_hz) else meta.rate_hz,
            )
            with lock:
                rows.append(row)

        return on_sample

    view = ParamView.of(transport.params)
    reporter = ReceptionReporter(transport).start() if spec.estimate else None
    handles: list[Handle] = []
    subscribers: list[ManagedSubscriber] = []
    for i, camera in enumerate(cameras):
        if spec.managed:
            subscriber = ManagedSubscriber(transport, camera.topic, receiver(i), reporter=reporter)
            subscribers.append(subscriber)
            handles.append(subscriber)
        else:
            handles.append(transport.subscribe(camera.topic, receiver(i), Variant.FULL))

    if spec.urgent_stream:
        for k, stream in enumerate(URGENT_STREAMS):
            handles.append(ManagedSubscriber(transport, stream.topic, receiver(len(cameras) + k)))
    unmanaged = [Variant.FULL.value for _ in cameras]

    def tick() -> dict[str, Any]:
        with lock:
            batch, rows[:] = list(rows), []
        variants = [s.variant.value for s in subscribers] or unmanaged
        return operator_tick(view, batch, variants, cameras=cameras).encode()

    try:
        while not life.over() and time.time() < t0 + spec.duration_s + TAIL_S:
            stop.wait(TICK_S)
            emit(tick())
        if not life.failed:  # a run that lost a thread is not done: the runner fails it
            emit({"type": "done"})
    finally:
        for handle in handles:
            handle.close()
        if reporter is not None:
            reporter.close()


def run_role(
    role: str, transport: Transport, spec: RoleSpec, *, t0: float, stop: threading.Event, emit: Emit
) -> None:
    """Run ``role`` from ``t0`` (wall clock of step 1) to its end; reports go to ``emit``.

    ``DbmlError`` naming the role when a dbml thread of this process died during the run (said
    critical, with why, as it died): the role ends within a period of it, not at the last step.
    """
    life = Lifetime(stop, None)
    urgent: BackgroundThread | None = None
    if spec.urgent_stream and role == ROLES[2]:  # robot R1
        urgent = BackgroundThread(
            lambda: _urgent_streams(transport, t0, spec, stop, life=life), name="urgent", log=log
        ).start()
    try:
        code = _run_role(role, transport, spec, t0=t0, stop=stop, life=life, emit=emit)
    finally:
        if urgent is not None:
            urgent.join(_URGENT_JOIN_S)
    if code != 0 or life.exit_code() != 0:  # the optimizer said it already
        raise DbmlError(f"role {role}: a dbml thread died during the run (see above)")


def _run_role(
    role: str,
    transport: Transport,
    spec: RoleSpec,
    *,
    t0: float,
    stop: threading.Event,
    life: Lifetime,
    emit: Emit,
) -> int:
    """The role's run; its exit code (the optimizer's, which ends at a death of its own)."""
    if role == "operator":
        target = ViewTarget.from_flags(spec.foxglove, spec.record)
        live = None if target is None else open_view(transport, target, writers=_OPERATOR)
        try:
            _operator(transport, t0, spec, stop, life=life, emit=emit, live=live)
        finally:
            if live is not None:
                live.close()
    elif role == "optimizer":
        return _optimizer(transport, t0, spec, stop)
    elif spec.managed:
        _managed_robot(transport, robot_index(role), t0, spec, stop, life=life)
    else:
        _unmanaged_robot(transport, robot_index(role), t0, spec, stop, life=life)
    return 0


def _open(role: str, spec: RoleSpec) -> Transport:
    if spec.transport == "ros1":
        from dbml.transports.ros1 import Ros1Transport

        return Ros1Transport(node_name=f"dbml_{role}")
    return open_transport(
        spec.transport,
        host=spec.host,
        listen=spec.listen,
        connect=spec.connect,
        config_file=spec.config_file,
        domain_id=spec.domain_id,
        # Priority links: the urgent stream's class gets a connection of its own.
        priority_links=spec.transport == "zenoh" and spec.urgent_stream,
        follow_all_params=role in {"operator", "optimizer"},  # a robot only publishes
    )


def main(argv: list[str] | None = None) -> int:
    """One role as an OS process, driven over stdin and stdout by the experiment runner."""
    parser = argparse.ArgumentParser(prog="python -m dbml.experiment.roles")
    parser.add_argument("role", help=f"one of {', '.join(ROLES)} or a fleet's r3..rN")
    parser.add_argument("spec", help="the RoleSpec as JSON")
    args = parser.parse_args(argv)
    role, spec = args.role, RoleSpec.from_json(args.spec)
    fleet = {"operator", "optimizer", *(c.robot.lower() for c in fleet_cameras(spec.robots))}
    if role not in fleet:
        parser.error(f"role={role!r} is not one of {', '.join(sorted(fleet))}")
    with stop_on_signals() as stop:
        life = Lifetime(stop, None)  # the process's: a thread dead before the run counts too
        transport = _open(role, spec)
        # After the node starts: rospy replaces the root handlers with its own log file.
        logging.basicConfig(
            force=True, level=logging.WARNING, format=f"{role}: %(name)s: %(message)s"
        )
        try:
            transport.wait_for_peers(spec.peer_wait_s)
            serve_role(
                role,
                stop,
                lambda t0: run_role(role, transport, spec, t0=t0, stop=stop, emit=emit_json),
            )
        except DbmlError as err:  # a dead thread, or a malformed control line: said, exit 1
            sys.stderr.write(f"{role}: {err}\n")
            return 1
        finally:
            transport.close()
    return life.exit_code()


if __name__ == "__main__":
    sys.exit(main())
