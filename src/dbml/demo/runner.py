"""``dbml demo teleop``: the live scenario on one machine, checked against Table 2.

The roles run on loopback: OS processes over zenoh (a rendezvous port of the run's own) or ROS 1
(the master at ``ROS_MASTER_URI`` when one answers, else one started for the run; each role a
node with its own ROS_IP, so R1, R2 and the operator are different ROS hosts), ROS 2 over
rmw_zenoh's format (see ``_ros2_processes``) or over rclpy (see ``_rclpy_processes``), or threads
over the memory transport. Per step and robot the result holds tc, priority, the allocated and
measured rate, and whether they match Table 2 and each other.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import sys
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

from dbml.core.errors import DbmlError
from dbml.experiment.analysis import (
    RATE_TOLERANCE_HZ,
    SeriesPoint,
    StepResult,
    Window,
)
from dbml.experiment.rclpypeers import RCLPY_MISSING
from dbml.experiment.roles import HOSTS, RoleSpec
from dbml.experiment.ros2peers import IMAGE_TYPE, SDK_MISSING
from dbml.experiment.ros2peers import ROLES as ROS2_PEER_ROLES
from dbml.experiment.runner import Command, Helper, Observer, run_experiment
from dbml.harness.processes import free_port
from dbml.harness.ros2env import claim_domain, ros2_child_env
from dbml.harness.rosmaster import RosMaster
from dbml.scenarios.reproduce import reproduce_table2
from dbml.scenarios.teleop import LINK_MBIT, MAX_RATE_HZ, MIN_RATE_HZ, ROBOTS, STEPS
from dbml.transports.registry import TRANSPORTS
from dbml.view.target import ViewTarget

__all__ = ["MIN_STEP_S", "DemoOptions", "DemoResult", "DemoRobot", "DemoStep", "run_teleop_demo"]

MIN_STEP_S = 1.0
"""The shortest step that still times a 1.48 Hz stream after ``settle_s``."""
ROS1_HOSTS = {
    "optimizer": "127.0.0.1",
    "r1": "127.0.0.2",
    "r2": "127.0.0.3",
    "operator": "127.0.0.4",
}
"""ROS_IP per role: loopback addresses, so the master sees four hosts on one machine."""
ROS2_LISTEN = "tcp/127.0.0.1:0"
"""Each ROS 2 process listens on a port of its own: the router's gossip links peers directly."""
BRIDGE_WAIT_S = 50.0
"""How long a bridge waits for its camera's first frame (the robots start after it)."""
ROLES_MODULE = "dbml.experiment.roles"
ROS2_PEERS_MODULE = "dbml.experiment.ros2peers"
RCLPY_PEERS_MODULE = "dbml.experiment.rclpypeers"
LOG_PREFIX = "dbml-demo-ros-"
"""The run's ROS log directory (a temporary one: the demo writes no files of its own)."""
PEERS_MODULES = {"ros2": ROS2_PEERS_MODULE, "rclpy": RCLPY_PEERS_MODULE}
"""The transports whose robots and operator are plain ROS 2 nodes, and the module playing them."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DemoOptions:
    """What ``dbml demo teleop`` runs; checked on creation, messages name the flag."""

    step_seconds: float = 3.0
    transport: str = "zenoh"
    view: ViewTarget | None = None
    """``--foxglove``/``--record``: the operator's live view (its frames, the allocation)."""

    def __post_init__(self) -> None:
        if not self.step_seconds >= MIN_STEP_S:
            raise DbmlError(
                f"--step-seconds={self.step_seconds!r} must be >= 1 (rates down to 1.48 Hz)"
            )
        if self.transport not in TRANSPORTS:
            raise DbmlError(
                f"--transport={self.transport!r} is not one of: {', '.join(TRANSPORTS)}"
            )
        if self.view is not None and self.transport in PEERS_MODULES:
            raise DbmlError(
                f"--foxglove/--record with --transport={self.transport!r}: the operator is a "
                "plain ROS 2 node there, without dbml's view; run the view beside it with "
                f"`dbml monitor --transport {self.transport} --foxglove PORT`"
            )


@dataclass(frozen=True, slots=True)
class DemoRobot:
    """One robot in one step: the event, what was allocated and measured, and the checks."""

    topic: str
    tc_s: float
    priority: float
    measured: Window
    table2_hz: float

    @property
    def within_tolerance(self) -> bool:
        """Measured within 5 % (or 0.3 Hz) of allocated."""
        return self.measured.within_rate(floor_hz=RATE_TOLERANCE_HZ)

    @property
    def matches_table2(self) -> bool:
        """The allocation is Table 2's, to its printed precision."""
        allocated = self.measured.allocated_hz
        return allocated is not None and round(allocated, 2) == self.table2_hz


@dataclass(frozen=True, slots=True)
class DemoStep:
    """One step of the demo."""

    step: StepResult
    robots: tuple[DemoRobot, ...]

    @property
    def total_mbit(self) -> float:
        """What arrived, against the scenario's 11 Mbit/s."""
        return self.step.goodput_mbit


@dataclass(frozen=True, slots=True)
class DemoResult:
    """A demo run: every step it saw to its end, and the rolling series for a plot."""

    options: DemoOptions
    steps: tuple[DemoStep, ...] = ()
    series: tuple[SeriesPoint, ...] = ()
    interrupted: bool = False

    @property
    def ok(self) -> bool:
        """Every step ran, allocated Table 2 and delivered it."""
        return (
            not self.interrupted
            and len(self.steps) == len(STEPS)
            and all(r.within_tolerance and r.matches_table2 for s in self.steps for r in s.robots)
        )


def _judge(step: StepResult) -> DemoStep:
    table2 = reproduce_table2()[step.step - 1]
    return DemoStep(
        step,
        tuple(
            DemoRobot(camera.topic, row.tc_s, row.priority, measured, row.paper.rate_hz)
            for camera, row, measured in zip(ROBOTS, table2, step.robots, strict=True)
        ),
    )


def _command(master: RosMaster | None) -> Command:
    """How a role process starts: its environment.

    Over zenoh a rendezvous port of the run's own (a mesh of its own); over ROS 1 the nodes of
    ``master``, each on its own loopback address.
    """
    zenoh_port = str(free_port())

    def command(role: str, argv: list[str]) -> tuple[list[str], dict[str, str]]:
        if master is None:
            return argv, dict(os.environ, DBML_ZENOH_PORT=zenoh_port)
        host = ROS1_HOSTS[role]
        return argv, dict(os.environ, ROS_MASTER_URI=master.uri, ROS_IP=host, ROS_HOSTNAME=host)

    return command


def _bridges(network: tuple[str, ...], *, env: dict[str, str] | None) -> tuple[Helper, ...]:
    """One ``dbml bridge`` per camera, on its robot's host, before the robots start."""
    dbml = (sys.executable, "-m", "dbml")
    return tuple(
        Helper(
            name=f"bridge-{camera.robot.lower()}",
            argv=(
                *dbml,
                "bridge",
                camera.topic,
                "--min-hz",
                str(MIN_RATE_HZ),
                "--max-hz",
                str(MAX_RATE_HZ),
                "--type",
                IMAGE_TYPE,
                "--wait",
                str(BRIDGE_WAIT_S),
                "--host",
                HOSTS[camera.robot.lower()],
                *network,
            ),
            env=env,
            before=ROBOTS[0].robot.lower(),
        )
        for camera in ROBOTS
    )


def _peers_command(transport: str, env: dict[str, str]) -> Command:
    """Roles' argv, with the robots and the operator played by ``transport``'s plain peers."""
    module = PEERS_MODULES[transport]

    def command(role: str, argv: list[str]) -> tuple[list[str], dict[str, str]]:
        if role in ROS2_PEER_ROLES:  # the same protocol, played by plain ROS 2 nodes
            argv = [module if a == ROLES_MODULE else a for a in argv]
        return argv, env

    return command


def _ros2_processes(
    specs: dict[str, RoleSpec],
) -> tuple[dict[str, RoleSpec], Command, tuple[Helper, ...]]:
    """The ROS 2 run: plain ROS 2 robots and operator, dbml's bridges, optimizer and router.

    ROS 2 nodes meet at a zenoh router (``dbml router`` on a free loopback port, as
    ``rmw_zenohd`` on 7447), which starts first; everyone connects to it and listens on a port
    of its own. The robots and the operator are ``ros2peers`` (zenoh-ros2-sdk, no dbml); one
    ``dbml bridge`` per camera, on its robot's host, manages it; the optimizer is ``roles``'.
    Bridges start after the optimizer and operator, before the robots they bridge.
    """
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    network = ("--transport", "ros2", "--connect", endpoint, "--listen", ROS2_LISTEN)
    dbml = (sys.executable, "-m", "dbml")
    router = Helper(name="router", argv=(*dbml, "router", "--listen", endpoint), port=port)
    specs = {
        role: replace(spec, connect=(endpoint,), listen=(ROS2_LISTEN,))
        for role, spec in specs.items()
    }
    return specs, _peers_command("ros2", dict(os.environ)), (router, *_bridges(network, env=None))


def _rclpy_processes(
    specs: dict[str, RoleSpec], *, domain_id: int, log_dir: Path
) -> tuple[dict[str, RoleSpec], Command, tuple[Helper, ...]]:
    """The rclpy run: plain rclpy robots and operator, dbml's bridges and optimizer, over DDS.

    Every process joins ROS 2 domain ``domain_id`` (the run's own: DDS discovery needs no
    router) with its ROS logs under ``log_dir``. The robots and the operator are
    ``rclpypeers`` (no dbml); one ``dbml bridge --transport rclpy`` per camera, on its robot's
    host, manages it; the optimizer is ``roles``'. Bridges start before the robots.
    """
    env = ros2_child_env(domain_id=domain_id, log_dir=log_dir)
    network = ("--transport", "rclpy", "--domain-id", str(domain_id))
    specs = {role: replace(spec, domain_id=domain_id) for role, spec in specs.items()}
    return specs, _peers_command("rclpy", env), _bridges(network, env=env)


def run_teleop_demo(options: DemoOptions, *, observe: Observer | None = None) -> DemoResult:
    """Run the scenario live; ``observe`` sees every report of the operator (a live view)."""
    if options.transport == "ros1" and importlib.util.find_spec("rospy") is None:
        raise DbmlError(
            f"--transport ros1 needs rospy, which {sys.executable} cannot import: run "
            "`make run-ros1` (Debian's ROS packages and a venv of Debian's Python)"
        )
    if options.transport == "ros2" and importlib.util.find_spec("zenoh_ros2_sdk") is None:
        raise DbmlError(SDK_MISSING)
    if options.transport == "rclpy" and importlib.util.find_spec("rclpy") is None:
        raise DbmlError(RCLPY_MISSING)
    specs = {
        role: RoleSpec(step_s=options.step_seconds, transport=options.transport, host=host)
        for role, host in HOSTS.items()
    }
    if options.view is not None:  # the operator's: it receives the frames
        specs["operator"] = replace(
            specs["operator"],
            foxglove=options.view.foxglove_flag,
            record=options.view.record_flag,
        )
    helpers: tuple[Helper, ...] = ()
    with contextlib.ExitStack() as run:
        master = RosMaster.reuse_or_start() if options.transport == "ros1" else None
        if master is not None:
            run.callback(master.stop)
        command: Command | None = None
        if options.transport == "ros2":
            specs, command, helpers = _ros2_processes(specs)
        elif options.transport == "rclpy":
            specs, command, helpers = _rclpy_processes(
                specs,
                domain_id=run.enter_context(claim_domain()),
                log_dir=Path(run.enter_context(tempfile.TemporaryDirectory(prefix=LOG_PREFIX))),
            )
        elif TRANSPORTS[options.transport].spans_processes:
            command = _command(master)
        recording = run_experiment(
            specs, what="demo", command=command, observe=observe, helpers=helpers
        )
    if recording.t0 is None:
        return DemoResult(options, interrupted=recording.interrupted)
    analysis = recording.analyse(step_s=options.step_seconds, link_mbit=LINK_MBIT)
    return DemoResult(
        options,
        tuple(_judge(step) for step in analysis.steps),
        analysis.series,
        recording.interrupted,
    )
