"""The roles of the teleoperation experiment: one set for the demo and the testbed.

- ``optimizer``: the optimizer node with the scenario's budget (the testbed's links and
  estimator when asked for).
- ``r1``/``r2``: a robot publishing its camera's frames. Managed, through a publisher whose
  priority follows Table 2's replayed events (eq. 6-7); unmanaged (the testbed's baseline), a
  plain publisher at the camera's maximum rate, as without dbml.
- ``operator``: receives both cameras (managed subscribers, or plain ones when unmanaged) and
  reports what arrived and the parameters in force (``operator``); the runner analyses them.

:func:`serve` is a role's whole life: open its transport, wait for its peers, speak the
supervisor's protocol (``harness.child.serve_role``: ``ready``, ``start <t0>``, reports, the end
at the last step, on ``stop``, EOF, SIGINT or SIGTERM). A role process runs it
(``python -m dbml.experiment role ROLE SPEC_JSON``); over the memory transport the runner runs
it on a thread, on the run's memory network.

A role that loses a dbml thread meanwhile (its own, a node's, the transport's) would go on
reporting a run that is not the one measured: it ends early, without ``done``, and its process
exits 1, so the runner fails the run naming it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable

from dbml.core.config import DbmSettings
from dbml.core.errors import SpecError
from dbml.core.ladder import Preference
from dbml.core.spec import LinkSpec
from dbml.experiment.operator import run_operator
from dbml.experiment.spec import (
    LADDER_MIN_QUALITY,
    PERIOD_S,
    ROLES,
    TAIL_S,
    URGENT_PRIORITY,
    URGENT_RATE_HZ,
    URGENT_SIZE_BYTES,
    URGENT_STREAMS,
    Frames,
    RoleSpec,
    fleet_phase_s,
    robot_index,
    wait_until,
)
from dbml.harness.child import Emit, RoleError, emit_json, serve_role
from dbml.protocol import names
from dbml.protocol.metadata import pack_meta
from dbml.protocol.schema import Writer
from dbml.runtime.priority import collision_priority_source
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.rate import Rate
from dbml.runtime.serve import Lifetime, run_optimizer
from dbml.scenarios.fleet import fleet_cameras, fleet_steps
from dbml.scenarios.teleop import MAX_RATE_HZ, MIN_RATE_HZ, ROBOTS, RobotEvent
from dbml.transports.base import Transport, Variant
from dbml.transports.memory import MemoryNetwork
from dbml.transports.registry import open_transport
from dbml.transports.worker import BackgroundThread
from dbml.view.live import open_view
from dbml.view.target import ViewTarget

__all__ = ["fleet_roles", "run_role", "serve"]

log = logging.getLogger("dbml.experiment")

_OPERATOR = frozenset({Writer.OPERATOR})
"""The operator's view sets what an operator writes: the budget and priorities."""
_PAN_OFFSET_PX = 800
"""How far apart the robots' cameras start on the panorama (so they see different photographs)."""
_URGENT_JOIN_S = 5.0
"""How long robot R1 waits for its urgent streams' last tick (a send in progress)."""


def fleet_roles(robots: int) -> tuple[str, ...]:
    """Every role of a fleet of ``robots``: the operator, the optimizer, ``r1``..``rN``."""
    return ("operator", "optimizer", *(c.robot.lower() for c in fleet_cameras(robots)))


def _optimizer(transport: Transport, t0: float, spec: RoleSpec, stop: threading.Event) -> int:
    settings = DbmSettings(spec.link_mbit, spec.utilization, PERIOD_S, spec.strategy)
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
        design=spec.estimator_design,
    )


def _drive(
    robot: str,
    index: int,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    rate: Rate,
    send: Callable[[], object],
    on_event: Callable[[RobotEvent], object],
) -> None:
    """A managed robot's run: its events replayed step by step, ``send()`` at every tick.

    The first ``send`` goes before step 1 (the size, and a camera's ladder, known by then).
    """
    # The robot's own end, not ``stop``: threads over the memory transport share ``stop``, and a
    # robot done with its last frame must not end the operator before its last report.
    finished = threading.Event()

    def replay_events() -> None:
        for k, step in enumerate(fleet_steps(spec.robots)):
            if not wait_until(t0 + k * spec.step_s, finished) or stop.is_set():
                return
            on_event(step.events[index])

    events = BackgroundThread(replay_events, name=f"events-{robot}", log=log)
    try:
        send()
        events.start()
        wait_until(t0 + fleet_phase_s(index, spec.robots), stop)
        rate.reset()
        while not life.over() and time.time() < t0 + spec.duration_s:
            rate.sleep()
            send()
    finally:
        finished.set()
        events.join(2.0)


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
    frame = spec.transport.camera_frame(transport, camera.topic, camera.size_bytes)  # types it
    publisher = ManagedPublisher(
        transport, camera.topic, min_rate_hz=MIN_RATE_HZ, max_rate_hz=MAX_RATE_HZ
    )
    priority = collision_priority_source(transport, camera.topic)
    try:
        _drive(
            camera.robot,
            index,
            t0,
            spec,
            stop,
            life=life,
            rate=publisher.rate,
            send=lambda: publisher.publish(frame),
            on_event=lambda e: priority.update(e.distance_m, e.speed_m_per_s),
        )
    finally:
        publisher.close()


def _camera_robot(
    transport: Transport,
    index: int,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
) -> None:
    """A robot whose camera sends real frames: a camera moving over photographs, as JPEG.

    Its ladder is on or off (``spec.ladder``); without it the frames go at the one quality
    whose frames are the paper's 84,000 B (the rate-only baseline). An event that raises its
    priority also asks to keep its frame rate (the robot near an obstacle): detail goes first.
    """
    from dbml.media.images import IMAGE_TYPE, Frame  # the quality extra's, imported on use
    from dbml.media.photos import PanCamera, position_frame_id, quality_for_size
    from dbml.runtime.camera import ManagedCamera

    camera = fleet_cameras(spec.robots)[index]
    if spec.transport.frame.msg_type is not None:  # a typed middleware: [topic] is an Image
        transport.set_topic_type(camera.topic, IMAGE_TYPE)
    # Across the panorama once in the run: the scene the run sees averages what the rate-only
    # quality was chosen on (the paper's 84,000 B a frame at 640x480).
    travel_px = PanCamera().travel_px
    eye = PanCamera(
        camera.width,
        camera.height,
        offset_px=_PAN_OFFSET_PX * index,
        speed_px_per_s=travel_px / spec.duration_s,
    )
    quality = quality_for_size(ROBOTS[0].size_bytes)
    publisher = ManagedCamera(
        transport,
        camera.topic,
        min_rate_hz=MIN_RATE_HZ,
        max_rate_hz=MAX_RATE_HZ,
        ladder=spec.ladder,
        min_quality=LADDER_MIN_QUALITY if spec.ladder else None,
        default_encoding=(1.0, quality),
    )
    priority = collision_priority_source(transport, camera.topic)
    preference: list[Preference] = []

    def on_event(event: RobotEvent) -> None:
        priority.update(event.distance_m, event.speed_m_per_s)
        wanted = Preference.KEEP_RATE if event.priority > 0 else Preference.BALANCED
        if preference[-1:] != [wanted]:
            transport.params.set(names.preference(camera.topic), wanted.value)
            preference.append(wanted)

    def capture() -> bool:
        x = eye.at(time.time() - t0)
        return publisher.publish_frame(
            Frame(eye.window(x), "rgb8", time.time_ns(), position_frame_id(x))
        )

    try:
        _drive(
            camera.robot,
            index,
            t0,
            spec,
            stop,
            life=life,
            rate=publisher.rate,
            send=capture,
            on_event=on_event,
        )
    finally:
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
    frame = spec.transport.camera_frame(transport, camera.topic, camera.size_bytes)
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


def run_role(
    role: str, transport: Transport, spec: RoleSpec, *, t0: float, stop: threading.Event, emit: Emit
) -> None:
    """Run ``role`` from ``t0`` (wall clock of step 1) to its end; reports go to ``emit``.

    ``RoleError`` naming the role when a dbml thread of this process died during the run (said
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
        raise RoleError(f"role {role}: a dbml thread died during the run (see above)")


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
            run_operator(transport, t0, spec, stop, life=life, emit=emit, live=live)
        finally:
            if live is not None:
                live.close()
    elif role == "optimizer":
        return _optimizer(transport, t0, spec, stop)
    elif spec.managed and spec.frames is Frames.PHOTOS:
        _camera_robot(transport, robot_index(role), t0, spec, stop, life=life)
    elif spec.managed:
        _managed_robot(transport, robot_index(role), t0, spec, stop, life=life)
    else:
        _unmanaged_robot(transport, robot_index(role), t0, spec, stop, life=life)
    return 0


def _open(role: str, spec: RoleSpec, network: MemoryNetwork | None) -> Transport:
    return open_transport(
        spec.transport.name,
        host=spec.host,
        listen=spec.listen,
        connect=spec.connect,
        config_file=spec.config_file,
        network=network,
        domain_id=spec.domain_id,
        priority_links=spec.priority_links,  # the urgent stream's class: a connection of its own
        follow_all_params=role in {"operator", "optimizer"},  # a robot only publishes
    )


def serve(
    role: str,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    lines: Iterable[str] | None = None,
    emit: Emit = emit_json,
    network: MemoryNetwork | None = None,
) -> int:
    """Role ``role`` from its transport's opening to its end: its exit code.

    ``lines`` and ``emit``: its control lines and reports (stdin and stdout by default);
    ``network``: the run's memory network, for roles run as threads. ``RoleError`` when its run
    failed (a dbml thread died, its control failed): the process exits 1.
    """
    fleet = fleet_roles(spec.robots)
    if role not in fleet:
        raise SpecError(f"role={role!r} is not one of {', '.join(sorted(fleet))}")
    life = Lifetime(stop, None)  # the process's: a thread dead before the run counts too
    transport = _open(role, spec, network)
    try:
        if network is None:  # a process of its own, its node started: rospy replaced the handlers
            logging.basicConfig(
                force=True, level=logging.WARNING, format=f"{role}: %(name)s: %(message)s"
            )
        transport.wait_for_peers(spec.peer_wait_s)
        serve_role(
            role,
            stop,
            lambda t0: run_role(role, transport, spec, t0=t0, stop=stop, emit=emit),
            lines=lines,
            emit=emit,
        )
    finally:
        transport.close()
    return life.exit_code()
