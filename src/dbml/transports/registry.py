"""Transports by name; middleware is imported only when its transport is opened.

``TRANSPORTS`` maps each name to a ``TransportEntry``: the factory and what a caller must know
before choosing it (whether it spans processes, how its processes find each other, whether its
messages carry dbml's metadata, whether its parameter store is complete when a process starts,
how its camera frames are made). The command line's choices and help come from it, in its
order, the default first.
"""

from __future__ import annotations

import enum
import importlib
import time
import types
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from dbml.core.errors import TransportError
from dbml.transports.base import Transport
from dbml.transports.codecs import (
    CDR_IMAGE,
    IMAGE_TYPE,
    RAW_FRAME,
    ROS1_IMAGE,
    FrameCodec,
    image_cdr,
)
from dbml.transports.memory import MemoryNetwork, MemoryTransport

__all__ = [
    "DEFAULT_TRANSPORT",
    "TRANSPORTS",
    "Discovery",
    "TransportEntry",
    "TransportFactory",
    "TransportOptions",
    "camera_frame",
    "entry",
    "open_transport",
]

DEFAULT_TRANSPORT = "zenoh"
"""The transport used when none is named."""


@dataclass(frozen=True, slots=True, kw_only=True)
class TransportOptions:
    """Everything ``open_transport`` may be given; each factory refuses what it cannot use."""

    host: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | Path | None = None
    network: MemoryNetwork | None = None
    follow_all_params: bool = True
    domain_id: int | None = None
    ros_distro: str | None = None
    msg_paths: tuple[str | Path, ...] = ()
    priority_links: bool = False
    ros_args: tuple[str, ...] = ()


class TransportFactory(Protocol):
    """Opens one transport from ``open_transport``'s options (each rejects what it cannot use)."""

    def __call__(self, options: TransportOptions, /) -> Transport:
        """Open the transport; a ``TransportError`` names what is missing or not accepted."""
        ...


class Discovery(enum.StrEnum):
    """How a transport's processes find each other: what a run of several must set up."""

    IN_PROCESS = "in-process"
    """One process only (``memory``): nothing to meet."""
    ZENOH = "zenoh"
    """Zenoh peers: a rendezvous on loopback, or explicit endpoints across hosts."""
    ROS_MASTER = "ros-master"
    """A ROS 1 master at ``ROS_MASTER_URI``."""
    ZENOH_ROUTER = "zenoh-router"
    """A zenoh router per host, as rmw_zenoh's ROS 2 nodes meet."""
    DDS = "dds"
    """DDS discovery in a ROS 2 domain (``ROS_DOMAIN_ID``)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class TransportEntry:
    """One registered transport: how to open it and what it offers."""

    name: str
    """Its key in ``TRANSPORTS`` (the ``--transport`` value)."""
    factory: TransportFactory
    summary: str
    """One line for a command's help."""
    spans_processes: bool
    """Whether processes (and machines) meet over it; ``memory`` lives in one process."""
    carries_metadata: bool
    """Whether messages carry dbml's attachment (send time, sequence), which estimation needs."""
    discovery: Discovery
    """How its processes find each other."""
    params_complete_at_start: bool
    """Whether a process reads the whole store when it starts (the ROS parameter server), so an
    optimizer must write the defaults of unset parameters where everyone reads them."""
    typed_topics: bool = False
    """Whether every topic has a message type (ROS 1, ROS 2), so one that cannot be found is
    an error rather than untyped bytes."""
    send_times: bool = False
    """Whether a received message says when it was sent and its sequence number (dbml's
    attachment, or DDS's sample info over rclpy): what ``--estimate`` needs."""
    frame: FrameCodec = RAW_FRAME
    """A synthetic camera frame as this transport carries it (``camera_frame``)."""

    def camera_frame(self, transport: Transport, topic: str, size_bytes: int) -> bytes:
        """A synthetic camera frame of exactly ``size_bytes`` as this transport carries it.

        ``transport`` is an open transport of this entry. Over a typed middleware (ROS 1, ROS 2)
        the frame is a serialised ``sensor_msgs/Image`` and ``topic`` is declared of that type
        first, so the size the optimizer sees is the size asked for; elsewhere raw bytes.
        """
        codec = self.frame
        frame = codec.encode(size_bytes)  # first: a size too small is refused before anything
        if codec.msg_type is not None:
            transport.set_topic_type(topic, codec.msg_type)
        return frame


def _stamped_image(size_bytes: int) -> bytes:
    """A CDR ``sensor_msgs/msg/Image`` stamped with the wall clock when made (``ros2``'s frame).

    A ROS 2 viewer subscribed through rmw_zenoh shows when it was made.
    """
    return image_cdr(size_bytes, stamp_ns=time.time_ns())


def _no_network(name: str, options: TransportOptions) -> None:
    if options.network is not None:
        raise TransportError(f"transport={name!r} takes no network: only 'memory' does")


def _no_ros2_options(name: str, options: TransportOptions) -> None:
    for option, value in (
        ("domain_id", options.domain_id),
        ("ros_distro", options.ros_distro),
        ("msg_paths", options.msg_paths or None),
    ):
        if value is not None:
            raise TransportError(
                f"transport={name!r} takes no {option} ({value!r}): only 'ros2' does"
            )


def _no_ros_args(name: str, options: TransportOptions) -> None:
    if options.ros_args:
        raise TransportError(
            f"transport={name!r} takes no --ros-args ({' '.join(options.ros_args)}): "
            "only 'rclpy' runs ROS 2 nodes in this process"
        )


def _no_priority_links(name: str, options: TransportOptions) -> None:
    if options.priority_links:
        raise TransportError(f"transport={name!r} has no priority links: only zenoh's do")


def _no_endpoints(name: str, options: TransportOptions, why: str) -> None:
    if options.connect or options.listen or options.config_file:
        raise TransportError(f"transport={name!r} takes no endpoints or config file{why}")


def _open_ros2(options: TransportOptions) -> Transport:
    _no_network("ros2", options)
    _no_ros_args("ros2", options)
    module = importlib.import_module("dbml.transports.ros2")
    transport: Transport = module.Ros2Transport(
        host=options.host,
        connect=options.connect,
        listen=options.listen,
        config_file=options.config_file,
        domain_id=options.domain_id,
        ros_distro=options.ros_distro,
        msg_paths=options.msg_paths,
        follow_all_params=options.follow_all_params,
        priority_links=options.priority_links,
    )
    return transport


def _open_rclpy(options: TransportOptions) -> Transport:
    from dbml.transports.ros2.wire import check_domain_id  # pure: no middleware imported

    _no_endpoints(
        "rclpy",
        options,
        ": DDS discovery finds peers (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE, "
        "ROS_STATIC_PEERS)",
    )
    _no_network("rclpy", options)
    _no_priority_links("rclpy", options)
    for option, value in (("ros_distro", options.ros_distro), ("msg_paths", options.msg_paths)):
        if value:
            raise TransportError(
                f"transport='rclpy' takes no {option} ({value!r}): rclpy brings its own types"
            )
    try:
        cls = importlib.import_module("dbml.transports.rclpy").RclpyTransport
    except ImportError as err:
        raise TransportError(str(err)) from err
    domain_id = None if options.domain_id is None else check_domain_id(options.domain_id)
    transport: Transport = cls(host=options.host, domain_id=domain_id, ros_args=options.ros_args)
    return transport


def _open_zenoh(options: TransportOptions) -> Transport:
    _no_network("zenoh", options)
    _no_ros2_options("zenoh", options)
    _no_ros_args("zenoh", options)
    module = importlib.import_module("dbml.transports.zenoh")
    transport: Transport = module.ZenohTransport(
        host=options.host,
        connect=options.connect,
        listen=options.listen,
        config_file=options.config_file,
        follow_all_params=options.follow_all_params,
        priority_links=options.priority_links,
    )
    return transport


def _open_ros1(options: TransportOptions) -> Transport:
    _no_endpoints("ros1", options, ": it uses ROS_MASTER_URI")
    _no_network("ros1", options)
    _no_ros2_options("ros1", options)
    _no_ros_args("ros1", options)
    _no_priority_links("ros1", options)
    try:
        cls = importlib.import_module("dbml.transports.ros1").Ros1Transport
    except ImportError as err:
        raise TransportError(str(err)) from err
    transport: Transport = cls(host=options.host)
    return transport


def _open_memory(options: TransportOptions) -> Transport:
    _no_endpoints("memory", options, "")
    _no_ros2_options("memory", options)
    _no_ros_args("memory", options)
    _no_priority_links("memory", options)
    return MemoryTransport(options.network, host=options.host)


TRANSPORTS: Mapping[str, TransportEntry] = types.MappingProxyType(
    {
        "zenoh": TransportEntry(
            name="zenoh",
            discovery=Discovery.ZENOH,
            factory=_open_zenoh,
            summary="eclipse-zenoh, peer to peer; loopback with no flags, endpoints across hosts",
            spans_processes=True,
            carries_metadata=True,
            params_complete_at_start=False,
            send_times=True,
        ),
        "ros1": TransportEntry(
            name="ros1",
            discovery=Discovery.ROS_MASTER,
            factory=_open_ros1,
            summary="rospy topics and the parameter server of the master at ROS_MASTER_URI",
            spans_processes=True,
            carries_metadata=False,
            params_complete_at_start=True,
            typed_topics=True,
            frame=ROS1_IMAGE,
        ),
        "rclpy": TransportEntry(
            name="rclpy",
            discovery=Discovery.DDS,
            factory=_open_rclpy,
            summary="real ROS 2 through rclpy on its RMW (Fast DDS by default): topics and "
            "parameters on /dbm and [topic]/dbm",
            spans_processes=True,
            carries_metadata=False,
            params_complete_at_start=False,
            typed_topics=True,
            send_times=True,
            frame=CDR_IMAGE,
        ),
        "ros2": TransportEntry(
            name="ros2",
            discovery=Discovery.ZENOH_ROUTER,
            factory=_open_ros2,
            summary="ROS 2 topics as rmw_zenoh carries them, via the zenoh router of this host",
            spans_processes=True,
            carries_metadata=False,
            params_complete_at_start=False,
            typed_topics=True,
            frame=FrameCodec(IMAGE_TYPE, _stamped_image),
        ),
        "memory": TransportEntry(
            name="memory",
            discovery=Discovery.IN_PROCESS,
            factory=_open_memory,
            summary="in one process, synchronous and deterministic (tests, simulations)",
            spans_processes=False,
            carries_metadata=True,
            params_complete_at_start=False,
            send_times=True,
        ),
    }
)
"""Registered transports by name, the default first; read-only."""


def open_transport(
    name: str = DEFAULT_TRANSPORT,
    *,
    host: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: str | Path | None = None,
    network: MemoryNetwork | None = None,
    follow_all_params: bool = True,
    domain_id: int | None = None,
    ros_distro: str | None = None,
    msg_paths: Sequence[str | Path] = (),
    priority_links: bool = False,
    ros_args: Sequence[str] = (),
) -> Transport:
    """Open a transport by name.

    ``memory`` joins ``network`` (a private in-process network if none is given); ``zenoh``
    meets peers on loopback, or at ``connect`` / ``listen`` endpoints or a zenoh
    ``config_file``; ``ros1`` joins the ROS master at ``ROS_MASTER_URI``. ``host`` is this
    process's identity (over ROS 1, the host part of the node's URI, as ``ROS_HOSTNAME`` sets).
    ``follow_all_params=False`` is for a process that only publishes: over zenoh it then hears
    the global parameters, the optimizer's allocations and its own channels' parameters, not
    every other publisher's reports (ROS 1's parameter server and memory hold everything anyway).
    ``rclpy`` joins ROS 2 domain ``domain_id`` (else ``ROS_DOMAIN_ID``) through rclpy.
    ``ros2`` joins rmw_zenoh's router of this host (or ``connect``/``listen``) in ROS 2 domain
    ``domain_id`` (else ``ROS_DOMAIN_ID``), with the types of ``ros_distro`` and the ``.msg``
    files under ``msg_paths``; the other transports refuse these options. ``priority_links``
    (zenoh, ros2) opens a link per range of priorities to each ``connect`` endpoint, so urgent
    classes never wait behind bulk bytes in one TCP connection; the listening side needs it too.
    ``ros_args`` (rclpy): ROS 2's own arguments, every ``--ros-args`` block
    (``dbml.transports.rclpy.rosargs``).
    """
    return entry(name).factory(
        TransportOptions(
            host=host,
            connect=tuple(connect),
            listen=tuple(listen),
            config_file=config_file,
            network=network,
            follow_all_params=follow_all_params,
            domain_id=domain_id,
            ros_distro=ros_distro,
            msg_paths=tuple(msg_paths),
            priority_links=priority_links,
            ros_args=tuple(ros_args),
        )
    )


def camera_frame(transport: Transport, name: str, topic: str, size_bytes: int) -> bytes:
    """``entry(name).camera_frame(...)``: a frame as transport ``name`` carries it."""
    return entry(name).camera_frame(transport, topic, size_bytes)


def entry(name: str, *, field: str = "transport") -> TransportEntry:
    """The registered transport ``name``; ``TransportError`` naming ``field`` and the choices."""
    found = TRANSPORTS.get(name)
    if found is None:
        raise TransportError(f"{field}={name!r} is not one of: {', '.join(TRANSPORTS)}")
    return found
