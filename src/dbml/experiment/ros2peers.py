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

As a process (``python -m dbml.experiment ros2-peer ROLE SPEC_JSON``) a peer speaks the roles'
protocol (``harness.child.serve_role``) and meets the others at the zenoh router at
``spec.connect[0]``, as ROS 2 nodes do. The SDK keeps one session per process: one peer each.
As ``roles``' processes, a peer that loses a dbml thread (the camera driver, its transport's)
ends early, without ``done``, and exits 1.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable
from functools import cache
from typing import Any

import numpy as np

from dbml.core.errors import DbmlError
from dbml.core.extras import require
from dbml.experiment.peers import (
    FLOAT64_TYPE,
    IMAGE_TYPE,
    OPTIMIZED_SUFFIX,
    PRIORITY_SUFFIX,
    FrameRecorder,
    peer_roles,
    replay_priorities,
    report_ticks,
    run_paced,
    wait_first_frames,
)
from dbml.experiment.spec import RoleSpec, robot_index
from dbml.harness.child import Emit, emit_json, serve_role
from dbml.runtime.params import ParamView
from dbml.runtime.serve import Lifetime
from dbml.scenarios.teleop import MAX_RATE_HZ, ROBOTS
from dbml.transports.registry import open_transport
from dbml.transports.worker import BackgroundThread

__all__ = [
    "DEFINITIONS",
    "IMAGE_OVERHEAD_BYTES",
    "SDK_MISSING",
    "SdkSession",
    "image_fields",
    "router_address",
    "serve",
    "type_hash",
]

log = logging.getLogger("dbml.experiment.ros2peers")

SDK_MISSING = (
    "--transport ros2 runs its robots and operator as plain ROS 2 nodes with zenoh-ros2-sdk, "
    f"which {sys.executable} cannot import: pip install 'dbml[ros2]'"
)
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
FRAME_ID = "camera"
ENCODING = "mono8"
IMAGE_OVERHEAD_BYTES = 52
"""Serialised ``Image`` bytes besides its data (frame_id "camera", mono8, CDR header)."""
_NS_PER_S = 1_000_000_000
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


def _publish_frames(publisher: Any, types: Any, size_bytes: int, stop: threading.Event) -> None:
    """A camera driver: one frame every ``1 / MAX_RATE_HZ`` s until ``stop``."""
    data = np.zeros(size_bytes - IMAGE_OVERHEAD_BYTES, dtype=np.uint8)
    run_paced(
        lambda: publisher.publish(**image_fields(types, size_bytes, time.time_ns(), data)),
        rate_hz=MAX_RATE_HZ,
        stop=stop,
    )


def _serve_camera(
    role: str, spec: RoleSpec, stop: threading.Event, *, lines: Iterable[str] | None
) -> int:
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
            lines=lines,
        )
    finally:
        camera_stop.set()
        if driver is not None:
            driver.join(_DRIVER_JOIN_S)
        for publisher in publishers:
            publisher.close()
        sdk.close()
    return life.exit_code()


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


def _serve_operator(
    spec: RoleSpec, stop: threading.Event, *, lines: Iterable[str] | None, emit: Emit
) -> int:
    """The operator peer's run; 1 when a dbml thread (its transport's) died meanwhile, else 0."""
    life = Lifetime(stop, None)
    sdk = SdkSession(spec.connect[0])
    recorder = FrameRecorder()
    topics = [camera.topic + OPTIMIZED_SUFFIX for camera in ROBOTS]
    subscribers: list[Any] = []
    try:
        transport = open_transport(
            spec.transport.name,
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
            "operator",
            stop,
            lambda t0: report_ticks(view, recorder, t0, spec, stop, life=life, emit=emit),
            lines=lines,
            emit=emit,
        )
    finally:
        for subscriber in subscribers:
            subscriber.close()
        transport.close()
        sdk.close()
    return life.exit_code()


def serve(
    role: str,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    lines: Iterable[str] | None = None,
    emit: Emit = emit_json,
) -> int:
    """One plain ROS 2 peer, from its session's opening to its end: its exit code."""
    if role not in peer_roles():
        raise DbmlError(f"role={role!r} is not one of {', '.join(peer_roles())}")
    if not spec.connect:
        raise DbmlError("spec.connect=(): the ROS 2 peers need the router's endpoint")
    if role == "operator":
        return _serve_operator(spec, stop, lines=lines, emit=emit)
    return _serve_camera(role, spec, stop, lines=lines)
