"""Plain ROS 2 peers of the teleoperation demo: the robots' cameras and the operator, no dbml.

``dbml demo teleop --transport ros2`` shows that dbml manages ROS 2 topics whose publishers and
subscribers know nothing about it: ``dbml bridge`` puts each camera under management and the
optimizer allocates over rmw_zenoh's wire format. The peers here are therefore written against
``zenoh-ros2-sdk``, an independent pure-Python implementation of that format (keys, CDR,
attachments, liveliness tokens), and not against dbml's ``ros2`` transport: two implementations
sharing code would agree with each other on a shared mistake; two independent ones agreeing is
the evidence of interoperability.

- ``r1``/``r2``: a camera driver publishing ``sensor_msgs/msg/Image`` on ``/rN/camera`` at the
  camera's maximum rate (84,000 / 21,000 bytes serialised, ``header.stamp`` = send time), and
  the channel's priority the ROS 2 way: ``std_msgs/msg/Float64`` on ``/rN/camera/dbm/priority``,
  eq. 6-7 of Table 2's replayed events, republished every second so a late bridge hears it.
- ``operator``: a ROS 2 subscription of each ``/rN/camera/optimized`` (where the bridges
  republish), recording each frame's arrival and send time, size and a per-topic count; and,
  through a dbml session, the parameters in force, reported each tick in the format of
  ``roles``' operator, so the same runner and analysis judge the run.

As a process (``python -m dbml.experiment.ros2peers ROLE SPEC_JSON``) a peer speaks the roles'
protocol (``harness.processes.serve_role``) and meets the others at the zenoh router at
``spec.connect[0]``, as ROS 2 nodes do. The SDK keeps one session per process: one peer each.
As ``roles``' processes, a peer that loses a dbml thread (the camera driver, its transport's)
ends early, without ``done``, and exits 1.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from functools import cache
from typing import Any

import numpy as np

from dbml.core.errors import DbmlError
from dbml.core.extras import require
from dbml.core.priority import collision_priority, time_to_collision_s
from dbml.experiment.analysis import Arrival
from dbml.experiment.roles import TAIL_S, TICK_S, RoleSpec, operator_tick, robot_index, wait_until
from dbml.harness.processes import emit_json, serve_role, stop_on_signals
from dbml.runtime.params import ParamView
from dbml.runtime.serve import Lifetime
from dbml.scenarios.teleop import MAX_RATE_HZ, ROBOTS, STEPS, RobotCamera, Step
from dbml.transports.base import PRIORITY_SUFFIX, Variant
from dbml.transports.registry import open_transport
from dbml.transports.worker import BackgroundThread

__all__ = [
    "DEFINITIONS",
    "FIRST_FRAMES_TIMEOUT_S",
    "FLOAT64_TYPE",
    "IMAGE_OVERHEAD_BYTES",
    "IMAGE_TYPE",
    "OPTIMIZED_SUFFIX",
    "PRIORITY_REPEAT_S",
    "PRIORITY_SUFFIX",
    "ROLES",
    "SDK_MISSING",
    "FrameRecorder",
    "SdkSession",
    "image_fields",
    "main",
    "replay_priorities",
    "report_ticks",
    "router_address",
    "run_paced",
    "step_priority",
    "type_hash",
    "wait_first_frames",
]

log = logging.getLogger("dbml.experiment.ros2peers")

ROLES = ("operator", *(camera.robot.lower() for camera in ROBOTS))
"""The roles played by plain ROS 2 peers (the optimizer stays ``roles``' own)."""
SDK_MISSING = (
    "--transport ros2 runs its robots and operator as plain ROS 2 nodes with zenoh-ros2-sdk, "
    f"which {sys.executable} cannot import: pip install 'dbml[ros2]'"
)
IMAGE_TYPE = "sensor_msgs/msg/Image"
FLOAT64_TYPE = "std_msgs/msg/Float64"
DEFINITIONS: tuple[tuple[str, str], ...] = (
    ("builtin_interfaces/msg/Time", "int32 sec\nuint32 nanosec\n"),
    ("std_msgs/msg/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"),
    (
        IMAGE_TYPE,
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n",
    ),
    (FLOAT64_TYPE, "float64 data\n"),
)
"""Each type's ``.msg`` text, dependencies first: offline, the SDK cannot fetch them itself."""
HASH_STORE = "ros2_jazzy"
"""Where the RIHS01 hashes come from (the SDK computes wrong ones for nested types offline)."""
OPTIMIZED_SUFFIX = Variant.OPTIMIZED.key("")
"""A managed topic's copy at the allocated rate: what a ROS 2 operator subscribes to."""
FRAME_ID = "camera"
ENCODING = "mono8"
IMAGE_OVERHEAD_BYTES = 52
"""Serialised ``Image`` bytes besides its data (frame_id "camera", mono8, CDR header)."""
PRIORITY_REPEAT_S = 1.0
"""Each priority is published again this often: a ROS 2 topic keeps no value for latecomers."""
FIRST_FRAMES_TIMEOUT_S = 50.0
"""How long the operator waits for a frame of every managed camera before it reports ready
(the runner waits 60 s for every role)."""
_NS_PER_S = 1_000_000_000
_FIRST_FRAMES_POLL_S = 0.05
_SHM_OFF = "transport/shared_memory/enabled=false"
_OVERRIDE_ENV = "ZENOH_CONFIG_OVERRIDE"
_DRIVER_JOIN_S = 5.0
"""How long a camera waits for its driver's frame in progress when it ends."""


def router_address(endpoint: str) -> tuple[str, int]:
    """The SDK's ``router_ip``/``router_port`` of a zenoh endpoint ``tcp/HOST:PORT``.

    The SDK connects over TCP only, so any other protocol is refused here, naming the value.
    """
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if protocol != "tcp" or not host or not port.isdigit() or not 0 < int(port) < 2**16:
        raise DbmlError(f"endpoint={endpoint!r}: the ROS 2 peers need tcp/HOST:PORT")
    return host, int(port)


@cache
def type_hash(msg_type: str) -> str:
    """``msg_type``'s RIHS01 hash, as rmw_zenoh puts it in its keys."""
    require("rosbags", extra="ros2", what="a plain ROS 2 peer")
    from rosbags.typesys import Stores, get_typestore

    value: str = get_typestore(Stores(HASH_STORE)).hash_rihs01(msg_type)
    return value


def step_priority(step: Step, index: int) -> float:
    """Robot ``index``'s camera priority in ``step``: eq. 6-7 of its distance and speed.

    The same pure functions as the managed robot's ``collision_priority_source``, published on
    a ROS 2 topic instead of written as a parameter.
    """
    event = step.events[index]
    return collision_priority(time_to_collision_s(event.distance_m, event.speed_m_per_s))


def image_fields(types: Any, size_bytes: int, stamp_ns: int, data: Any = None) -> dict[str, Any]:
    """An ``Image`` of ``size_bytes`` serialised, stamped ``stamp_ns``: ``publish(**fields)``.

    ``types`` maps type names to classes (a rosbags typestore's ``types``); ``data``, when
    given, is reused (``size_bytes - IMAGE_OVERHEAD_BYTES`` zero bytes).
    """
    width = size_bytes - IMAGE_OVERHEAD_BYTES
    if width < 0:
        raise DbmlError(
            f"size_bytes={size_bytes!r}: an Image takes {IMAGE_OVERHEAD_BYTES} at least"
        )
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](
            sec=stamp_ns // _NS_PER_S, nanosec=stamp_ns % _NS_PER_S
        ),
        frame_id=FRAME_ID,
    )
    return {
        "header": header,
        "height": 1,
        "width": width,
        "encoding": ENCODING,
        "is_bigendian": 0,
        "step": width,
        "data": np.zeros(width, dtype=np.uint8) if data is None else data,
    }


class SdkSession:
    """This process's SDK session at the router ``endpoint``, with the peers' types registered.

    Shared memory is off (as rmw_zenoh's default). Close it once, at the process's end: the SDK
    keeps it as a per-process singleton.
    """

    def __init__(self, endpoint: str) -> None:
        self.router_ip, self.router_port = router_address(endpoint)
        override = os.environ.get(_OVERRIDE_ENV, "")
        os.environ[_OVERRIDE_ENV] = f"{override};{_SHM_OFF}" if override else _SHM_OFF
        what, package = "a plain ROS 2 peer", "zenoh-ros2-sdk"
        sdk = require("zenoh_ros2_sdk", extra="ros2", what=what, package=package)
        session = require("zenoh_ros2_sdk.session", extra="ros2", what=what, package=package)
        self._sdk = sdk
        self._session: Any = session.ZenohSession.get_instance(self.router_ip, self.router_port)
        for msg_type, definition in DEFINITIONS:
            self._session.register_message_type(definition, msg_type)

    @property
    def store(self) -> Any:
        """The SDK's rosbags typestore (its ``types`` and ``serialize_cdr``)."""
        return self._session.store

    def _options(self, msg_type: str, node_name: str) -> dict[str, Any]:
        return {
            "msg_type": msg_type,
            "msg_definition": dict(DEFINITIONS)[msg_type],
            "type_hash": type_hash(msg_type),
            "node_name": node_name,
            "router_ip": self.router_ip,
            "router_port": self.router_port,
        }

    def publisher(self, topic: str, msg_type: str, *, node_name: str) -> Any:
        """A ROS 2 publisher (``publish(**fields)``, ``close()``)."""
        return self._sdk.ROS2Publisher(topic=topic, **self._options(msg_type, node_name))

    def subscriber(
        self, topic: str, msg_type: str, callback: Callable[[Any], None], *, node_name: str
    ) -> Any:
        """A ROS 2 subscription calling ``callback(message)`` (``close()``)."""
        return self._sdk.ROS2Subscriber(
            topic=topic, callback=callback, **self._options(msg_type, node_name)
        )

    def close(self) -> None:
        """Close the process's session (its tokens go with it)."""
        self._session.close()


def run_paced(send: Callable[[], None], *, rate_hz: float, stop: threading.Event) -> None:
    """``send()`` every ``1 / rate_hz`` s until ``stop``, as a camera driver: never a burst.

    Paced on an absolute schedule (no drift); a send late by more than a period is not caught up.
    """
    period_s = 1.0 / rate_hz
    next_s = time.monotonic()
    while not stop.is_set():
        send()
        next_s += period_s
        now = time.monotonic()
        next_s = max(next_s, now - period_s)  # late by more than a frame: do not catch up
        stop.wait(max(0.0, next_s - now))


def _publish_frames(publisher: Any, types: Any, size_bytes: int, stop: threading.Event) -> None:
    """A camera driver: one frame every ``1 / MAX_RATE_HZ`` s until ``stop``."""
    data = np.zeros(size_bytes - IMAGE_OVERHEAD_BYTES, dtype=np.uint8)
    run_paced(
        lambda: publisher.publish(**image_fields(types, size_bytes, time.time_ns(), data)),
        rate_hz=MAX_RATE_HZ,
        stop=stop,
    )


def replay_priorities(
    send: Callable[[float], None],
    index: int,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    steps: Sequence[Step] = STEPS,
) -> None:
    """``send`` the priority of each step from its start, again every ``PRIORITY_REPEAT_S``.

    Robot ``index``'s of ``steps`` (Table 2's, or a fleet's: ``fleet_steps``), until the last
    step, ``stop``, or a dbml thread's death (``life``).
    """
    if not wait_until(t0, stop):
        return
    while not life.over():
        now = time.time()
        k = int((now - t0) // spec.step_s)
        if k >= len(steps):
            return
        send(step_priority(steps[k], index))
        if not wait_until(min(t0 + (k + 1) * spec.step_s, now + PRIORITY_REPEAT_S), stop):
            return


def _serve_camera(role: str, spec: RoleSpec, stop: threading.Event) -> int:
    """A camera peer's run; 1 when a dbml thread (its driver's) died meanwhile, else 0."""
    index = robot_index(role)
    camera = ROBOTS[index]
    sdk = SdkSession(spec.connect[0])
    publishers: list[Any] = []
    driver: BackgroundThread | None = None
    camera_stop = threading.Event()
    life = Lifetime(stop, None)
    try:
        frames = sdk.publisher(camera.topic, IMAGE_TYPE, node_name=f"{role}_camera")
        publishers.append(frames)
        priority = sdk.publisher(
            camera.topic + PRIORITY_SUFFIX, FLOAT64_TYPE, node_name=f"{role}_collision"
        )
        publishers.append(priority)
        types, size_bytes = sdk.store.types, camera.size_bytes
        driver = BackgroundThread(
            lambda: _publish_frames(frames, types, size_bytes, camera_stop),
            name=f"camera-{role}",
            log=log,
        )
        driver.start()  # from the start, as a camera driver: the bridge waits for a frame
        serve_role(
            role,
            stop,
            lambda t0: replay_priorities(
                lambda value: priority.publish(data=value), index, t0, spec, stop, life=life
            ),
        )
    finally:
        camera_stop.set()
        if driver is not None:
            driver.join(_DRIVER_JOIN_S)
        for publisher in publishers:
            publisher.close()
        sdk.close()
    return life.exit_code()


class FrameRecorder:
    """An operator's record of each frame: robot, count, send and arrival time, size.

    Fed from subscription callbacks (any thread), read by the tick loop.
    """

    def __init__(self, robots: int = len(ROBOTS)) -> None:
        self._lock = threading.Lock()
        self._rows: list[Arrival] = []
        self._counts = [0 for _ in range(robots)]

    def record(
        self,
        index: int,
        *,
        arrival_s: float,
        sent_s: float | None,
        size_bytes: int,
        seq: int | None = None,
        rate_hz: float | None = None,
    ) -> None:
        """One frame of robot ``index``.

        ``seq`` None: the per-topic count from 0. ``rate_hz``: the rate the frame says it was
        sent at, None for a plain ROS 2 message of a managed channel (it carries none).
        """
        with self._lock:
            count = self._counts[index]
            self._counts[index] += 1
            self._rows.append(
                Arrival(
                    robot=index,
                    seq=count if seq is None else seq,
                    sent_s=sent_s,
                    arrival_s=arrival_s,
                    size_bytes=size_bytes,
                    rate_hz=rate_hz,
                )
            )

    def counts(self) -> list[int]:
        """Frames received so far, per robot."""
        with self._lock:
            return list(self._counts)

    def take(self) -> list[Arrival]:
        """The frames since the last call."""
        with self._lock:
            rows, self._rows = self._rows, []
        return rows


def wait_first_frames(
    recorder: FrameRecorder, topics: Sequence[str], stop: threading.Event
) -> None:
    """Return once every topic delivered a frame; raise naming those that did not."""
    deadline = time.monotonic() + FIRST_FRAMES_TIMEOUT_S
    while not all(recorder.counts()) and time.monotonic() < deadline and not stop.is_set():
        stop.wait(_FIRST_FRAMES_POLL_S)
    missing = [t for t, n in zip(topics, recorder.counts(), strict=True) if n == 0]
    if missing and not stop.is_set():
        raise DbmlError(
            f"operator: no frame on {', '.join(missing)} within {FIRST_FRAMES_TIMEOUT_S:g} s "
            "(are the bridges and the robots running?)"
        )


def report_ticks(
    view: ParamView,
    recorder: FrameRecorder,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    cameras: Sequence[RobotCamera] = ROBOTS,
    variant: Variant = Variant.OPTIMIZED,
) -> None:
    """The operator's run: a report every ``TICK_S`` in ``roles``' format, then ``done``.

    Every subscription is of ``variant`` of each of ``cameras`` (by default the optimized copy
    of Table 2's); a run that lost a thread is not done (the runner fails it).
    """
    variants = [variant.value for _ in cameras]
    while not life.over() and time.time() < t0 + spec.duration_s + TAIL_S:
        stop.wait(TICK_S)
        emit_json(operator_tick(view, recorder.take(), variants, cameras=cameras).encode())
    if not life.failed:
        emit_json({"type": "done"})


def _sdk_image_callback(recorder: FrameRecorder, store: Any, index: int) -> Callable[[Any], None]:
    """The SDK subscription callback of robot ``index``'s optimized topic."""

    def record(message: Any) -> None:
        arrival_s = time.time()
        stamp = message.header.stamp
        recorder.record(
            index,
            arrival_s=arrival_s,
            sent_s=stamp.sec + stamp.nanosec / _NS_PER_S,
            size_bytes=len(store.serialize_cdr(message, IMAGE_TYPE)),
        )

    return record


def _serve_operator(spec: RoleSpec, stop: threading.Event) -> int:
    """The operator peer's run; 1 when a dbml thread (its transport's) died meanwhile, else 0."""
    life = Lifetime(stop, None)
    sdk = SdkSession(spec.connect[0])
    recorder = FrameRecorder()
    topics = [camera.topic + OPTIMIZED_SUFFIX for camera in ROBOTS]
    subscribers: list[Any] = []
    try:
        transport = open_transport(
            spec.transport,
            host=spec.host,
            listen=spec.listen,
            connect=spec.connect,
            follow_all_params=True,  # it reports every channel's allocation
        )
    except BaseException:
        sdk.close()
        raise
    view = ParamView.of(transport.params)
    try:
        for i, topic in enumerate(topics):
            subscribers.append(
                sdk.subscriber(
                    topic,
                    IMAGE_TYPE,
                    _sdk_image_callback(recorder, sdk.store, i),
                    node_name=f"operator_{ROBOTS[i].robot.lower()}",
                )
            )
        transport.wait_for_peers(spec.peer_wait_s)
        wait_first_frames(recorder, topics, stop)
        serve_role(
            "operator", stop, lambda t0: report_ticks(view, recorder, t0, spec, stop, life=life)
        )
    finally:
        for subscriber in subscribers:
            subscriber.close()
        transport.close()
        sdk.close()
    return life.exit_code()


def main(argv: list[str] | None = None) -> int:
    """One plain ROS 2 peer as an OS process, driven over stdin and stdout by the runner."""
    parser = argparse.ArgumentParser(prog="python -m dbml.experiment.ros2peers")
    parser.add_argument("role", choices=ROLES)
    parser.add_argument("spec", help="the RoleSpec as JSON (connect[0]: the zenoh router)")
    args = parser.parse_args(argv)
    role, spec = args.role, RoleSpec.from_json(args.spec)
    logging.basicConfig(level=logging.WARNING, format=f"{role}: %(name)s: %(message)s")
    if not spec.connect:
        sys.stderr.write(f"{role}: spec.connect=(): the ROS 2 peers need the router's endpoint\n")
        return 2
    try:
        with stop_on_signals() as stop:
            if role == "operator":
                return _serve_operator(spec, stop)
            return _serve_camera(role, spec, stop)
    except DbmlError as err:
        sys.stderr.write(f"{role}: {err}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())
