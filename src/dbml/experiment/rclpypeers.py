"""Plain rclpy peers of the teleoperation demo: the robots' cameras and the operator, no dbml.

``dbml demo teleop --transport rclpy`` shows that dbml manages real ROS 2 topics (rclpy on Fast
DDS) whose publishers and subscribers know nothing about it: ``dbml bridge`` puts each camera
under management and the optimizer allocates. The peers here are what a ROS 2 user writes, the
twins of ``ros2peers`` (which does the same job over rmw_zenoh's wire format):

- ``r1``/``r2``: a camera driver node publishing ``sensor_msgs/msg/Image`` on ``/rN/camera`` at
  the camera's maximum rate, RELIABLE keep-last like a typical driver, each frame serialising to
  exactly the camera's size with ``header.stamp`` = send time; and a node publishing the
  channel's priority the ROS 2 way, ``std_msgs/msg/Float64`` on ``/rN/camera/dbm/priority``:
  Table 2's value of each step, again every ``PRIORITY_REPEAT_S`` (``ros2peers``' schedule).
- ``operator``: raw best-effort subscriptions of each ``/rN/camera/optimized`` (best effort
  matches a reliable publisher as well as a best-effort one), recording each frame's arrival
  and send time (``header.stamp``, read from the CDR), size and a per-topic count; and, through
  dbml's ``rclpy`` transport, the parameters in force, reported each tick in ``roles``' format,
  so the same runner and analysis judge the run. Unmanaged (``spec.managed`` False: the
  testbed's baseline, no bridge) it subscribes the full ``/rN/camera`` instead, and each frame
  says the camera's own rate. With ``--sample-info`` (the testbed) a frame's sequence number
  and send time are DDS's own, from the sample info rclpy hands a two-argument callback: the
  writer's sequence number (so gaps are losses on the link) and its source timestamp (the
  bridge's send, as zenoh's metadata says the managed publisher's). With ``spec.estimate`` its
  dbml transport also reports what arrived to the estimator (``ReceptionReporter``), each
  frame with dbml's metadata made of that sample info (``sample_meta`` of
  ``dbml.transports.rclpy.transport``): rclpy alone gives the plain node everything the
  estimator needs; dbml only carries it.

Robots ``r3``..``rN`` of a fleet (``spec.robots``, ``dbml.scenarios.fleet``) are cameras too,
with the fleet's sizes and rotating events.

As a process (``python -m dbml.experiment rclpy-peer ROLE SPEC_JSON [--sample-info]``) a peer
speaks the roles' protocol (``harness.child.serve_role``) in ROS 2 domain
``spec.domain_id`` (else ``ROS_DOMAIN_ID``). Each peer has a private context (signals stay
the program's: ``harness.ros2node.PrivateRos``), an executor spinning on a thread that reports
its death, and shuts both down at its end (no ``/dev/shm/fastdds_*`` left). A peer that loses a
thread ends early, without ``done``, and exits 1. rclpy is imported when a peer runs, so the
demo can name this module without it.
"""

from __future__ import annotations

import logging
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from dbml.core.errors import DbmlError, TransportError
from dbml.experiment.peers import (
    OPTIMIZED_SUFFIX,
    PRIORITY_SUFFIX,
    FrameRecorder,
    replay_priorities,
    report_ticks,
    run_paced,
    wait_first_frames,
)
from dbml.experiment.spec import RoleSpec, robot_index
from dbml.harness.child import Emit, emit_json, serve_role
from dbml.protocol.metadata import MessageMeta
from dbml.runtime.params import ParamView
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.serve import Lifetime
from dbml.scenarios.fleet import fleet_cameras, fleet_steps
from dbml.scenarios.teleop import MAX_RATE_HZ, RobotCamera
from dbml.transports.base import Sample, Variant
from dbml.transports.registry import open_transport
from dbml.transports.worker import BackgroundThread

if TYPE_CHECKING:
    from dbml.harness.ros2node import PrivateRos

__all__ = [
    "DRIVER_DEPTH",
    "RCLPY_MISSING",
    "SUBSCRIPTION_DEPTH",
    "image_message",
    "image_stamp_ns",
    "require_rclpy",
    "serve",
]

log = logging.getLogger("dbml.experiment.rclpypeers")

RCLPY_MISSING = (
    "--transport rclpy runs its robots and operator as plain ROS 2 nodes with rclpy, "
    f"which {sys.executable} cannot import: pip install 'dbml[rclpy]'"
)
DRIVER_DEPTH = 10
"""The camera's and the priority's publishers keep this many (rclpy's usual ``qos=10``)."""
SUBSCRIPTION_DEPTH = 10
FRAME_ID = "camera"
ENCODING = "mono8"
_NS_PER_S = 1_000_000_000
_DRIVER_JOIN_S = 5.0
"""How long a camera waits for its driver's frame in progress when it ends."""
_PLAIN_CDR = frozenset({0x0000, 0x0001, 0x0006, 0x0007})
"""Encapsulations whose body is laid out plainly (CDR, CDR2 of a final type; odd: little
endian). An ``Image`` is final, so its stamp is the body's first 8 bytes in either."""
_STAMP = {True: struct.Struct("<iI"), False: struct.Struct(">iI")}
_ENCAPSULATION_BYTES = 4


def require_rclpy() -> Any:
    """rclpy, or ``DbmlError(RCLPY_MISSING)`` naming what to install."""
    try:
        import rclpy
    except ImportError:
        raise DbmlError(RCLPY_MISSING) from None
    return rclpy


def image_message(size_bytes: int) -> Any:
    """A mono8 ``sensor_msgs/msg/Image`` of frame ``camera`` that serialises to ``size_bytes``.

    One row of zero pixels; its size is measured with rclpy's own serialisation, not assumed,
    so the size the bridge reports to the optimizer is the camera's.
    """
    require_rclpy()
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    image = Image(height=1, encoding=ENCODING, is_bigendian=0)
    image.header.frame_id = FRAME_ID
    width = size_bytes - len(serialize_message(image))
    if width < 0:
        raise DbmlError(f"size_bytes={size_bytes!r}: an Image takes {size_bytes - width} at least")
    image.width = image.step = width
    image.data = bytes(width)
    if len(serialize_message(image)) != size_bytes:
        raise DbmlError(f"an Image of {width} pixels does not serialise to {size_bytes} bytes")
    return image


def _image_class() -> Any:
    """``sensor_msgs.msg.Image`` (imported when a peer runs)."""
    from sensor_msgs.msg import Image

    return Image


def image_stamp_ns(payload: bytes) -> int | None:
    """``header.stamp`` of a serialised ``Image`` in ns; None if the encapsulation is not plain.

    A raw subscription hands over CDR: the stamp is 8 bytes after the encapsulation header,
    cheaper to read than deserialising 84 KB.
    """
    if len(payload) < _ENCAPSULATION_BYTES + _STAMP[True].size:
        return None
    kind = int.from_bytes(payload[:2], "big")
    if kind not in _PLAIN_CDR:
        return None
    sec, nanosec = _STAMP[bool(kind & 1)].unpack_from(payload, _ENCAPSULATION_BYTES)
    return int(sec) * _NS_PER_S + int(nanosec)


def _private_ros(*, domain_id: int | None, name: str) -> PrivateRos:
    """A ``PrivateRos`` (``DbmlError(RCLPY_MISSING)`` without rclpy)."""
    require_rclpy()
    from dbml.harness.ros2node import PrivateRos

    return PrivateRos(domain_id=domain_id, name=name)


def _qos(*, reliable: bool, depth: int) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def _frame_sender(publisher: Any, size_bytes: int) -> Callable[[], None]:
    """Publish one frame stamped now (one ``Image`` reused: a driver's buffer)."""
    image = image_message(size_bytes)
    stamp = image.header.stamp

    def send() -> None:
        stamp.sec, stamp.nanosec = divmod(time.time_ns(), _NS_PER_S)
        publisher.publish(image)

    return send


def _serve_camera(
    role: str, spec: RoleSpec, stop: threading.Event, *, lines: Iterable[str] | None
) -> int:
    """A camera peer's run; 1 when a thread (its driver's, its executor's) died meanwhile."""
    from std_msgs.msg import Float64

    index = robot_index(role)
    camera = fleet_cameras(spec.robots)[index]
    life = Lifetime(stop, None)
    ros = _private_ros(domain_id=spec.domain_id, name=role)
    driver: BackgroundThread | None = None
    camera_stop = threading.Event()
    try:
        send_frame = _frame_sender(
            ros.node(f"{role}_camera").create_publisher(
                _image_class(), camera.topic, _qos(reliable=True, depth=DRIVER_DEPTH)
            ),
            camera.size_bytes,
        )
        priority = ros.node(f"{role}_collision").create_publisher(
            Float64, camera.topic + PRIORITY_SUFFIX, _qos(reliable=True, depth=DRIVER_DEPTH)
        )
        ros.start()
        driver = BackgroundThread(
            lambda: run_paced(send_frame, rate_hz=MAX_RATE_HZ, stop=camera_stop),
            name=f"camera-{role}",
            log=log,
        )
        driver.start()  # from the start, as a camera driver: the bridge waits for a frame
        serve_role(
            role,
            stop,
            lambda t0: replay_priorities(
                lambda value: priority.publish(Float64(data=value)),
                index,
                t0,
                spec,
                stop,
                life=life,
                steps=fleet_steps(spec.robots),
            ),
            lines=lines,
        )
    finally:
        camera_stop.set()
        if driver is not None:
            driver.join(_DRIVER_JOIN_S)
        ros.close()
    return life.exit_code()


def _dds_meta(info: Any) -> tuple[bytes, MessageMeta] | None:
    """DDS's sequence number and send time of a sample as dbml's metadata, packed and read.

    None when the RMW did not fill them.
    """
    from dbml.transports.rclpy.transport import sample_meta

    packed = sample_meta(info)
    if packed is None:
        return None
    try:
        return packed, MessageMeta.decode(packed)
    except TransportError:
        return None


def _frame_callback(
    recorder: FrameRecorder,
    index: int,
    camera: RobotCamera,
    *,
    sample_info: bool,
    reporter: ReceptionReporter | None,
    rate_hz: float | None,
) -> Callable[[bytes, Any], None]:
    """The raw subscription callback of robot ``index``'s topic (message and sample info).

    ``sample_info``: the frame's sequence number and send time are DDS's, else a count and
    ``header.stamp``. ``reporter``: the frame goes to the estimator's reception reports too,
    under the channel's name. ``rate_hz``: the rate the frame says it was sent at (an unmanaged
    camera's own), None for a managed copy (a plain message carries none).
    """

    def record(payload: bytes, info: Any) -> None:
        arrival_s = time.time()
        dds = _dds_meta(info) if sample_info or reporter is not None else None
        if reporter is not None and dds is not None:
            reporter.record(Sample(camera.topic, payload, dds[0]))
        if sample_info and dds is not None:
            seq: int | None = dds[1].seq
            sent_s: float | None = dds[1].sent_ns / _NS_PER_S
        else:
            stamp_ns = image_stamp_ns(payload)
            seq, sent_s = None, None if stamp_ns is None else stamp_ns / _NS_PER_S
        recorder.record(
            index,
            arrival_s=arrival_s,
            seq=seq,
            sent_s=sent_s,
            size_bytes=len(payload),
            rate_hz=rate_hz,
        )

    return record


def _serve_operator(
    spec: RoleSpec,
    stop: threading.Event,
    *,
    sample_info: bool,
    lines: Iterable[str] | None,
    emit: Emit,
) -> int:
    """The operator peer's run; 1 when a thread (its executor's, its transport's) died."""
    life = Lifetime(stop, None)
    cameras = fleet_cameras(spec.robots)
    recorder = FrameRecorder(len(cameras))
    suffix = OPTIMIZED_SUFFIX if spec.managed else ""
    topics = [camera.topic + suffix for camera in cameras]
    transport = open_transport(spec.transport.name, host=spec.host, domain_id=spec.domain_id)
    reporter: ReceptionReporter | None = None
    ros: PrivateRos | None = None
    try:
        reporter = ReceptionReporter(transport).start() if spec.estimate else None
        ros = _private_ros(domain_id=spec.domain_id, name="operator")
        node = ros.node("operator")
        for i, (camera, topic) in enumerate(zip(cameras, topics, strict=True)):
            node.create_subscription(
                _image_class(),
                topic,
                _frame_callback(
                    recorder,
                    i,
                    camera,
                    sample_info=sample_info,
                    reporter=reporter,
                    rate_hz=None if spec.managed else MAX_RATE_HZ,
                ),
                _qos(reliable=False, depth=SUBSCRIPTION_DEPTH),
                raw=True,
            )
        ros.start()
        view = ParamView.of(transport.params)
        if spec.managed:  # unmanaged, no other dbml node runs: nothing to wait for
            transport.wait_for_peers(spec.peer_wait_s)
        wait_first_frames(recorder, topics, stop)
        variant = Variant.OPTIMIZED if spec.managed else Variant.FULL
        serve_role(
            "operator",
            stop,
            lambda t0: report_ticks(
                view,
                recorder,
                t0,
                spec,
                stop,
                life=life,
                cameras=cameras,
                variant=variant,
                emit=emit,
            ),
            lines=lines,
            emit=emit,
        )
    finally:
        try:
            if ros is not None:
                ros.close()  # first: no callback records into a closed reporter
            if reporter is not None:
                reporter.close()
        finally:
            transport.close()
    return life.exit_code()


def serve(
    role: str,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    sample_info: bool = False,
    lines: Iterable[str] | None = None,
    emit: Emit = emit_json,
) -> int:
    """One plain rclpy peer, from its nodes' start to its end: its exit code.

    ``sample_info``: the operator takes each frame's sequence number and send time from DDS's
    sample info (writer sequence number, source timestamp), not a count and ``header.stamp``.
    """
    peers = {"operator", *(camera.robot.lower() for camera in fleet_cameras(spec.robots))}
    if role not in peers:
        raise DbmlError(f"role={role!r} is not one of {', '.join(sorted(peers))}")
    require_rclpy()
    if role == "operator":
        return _serve_operator(spec, stop, sample_info=sample_info, lines=lines, emit=emit)
    return _serve_camera(role, spec, stop, lines=lines)
