"""Where the demo's roles run, for each way a transport's processes find each other.

The registry says how a transport's processes meet (``TransportEntry.discovery``); each way has
one :class:`DemoLayout`, which checks what it needs is installed and lays the run out on
loopback (a ``Plan``):

- in one process (``memory``): the roles as threads over one memory network;
- zenoh peers: OS processes meeting at a rendezvous port of the run's own;
- a ROS 1 master (the one at ``ROS_MASTER_URI`` when it answers, else one started for the run):
  each role a node with its own loopback address, so R1, R2 and the operator are other hosts;
- a zenoh router (rmw_zenoh's ROS 2): a router of the run's own, the robots and the operator
  played by plain ROS 2 nodes (``ros2peers``, zenoh-ros2-sdk), one bridge per camera;
- DDS (rclpy): a ROS 2 domain of the run's own, its ROS logs in a temporary folder, the robots
  and the operator played by plain rclpy nodes (``rclpypeers``), one bridge per camera.

With plain ROS 2 peers the operator is not dbml's, so it shows no live view (``dbml_operator``).
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import sys
import tempfile
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Protocol

from dbml.core.errors import DbmlError
from dbml.experiment.entry import Kind
from dbml.experiment.peers import peer_roles
from dbml.experiment.plan import Helper, Launch, Plan, bridge_helper, role_launch, router_helper
from dbml.experiment.rclpypeers import RCLPY_MISSING
from dbml.experiment.ros2peers import SDK_MISSING
from dbml.experiment.spec import RoleSpec
from dbml.harness.processes import free_port
from dbml.harness.ros2env import claim_domain, ros2_child_env
from dbml.harness.rosmaster import RosMaster
from dbml.scenarios.teleop import ROBOTS
from dbml.transports.registry import Discovery, TransportEntry

__all__ = ["LAYOUTS", "LOG_PREFIX", "ROS1_HOSTS", "ROS2_LISTEN", "DemoLayout", "layout_of"]

ROS1_HOSTS = {
    "optimizer": "127.0.0.1",
    "r1": "127.0.0.2",
    "r2": "127.0.0.3",
    "operator": "127.0.0.4",
}
"""ROS_IP per role: loopback addresses, so the master sees four hosts on one machine."""
ROS2_LISTEN = "tcp/127.0.0.1:0"
"""Each ROS 2 process listens on a port of its own: the router's gossip links peers directly."""
LOG_PREFIX = "dbml-demo-ros-"
"""The run's ROS log directory (a temporary one: the demo writes no files of its own)."""


class DemoLayout(Protocol):
    """How the demo's roles run for one way of meeting."""

    @property
    def dbml_operator(self) -> bool:
        """Whether the operator is dbml's own (a live view needs it)."""
        ...

    def check(self) -> None:
        """``DbmlError`` naming what to install, when this interpreter lacks it."""
        ...

    def plan(
        self, specs: Mapping[str, RoleSpec], transport: TransportEntry, run: contextlib.ExitStack
    ) -> Plan:
        """The run laid out; what it sets up (a master, a domain) is undone by ``run``."""
        ...


def _launches(
    kind: Kind, specs: Mapping[str, RoleSpec], env: Mapping[str, str]
) -> dict[str, Launch]:
    return {role: role_launch(kind, role, spec, env=env) for role, spec in specs.items()}


class _Threads:
    """Every role a thread of this process, over one memory network."""

    dbml_operator = True

    def check(self) -> None:
        """Nothing to install."""

    def plan(
        self, specs: Mapping[str, RoleSpec], transport: TransportEntry, run: contextlib.ExitStack
    ) -> Plan:
        """The roles as they are, run as threads."""
        return Plan(specs=specs)


class _ZenohMesh:
    """OS processes meeting at a rendezvous port of the run's own (a mesh of its own)."""

    dbml_operator = True

    def check(self) -> None:
        """Zenoh is a dependency: nothing to install."""

    def plan(
        self, specs: Mapping[str, RoleSpec], transport: TransportEntry, run: contextlib.ExitStack
    ) -> Plan:
        """Each role a process with ``DBML_ZENOH_PORT`` set to the run's port."""
        env = dict(os.environ, DBML_ZENOH_PORT=str(free_port()))
        return Plan(specs=specs, launches=_launches(Kind.ROLE, specs, env))


class _RosMaster:
    """OS processes as nodes of one ROS master, each on its own loopback address."""

    dbml_operator = True

    def check(self) -> None:
        """rospy, from Debian's ROS packages."""
        if importlib.util.find_spec("rospy") is None:
            raise DbmlError(
                f"--transport ros1 needs rospy, which {sys.executable} cannot import: run "
                "`make run-ros1` (Debian's ROS packages and a venv of Debian's Python)"
            )

    def plan(
        self, specs: Mapping[str, RoleSpec], transport: TransportEntry, run: contextlib.ExitStack
    ) -> Plan:
        """Each role's node with its own ROS_IP, at the master (started here if none runs)."""
        master = RosMaster.reuse_or_start()
        run.callback(master.stop)
        specs = {role: replace(spec, host=ROS1_HOSTS[role]) for role, spec in specs.items()}
        launches = {
            role: role_launch(
                Kind.ROLE,
                role,
                spec,
                env=dict(
                    os.environ,
                    ROS_MASTER_URI=master.uri,
                    ROS_IP=ROS1_HOSTS[role],
                    ROS_HOSTNAME=ROS1_HOSTS[role],
                ),
            )
            for role, spec in specs.items()
        }
        return Plan(specs=specs, launches=launches)


def _peer_launches(
    peers: Kind, specs: Mapping[str, RoleSpec], env: Mapping[str, str]
) -> dict[str, Launch]:
    """The robots and the operator played by ``peers``; the optimizer is dbml's role."""
    played = peer_roles()
    return {
        role: role_launch(peers if role in played else Kind.ROLE, role, spec, env=env)
        for role, spec in specs.items()
    }


class _Ros2Router:
    """rmw_zenoh's ROS 2: plain ROS 2 robots and operator, dbml's bridges, optimizer, router.

    ROS 2 nodes meet at a zenoh router (one on a free loopback port, as ``rmw_zenohd`` on 7447),
    which starts first; everyone connects to it and listens on a port of its own. The robots and
    the operator are ``ros2peers`` (zenoh-ros2-sdk, no dbml); one bridge per camera, on its
    robot's host, manages it; the optimizer is dbml's. Bridges start after the optimizer and
    operator, before the robots they bridge.
    """

    dbml_operator = False

    def check(self) -> None:
        """zenoh-ros2-sdk, for the plain peers."""
        if importlib.util.find_spec("zenoh_ros2_sdk") is None:
            raise DbmlError(SDK_MISSING)

    def plan(
        self, specs: Mapping[str, RoleSpec], transport: TransportEntry, run: contextlib.ExitStack
    ) -> Plan:
        """The router, the peers and the bridges at it."""
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        specs = {
            role: replace(spec, connect=(endpoint,), listen=(ROS2_LISTEN,))
            for role, spec in specs.items()
        }
        router = router_helper("router", listen=endpoint, port=port)
        bridges = tuple(
            bridge_helper(
                camera,
                transport=transport,
                before=ROBOTS[0].robot.lower(),
                connect=(endpoint,),
                listen=(ROS2_LISTEN,),
            )
            for camera in ROBOTS
        )
        launches = _peer_launches(Kind.ROS2_PEER, specs, dict(os.environ))
        return Plan(specs=specs, launches=launches, helpers=(router, *bridges))


class _Dds:
    """rclpy: plain rclpy robots and operator, dbml's bridges and optimizer, over DDS.

    Every process joins a ROS 2 domain of the run's own (DDS discovery needs no router) with its
    ROS logs in a temporary folder. The robots and the operator are ``rclpypeers`` (no dbml);
    one bridge per camera, on its robot's host, manages it; the optimizer is dbml's. Bridges
    start before the robots.
    """

    dbml_operator = False

    def check(self) -> None:
        """rclpy, for the plain peers (the ``rclpy`` extra)."""
        if importlib.util.find_spec("rclpy") is None:
            raise DbmlError(RCLPY_MISSING)

    def plan(
        self, specs: Mapping[str, RoleSpec], transport: TransportEntry, run: contextlib.ExitStack
    ) -> Plan:
        """The peers and the bridges in the run's domain."""
        domain_id = run.enter_context(claim_domain())
        log_dir = Path(run.enter_context(tempfile.TemporaryDirectory(prefix=LOG_PREFIX)))
        env = ros2_child_env(domain_id=domain_id, log_dir=log_dir)
        specs = {role: replace(spec, domain_id=domain_id) for role, spec in specs.items()}
        bridges: tuple[Helper, ...] = tuple(
            bridge_helper(
                camera,
                transport=transport,
                before=ROBOTS[0].robot.lower(),
                env=env,
                domain_id=domain_id,
            )
            for camera in ROBOTS
        )
        launches = _peer_launches(Kind.RCLPY_PEER, specs, env)
        return Plan(specs=specs, launches=launches, helpers=bridges)


LAYOUTS: Mapping[Discovery, DemoLayout] = {
    Discovery.IN_PROCESS: _Threads(),
    Discovery.ZENOH: _ZenohMesh(),
    Discovery.ROS_MASTER: _RosMaster(),
    Discovery.ZENOH_ROUTER: _Ros2Router(),
    Discovery.DDS: _Dds(),
}
"""The demo's layout for each way of meeting."""


def layout_of(transport: TransportEntry) -> DemoLayout:
    """The layout of ``transport``'s way of meeting."""
    return LAYOUTS[transport.discovery]
