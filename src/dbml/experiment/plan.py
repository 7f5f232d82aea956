"""A run laid out: how each of its children starts, and in which order.

A layout (the demo's, the testbed's) turns a run's options into a :class:`Plan`: each role's
``RoleSpec`` and :class:`Launch` (argv, environment, network namespace), and the
:class:`Helper` processes among them (a zenoh router, the cameras' bridges). The launches run
``python -m dbml.experiment KIND ...`` (``entry``); :func:`role_launch`, :func:`bridge_helper`
and :func:`router_helper` build them, so every layout starts its children the same way.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from dbml.core.errors import DbmlError
from dbml.experiment.bridge import BridgeSpec
from dbml.experiment.entry import Kind, child_argv
from dbml.experiment.peers import IMAGE_TYPE
from dbml.experiment.spec import RoleSpec, host_of
from dbml.scenarios.teleop import MAX_RATE_HZ, MIN_RATE_HZ, RobotCamera
from dbml.transports.registry import TransportEntry

__all__ = [
    "BRIDGE_WAIT_S",
    "Helper",
    "Launch",
    "Plan",
    "bridge_helper",
    "bridge_name",
    "role_launch",
    "router_helper",
]

BRIDGE_WAIT_S = 50.0
"""How long a bridge waits for its camera's first frame (the robots start after it)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Launch:
    """How one process of a run starts: its argv, its environment, its network namespace."""

    argv: tuple[str, ...]
    env: Mapping[str, str] | None = None
    """None: this process's."""
    netns: str | None = None
    """The network namespace it runs in (None: this process's)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Helper:
    """A process the roles need that speaks no role protocol: a zenoh router, a bridge.

    It starts just before role ``before`` (None: before every role), once ``port`` on
    127.0.0.1 accepts connections when given; it counts as a role that exits early if it ends
    before the last step, and is ended by PID with the roles.
    """

    name: str
    launch: Launch
    before: str | None = None
    port: int | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class Plan:
    """A run laid out: each role's spec (in start order), how it starts, and the helpers.

    ``launches`` None: the roles run as threads of this process, over a memory network of the
    run's own (no helpers then).
    """

    specs: Mapping[str, RoleSpec]
    launches: Mapping[str, Launch] | None = None
    helpers: tuple[Helper, ...] = ()

    def __post_init__(self) -> None:
        if self.launches is None and self.helpers:
            raise DbmlError("helper processes need role processes, not threads")
        if self.launches is not None and set(self.launches) != set(self.specs):
            raise DbmlError(f"launches for {sorted(self.launches)} but roles {sorted(self.specs)}")


def role_launch(
    kind: Kind,
    role: str,
    spec: RoleSpec,
    *options: str,
    env: Mapping[str, str] | None = None,
    netns: str | None = None,
) -> Launch:
    """Role ``role`` played by a ``kind`` child (dbml's role, or a plain ROS 2 peer)."""
    return Launch(argv=child_argv(kind, role, spec.to_json(), *options), env=env, netns=netns)


def bridge_name(camera: RobotCamera) -> str:
    """The name of ``camera``'s bridge among a run's children."""
    return f"bridge-{camera.robot.lower()}"


def bridge_helper(
    camera: RobotCamera,
    *,
    transport: TransportEntry,
    before: str,
    env: Mapping[str, str] | None = None,
    netns: str | None = None,
    domain_id: int | None = None,
    connect: tuple[str, ...] = (),
    listen: tuple[str, ...] = (),
) -> Helper:
    """The bridge of ``camera``'s topic on its robot's host, started before role ``before``."""
    role = camera.robot.lower()
    spec = BridgeSpec(
        topic=camera.topic,
        min_rate_hz=MIN_RATE_HZ,
        max_rate_hz=MAX_RATE_HZ,
        msg_type=IMAGE_TYPE,
        wait_s=BRIDGE_WAIT_S,
        host=host_of(role),
        transport=transport,
        domain_id=domain_id,
        connect=connect,
        listen=listen,
    )
    return Helper(
        name=bridge_name(camera),
        launch=Launch(argv=child_argv(Kind.BRIDGE, spec.to_json()), env=env, netns=netns),
        before=before,
    )


def router_helper(
    name: str,
    *,
    listen: str,
    connect: tuple[str, ...] = (),
    netns: str | None = None,
    port: int | None = None,
) -> Helper:
    """A zenoh router listening on ``listen`` (and meshed with ``connect``), before every role.

    ``port``: the run waits until it accepts connections on 127.0.0.1 there.
    """
    argv = child_argv(Kind.ROUTER, "--listen", listen, *(f"--connect={c}" for c in connect))
    return Helper(name=name, launch=Launch(argv=argv, netns=netns), port=port)
