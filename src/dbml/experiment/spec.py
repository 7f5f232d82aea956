"""What every part of the teleoperation experiment is told: its roles, hosts and ``RoleSpec``.

The roles (``optimizer``, the robots ``r1``..``rN``, the ``operator``), the host identity of
each, the operator's tick, the urgent streams of the transport-class comparison, and the
``RoleSpec`` a role process gets as one JSON argument. The spec's ``transport`` is a registry
entry and its ``strategy`` an enum: converted once, where the spec is made or read.
"""

from __future__ import annotations

import enum
import json
import re
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from dbml.core.allocation import Strategy
from dbml.core.errors import DbmlError
from dbml.estimator.designs import DEFAULT_DESIGN, Design
from dbml.scenarios.teleop import LINK_MBIT, MIN_RATE_HZ, ROBOTS, STEPS
from dbml.transports import registry
from dbml.transports.registry import TRANSPORTS, TransportEntry

__all__ = [
    "HOSTS",
    "LADDER_MIN_QUALITY",
    "PEER_WAIT_S",
    "PERIOD_S",
    "ROLES",
    "TAIL_S",
    "TICK_S",
    "URGENT_PRIORITY",
    "URGENT_RATE_HZ",
    "URGENT_SIZE_BYTES",
    "URGENT_STREAMS",
    "Frames",
    "RoleSpec",
    "UrgentStream",
    "fleet_phase_s",
    "host_of",
    "robot_index",
    "transport_entry",
    "wait_until",
]

ROLES = ("operator", "optimizer", *(camera.robot.lower() for camera in ROBOTS))
"""Every role, in the order they start: listeners before those that connect to them."""
HOSTS = {"operator": "operator", "optimizer": "base-station", "r1": "robot-r1", "r2": "robot-r2"}
"""Each role's host identity: four hosts, so every robot-to-operator stream is managed."""
LADDER_MIN_QUALITY = 0.9
"""A laddered camera's quality floor (SSIM on its probe frame). Below it a 640x480 frame is
visibly degraded (../shared/QUALITY.md: 320x240 q50 scores 0.83); without it a camera nobody
prioritises was left q30 (SSIM 0.851) beside a prioritised one: frames go first instead."""
TICK_S = 0.2
"""How often the operator reports what arrived."""
TAIL_S = 1.0
"""The operator and optimizer run this long after the last step, for frames still in flight."""
PERIOD_S = 1.0
"""The optimisation period (the paper's 1 s): the publishers' heartbeat."""
PEER_WAIT_S = 10.0
"""How long a role waits to reach the others before it reports ready."""

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


class Frames(enum.StrEnum):
    """What the robots' cameras send.

    ``synthetic``: frames of the paper's sizes (bytes that are no picture); ``photos``: real
    frames of a camera moving over photographs (``dbml.media.photos``), at the paper's
    resolutions, as JPEG on ``[topic]/optimized/compressed``: with a ladder (rate and quality
    chosen together) or without (``RoleSpec.ladder``: rate only, at the one JPEG quality whose
    frames are the paper's 84,000 B).
    """

    SYNTHETIC = "synthetic"
    PHOTOS = "photos"


def transport_entry(name: str, *, flag: str = "--transport") -> TransportEntry:
    """The registered transport ``name``; ``DbmlError`` naming ``flag`` and the choices if none."""
    return registry.entry(name, field=flag)


def host_of(role: str) -> str:
    """A role's host identity: ``HOSTS``', or a fleet robot's own (``robot-r3``)."""
    return HOSTS.get(role, f"robot-{role}")


@dataclass(frozen=True, slots=True, kw_only=True)
class RoleSpec:
    """Everything a role needs, passed to a role process as one JSON argument."""

    step_s: float
    transport: TransportEntry = TRANSPORTS["zenoh"]
    host: str | None = None
    """The host identity (over ROS 1 the address the node gives others, as ROS_HOSTNAME)."""
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    managed: bool = True
    """False: the robots publish at their maximum and no optimizer runs (the testbed's baseline)."""
    link_mbit: float = LINK_MBIT
    utilization: float = 1.0
    strategy: Strategy = Strategy.PAPER
    estimate: bool = False
    estimator_design: Design = DEFAULT_DESIGN
    """With ``estimate``: how the optimizer's estimator reads overuse."""
    uplinks_mbit: Mapping[str, float] = field(default_factory=dict)
    peer_wait_s: float = PEER_WAIT_S
    urgent_stream: bool = False
    """R1 also sends ``URGENT_STREAMS`` (the testbed's comparison of transport classes)."""
    priority_links: bool = False
    """The transport opens a link per range of priorities (zenoh's): for ``urgent_stream``."""
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
    frames: Frames = Frames.SYNTHETIC
    ladder: bool = True
    """With ``frames=photos``: the cameras publish their ladders (False: rate only)."""

    def to_json(self) -> str:
        """The spec as one JSON object (the role process's argument)."""
        document: dict[str, Any] = {
            name: getattr(self, name) for name in self.__dataclass_fields__ if name != "transport"
        }
        document["transport"] = self.transport.name
        document["uplinks_mbit"] = dict(self.uplinks_mbit)
        document["frames"] = self.frames.value
        document["estimator_design"] = self.estimator_design.value
        return json.dumps(document)

    @classmethod
    def from_json(cls, text: str) -> RoleSpec:
        """The spec ``to_json`` wrote; ``DbmlError`` naming a field it cannot take."""
        document: dict[str, Any] = json.loads(text)
        if not isinstance(document, dict):
            raise DbmlError(f"spec={text[:80]!r} is not a JSON object")
        document["transport"] = transport_entry(str(document.get("transport", "zenoh")))
        document["listen"] = tuple(document.get("listen", ()))
        document["connect"] = tuple(document.get("connect", ()))
        strategy = document.get("strategy", Strategy.PAPER.value)
        try:
            document["strategy"] = Strategy(strategy)
        except ValueError:
            raise DbmlError(f"spec strategy={strategy!r} is not a strategy") from None
        design = document.get("estimator_design", DEFAULT_DESIGN.value)
        try:
            document["estimator_design"] = Design(design)
        except ValueError:
            raise DbmlError(f"spec estimator_design={design!r} is not a design") from None
        frames = document.get("frames", Frames.SYNTHETIC.value)
        try:
            document["frames"] = Frames(frames)
        except ValueError:
            raise DbmlError(f"spec frames={frames!r} is not one of synthetic, photos") from None
        try:
            return cls(**document)
        except TypeError as err:
            raise DbmlError(f"spec: {err}") from None

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
