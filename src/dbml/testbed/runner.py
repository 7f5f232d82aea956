"""``dbml testbed teleop``: the paper's teleoperation scenario over a real, shaped network.

Robots R1 and R2 and the operator are network namespaces; their traffic to the operator shares
one ``tc``-shaped link (and, with ``--uplink``, a robot's own slower uplink). The experiment's
roles run inside: zenoh on explicit endpoints with shared memory off, the optimizer on the
operator's side (policies ``dbml`` and ``static``; none under ``unmanaged``). The link's rate
changes on schedule; the result holds, per step and robot, allocated and delivered rates,
latency, losses and goodput, the recovery after each link change, and the targets that apply.

With ``transport="rclpy"`` the same experiment runs on real ROS 2 (rclpy on Fast DDS), laid out
as ``dbml demo teleop --transport rclpy``: in each robot's namespace a plain rclpy camera
(``dbml.experiment.rclpypeers``) and, managed, a ``dbml bridge --transport rclpy`` of its topic
(``dbml.testbed.bridge``); in the operator's the optimizer (``roles``) and a plain rclpy operator
subscribing each ``/rN/camera/optimized`` (``/rN/camera`` unmanaged). DDS discovery crosses the
router by unicast: each robot's processes announce themselves to the operator's address
(``ROS_STATIC_PEERS``), see :func:`ros_env`.

Every namespace and process is removed at the end, also on error, Ctrl-C or SIGTERM; so are the
Fast DDS shared-memory files of a ROS 2 process that had to be killed.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import math
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from dbml.core.allocation import Strategy
from dbml.experiment.analysis import (
    BUDGET_BACK_S,
    FIRST_CUT_S,
    GOODPUT_AFTER_FRACTION,
    GOODPUT_FRACTION,
    MAX_P95_MS,
    OUTAGE_RECOVERY_S,
    PEAK_P95_AFTER_DROP_MS,
    RATE_TOLERANCE,
    RECOVERY_S,
    LinkChange,
    LinkPhase,
    Outage,
    Recovery,
    SeriesPoint,
    StepResult,
    StreamLatency,
    link_at,
    outages,
    recoveries,
    stream_latency,
)
from dbml.experiment.rclpypeers import IMAGE_TYPE, RCLPY_MISSING
from dbml.experiment.roles import HOSTS, URGENT_STREAMS, RoleSpec
from dbml.experiment.runner import (
    Command,
    Helper,
    Observer,
    Recording,
    run_experiment,
    sigterm_as_interrupt,
)
from dbml.harness.ros2env import claim_domain, fastdds_shm_files, remove_fastdds_shm, ros2_child_env
from dbml.scenarios.fleet import (
    MAX_ROBOTS,
    MIN_ROBOTS,
    fleet_allocation,
    fleet_cameras,
    fleet_steps,
    urgent_robot,
)
from dbml.scenarios.teleop import MAX_RATE_HZ, MIN_RATE_HZ, ROBOTS
from dbml.testbed.bridge import read_stats
from dbml.testbed.forward import NetnsForward
from dbml.testbed.netns import (
    OPERATOR,
    TOPOLOGIES,
    TRANSPORTS,
    Network,
    TestbedError,
    privilege_problem,
)
from dbml.view.target import ViewTarget

__all__ = [
    "ALLOCATION_TOLERANCE_HZ",
    "POLICIES",
    "TOPOLOGIES",
    "TRANSPORTS",
    "URGENT_P95_MS",
    "BridgePublish",
    "Summary",
    "TestbedOptions",
    "TestbedResult",
    "parse_schedule",
    "parse_uplinks",
    "ros_env",
    "run_teleop_testbed",
]

log = logging.getLogger("dbml.testbed")

POLICIES = ("dbml", "static", "unmanaged")
ALLOCATION_TOLERANCE_HZ = 0.01
"""A fleet's allocation equals ``allocate``'s when every rate is within this (rounding)."""
CLIENT_CONFIG = '{mode: "client"}\n'
"""The roles' zenoh config under ``--topology router``: they reach others only via routers."""
MIN_STEP_S = 1.0
"""The shortest step that still times a 1 Hz stream."""
DEFAULT_UTILIZATION = 0.92
"""dbml's budget as a share of the shaped rate: TCP/IP and Ethernet headers take ~4.3 % of the
wire (measured: raw TCP gets 95.7 % of a tbf rate), the rest is margin."""
PAPER_STATIC_UTILIZATION = 1.0
"""The paper's static baseline splits the whole 11 Mbit/s: 13.1 Hz per camera."""
ZENOH_PORT = 7447
OPTIMIZER_PORT = 7448
PEER_WAIT_S = 15.0
"""How long a role waits for its peers across the namespaces before it reports ready."""
URGENT_P95_MS = 120.0
"""The mapped urgent stream's p95 bound: two camera frame times (84 KB at 11 Mbit/s: 61 ms)."""
NETNS_OF_ROLE = {"operator": "op", "optimizer": "op", "r1": "r1", "r2": "r2"}
"""The namespace of each role; a fleet's robot ``rK`` runs in its own namespace ``rK``."""
ROLES_MODULE = "dbml.experiment.roles"
RCLPY_PEERS_MODULE = "dbml.experiment.rclpypeers"
BRIDGE_MODULE = "dbml.testbed.bridge"
BRIDGE_WAIT_S = 50.0
"""How long a bridge waits for its camera's first frame (the robots start after it)."""
ROS_LOG_DIR = "ros"
"""Where in the run's folder the ROS 2 processes log (``ROS_LOG_DIR``)."""
BUILTIN_TRANSPORTS = "FASTDDS_BUILTIN_TRANSPORTS"
"""Fast DDS's choice of its built-in transports (``UDPv4``: no shared memory)."""
SHM_WATCH_S = 5.0
"""How often the Fast DDS shared memory of the run's processes is listed while they run."""


def parse_schedule(text: str) -> tuple[tuple[float, float], ...]:
    """``"0:11,20:5,40:11"`` -> ((0, 11), (20, 5), (40, 11)): seconds -> Mbit/s, increasing.

    A rate of 0 takes the link down (an outage) until the next entry; not at 0 s, since the
    roles find each other over the link before step 1.
    """
    entries: list[tuple[float, float]] = []
    for part in text.split(","):
        at, sep, rate = part.strip().partition(":")
        try:
            if not sep:
                raise ValueError(part)
            t_s, mbit = float(at), float(rate)
        except ValueError:
            raise TestbedError(
                f"--link-schedule={text!r}: {part.strip()!r} must be SECONDS:MBIT"
            ) from None
        if not (math.isfinite(t_s) and t_s >= 0):
            raise TestbedError(f"--link-schedule={text!r}: time {at!r} must be >= 0")
        if not (math.isfinite(mbit) and mbit >= 0):
            raise TestbedError(
                f"--link-schedule={text!r}: rate {rate!r} must be > 0, or 0 for link down"
            )
        if mbit == 0 and t_s == 0:
            raise TestbedError(
                f"--link-schedule={text!r}: the link must be up at 0 s (the roles meet over it)"
            )
        if entries and t_s <= entries[-1][0]:
            raise TestbedError(f"--link-schedule={text!r}: times must increase ({at!r})")
        entries.append((t_s, mbit))
    return tuple(entries)


def parse_robot_schedules(
    items: Sequence[str], robots: Sequence[str]
) -> dict[str, tuple[tuple[float, float], ...]]:
    """``["R1=0:11,20:0,30:11"]`` -> {"R1": ((0, 11), (20, 0), (30, 11))}: a robot's own radio."""
    schedules: dict[str, tuple[tuple[float, float], ...]] = {}
    for item in items:
        robot, sep, spec = item.partition("=")
        robot = robot.strip().upper()
        if not sep or robot not in robots:
            raise TestbedError(
                f"--uplink-schedule={item!r} must be ROBOT=SPEC with ROBOT in {robots}"
            )
        if robot in schedules:
            raise TestbedError(f"--uplink-schedule={item!r}: {robot} has a schedule already")
        try:
            schedules[robot] = parse_schedule(spec)
        except TestbedError as err:
            raise TestbedError(f"--uplink-schedule={item!r}: {err}") from None
    return schedules


def parse_uplinks(items: Sequence[str], robots: Sequence[str]) -> dict[str, float]:
    """``["R1=4"]`` -> {"R1": 4.0}; the robot must exist and the rate be > 0."""
    uplinks: dict[str, float] = {}
    for item in items:
        robot, sep, rate = item.partition("=")
        robot = robot.strip().upper()
        if not sep or robot not in robots:
            raise TestbedError(f"--uplink={item!r} must be ROBOT=MBIT with ROBOT in {robots}")
        try:
            mbit = float(rate)
        except ValueError:
            raise TestbedError(f"--uplink={item!r}: rate {rate!r} is not a number") from None
        if not (math.isfinite(mbit) and mbit > 0):
            raise TestbedError(f"--uplink={item!r}: rate {rate!r} must be > 0")
        uplinks[robot] = mbit
    return uplinks


@dataclass(frozen=True, slots=True, kw_only=True)
class TestbedOptions:
    """A checked testbed run: ``strategy`` and ``utilization`` resolved for the policy."""

    __test__ = False  # not a pytest test class despite the name

    policy: str = "dbml"
    link_mbit: float = 11.0
    step_seconds: float = 6.0
    link_schedule: tuple[tuple[float, float], ...] = ()
    estimate: bool = False
    uplinks_mbit: Mapping[str, float] = field(default_factory=dict)
    robot_schedules: Mapping[str, tuple[tuple[float, float], ...]] = field(default_factory=dict)
    """Per robot, its own radio's schedule (``--uplink-schedule R1=SPEC``): 0 takes only that
    robot's link down, a rate shapes its uplink at it."""
    urgent_stream: bool = False
    """R1 adds a 1,000-byte 20 Hz urgent stream twice, mapped and unmapped (see ``roles``)."""
    robots: int = len(ROBOTS)
    """Robots r1..rN, each in its own namespace (``dbml.scenarios.fleet``: two is Table 2)."""
    topology: str = TOPOLOGIES[0]
    strategy: str | None = Strategy.PAPER.value
    """None under ``unmanaged``: no optimizer runs."""
    utilization: float | None = DEFAULT_UTILIZATION
    transport: str = TRANSPORTS[0]
    """``zenoh``, or ``rclpy``: real ROS 2 (see the module's docstring)."""
    view: ViewTarget | None = None
    """``--foxglove``/``--record``: the operator's live view, its server reached from here."""

    @classmethod
    def from_flags(
        cls,
        *,
        policy: str = "dbml",
        link_mbit: float = 11.0,
        step_seconds: float = 6.0,
        link_schedule: str | None = None,
        estimate: bool = False,
        uplinks: Sequence[str] = (),
        uplink_schedules: Sequence[str] = (),
        strategy: str | None = None,
        utilization: float | None = None,
        urgent_stream: bool = False,
        robots: int = len(ROBOTS),
        topology: str = TOPOLOGIES[0],
        transport: str = TRANSPORTS[0],
        view: ViewTarget | None = None,
    ) -> TestbedOptions:
        """The options of the command line's flags; a bad one raises naming the flag."""
        if policy not in POLICIES:
            raise TestbedError(f"--policy={policy!r} is not one of: {', '.join(POLICIES)}")
        if transport not in TRANSPORTS:
            raise TestbedError(f"--transport={transport!r} is not one of: {', '.join(TRANSPORTS)}")
        if transport == "rclpy" and topology != TOPOLOGIES[0]:
            raise TestbedError(
                f"--topology={topology} is zenoh-only (a zenoh router per host): "
                "--transport rclpy meets over DDS discovery"
            )
        if transport == "rclpy" and view is not None:
            raise TestbedError(
                "--foxglove/--record with --transport rclpy: the operator is a plain rclpy "
                "node there, without dbml's view"
            )
        if transport == "rclpy" and urgent_stream:
            raise TestbedError(
                "--urgent-stream is zenoh-only (it measures zenoh's priority links): "
                "not with --transport rclpy"
            )
        if isinstance(robots, bool) or not isinstance(robots, int):
            raise TestbedError(f"--robots={robots!r} must be an integer")
        if not MIN_ROBOTS <= robots <= MAX_ROBOTS:
            raise TestbedError(f"--robots={robots!r} must be in {MIN_ROBOTS}..{MAX_ROBOTS}")
        if topology not in TOPOLOGIES:
            raise TestbedError(f"--topology={topology!r} is not one of: {', '.join(TOPOLOGIES)}")
        if urgent_stream and topology != TOPOLOGIES[0]:
            # A router forwards every class on its one link: the measurement needs peers' links.
            raise TestbedError(f"--urgent-stream needs --topology {TOPOLOGIES[0]}, not {topology}")
        if not link_mbit > 0:
            raise TestbedError(f"--link-mbit={link_mbit!r} must be > 0")
        if not step_seconds >= MIN_STEP_S:
            raise TestbedError(f"--step-seconds={step_seconds!r} must be >= 1")
        common = cls(
            policy=policy,
            link_mbit=link_mbit,
            step_seconds=step_seconds,
            link_schedule=parse_schedule(link_schedule) if link_schedule else (),
            estimate=estimate,
            uplinks_mbit=parse_uplinks(uplinks, [c.robot for c in fleet_cameras(robots)]),
            robot_schedules=parse_robot_schedules(
                uplink_schedules, [c.robot for c in fleet_cameras(robots)]
            ),
            urgent_stream=urgent_stream,
            robots=robots,
            topology=topology,
            transport=transport,
            view=view,
        )
        both = sorted(set(common.uplinks_mbit) & set(common.robot_schedules))
        if both:
            raise TestbedError(f"--uplink and --uplink-schedule both shape {both}: give one")
        if policy == "unmanaged":
            for flag, given in (
                ("--estimate", estimate),
                ("--strategy", strategy),
                ("--utilization", utilization),
            ):
                if given:
                    raise TestbedError(f"{flag} needs an optimizer: --policy=unmanaged has none")
            return replace(common, strategy=None, utilization=None)
        if policy == "static":
            if strategy not in (None, Strategy.STATIC.value):
                raise TestbedError(f"--strategy={strategy!r}: --policy=static is the static one")
            return replace(
                common,
                strategy=Strategy.STATIC.value,
                utilization=utilization or PAPER_STATIC_UTILIZATION,
            )
        lp = Strategy.LP.value
        chosen = strategy or (lp if common.uplinks_mbit else Strategy.PAPER.value)
        if chosen not in {s.value for s in Strategy}:
            raise TestbedError(
                f"--strategy={strategy!r} is not one of: {', '.join(s.value for s in Strategy)}"
            )
        if common.uplinks_mbit and chosen != lp:
            raise TestbedError(f"--uplink needs --strategy=lp (per-link limits), not {chosen!r}")
        util = DEFAULT_UTILIZATION if utilization is None else utilization
        if not 0 < util <= 1:
            raise TestbedError(f"--utilization={utilization!r} must be in (0, 1]")
        return replace(common, strategy=chosen, utilization=util)

    @property
    def steady(self) -> bool:
        """Whether the link keeps its rate the whole run."""
        return not self.robot_schedules and all(
            mbit == self.link_mbit for _, mbit in self.link_schedule
        )

    @property
    def fleet(self) -> bool:
        """More robots than the paper's two: judged by ``allocate``, not by Table 2's rows."""
        return self.robots > len(ROBOTS)


@dataclass(frozen=True, slots=True)
class UplinkUse:
    """A robot's own shaped uplink and the most it carried in a step."""

    robot: str
    capacity_mbit: float
    goodput_mbit_max: float | None


@dataclass(frozen=True, slots=True)
class BridgePublish:
    """A bridge's publishes on ``[topic]/optimized`` over rclpy (``PublishStats``)."""

    robot: str
    published: int
    dropped: int
    """Publishes the middleware refused (raised inside rclpy; counted, never passed on)."""
    max_ms: float | None
    p99_ms: float | None
    frame_ms: float
    """One frame time: the largest camera frame (84,000 bytes) on the shaped link at the run's
    slowest rate (61 ms at 11 Mbit/s), what a synchronous publish waits for at most when the
    socket in front of it is full."""

    @property
    def within_one_frame(self) -> bool:
        """No publish took longer than one frame time."""
        return self.max_ms is not None and self.max_ms <= self.frame_ms


@dataclass(frozen=True, slots=True)
class Summary:
    """A run in a few numbers, and the targets that apply to it."""

    steps: int
    max_rate_error: float | None
    latency_p50_ms_max: float | None
    latency_p95_ms_max: float | None
    lost: int
    goodput_mbit_mean: float | None
    goodput_fraction_mean: float | None
    goodput_fraction_min: float | None
    uplinks: tuple[UplinkUse, ...]
    targets: Mapping[str, bool]


def _mean(values: Sequence[float]) -> float | None:
    return sum(values) / len(values) if values else None


@dataclass(frozen=True, slots=True)
class TestbedResult:
    """A testbed run: what it measured per step, over time and after each link change."""

    __test__ = False  # not a pytest test class despite the name

    options: TestbedOptions
    run_id: str
    steps: tuple[StepResult, ...] = ()
    series: tuple[SeriesPoint, ...] = ()
    changes: tuple[LinkChange, ...] = ()
    interrupted: bool = False
    phases: tuple[LinkPhase, ...] = ()
    outages: tuple[Outage, ...] = ()
    """Per 0 Mbit phase of the schedule: the restoration after it."""
    recoveries: tuple[Recovery, ...] = ()
    """Per outage (the shared link's or a robot's own) and robot behind it: back when."""
    urgent: tuple[StreamLatency, ...] = ()
    """With ``urgent_stream``: the mapped and the unmapped copy, over the whole run."""
    expected_hz: tuple[tuple[float, ...], ...] = ()
    """A fleet under dbml on a known budget: per step, each robot's rate by ``allocate`` on
    the channels its events imply (empty otherwise: estimated budget, uplinks, two robots)."""
    """Between link changes: utilisation, p95 and losses (RFC 8867's per-phase figures)."""
    bridges: tuple[BridgePublish, ...] = ()
    """Over rclpy with bridges: how their publishes went (empty otherwise)."""
    run_dir: Path | None = None
    """The run's folder when the caller gave one (ROS logs under ``ros/``); None: removed."""
    shm_files: tuple[Path, ...] = ()
    """Over rclpy: the Fast DDS shared-memory files the run's processes owned while running."""
    shm_removed: tuple[Path, ...] = ()
    """Of those, what a killed process left and the testbed removed (a graceful end: none)."""

    def summary(self) -> Summary:
        """The run in a few numbers."""
        robots = [r for s in self.steps for r in s.robots]
        fractions = [s.goodput_mbit / s.link_mbit for s in self.steps if s.link_mbit > 0]
        return Summary(
            steps=len(self.steps),
            max_rate_error=max(
                (
                    abs(r.delivered_hz - r.allocated_hz) / r.allocated_hz
                    for r in robots
                    if r.allocated_hz
                ),
                default=None,
            ),
            latency_p50_ms_max=max(
                (r.latency_p50_ms for r in robots if r.latency_p50_ms is not None), default=None
            ),
            latency_p95_ms_max=max(
                (r.latency_p95_ms for r in robots if r.latency_p95_ms is not None), default=None
            ),
            lost=sum(r.lost for r in robots),
            goodput_mbit_mean=_mean([s.goodput_mbit for s in self.steps]),
            goodput_fraction_mean=_mean(fractions),
            goodput_fraction_min=min(fractions, default=None),
            uplinks=tuple(
                UplinkUse(
                    robot,
                    capacity,
                    max((r.goodput_mbit for r in robots if r.robot == robot), default=None),
                )
                for robot, capacity in sorted(self.options.uplinks_mbit.items())
            ),
            targets=self.targets(),
        )

    def urgent_robots(self) -> tuple[str | None, ...]:
        """Per step, the robot whose events are the most urgent (None: all calm)."""
        cameras = fleet_cameras(self.options.robots)
        return tuple(
            None if (k := urgent_robot(step)) is None else cameras[k].robot
            for step in fleet_steps(self.options.robots)[: len(self.steps)]
        )

    def allocation_matches(self) -> bool | None:
        """Whether every step's allocation was ``allocate``'s (None: nothing to compare)."""
        if not self.expected_hz:
            return None
        return all(
            r.allocated_hz is not None and abs(r.allocated_hz - hz) <= ALLOCATION_TOLERANCE_HZ
            for step, expected in zip(self.steps, self.expected_hz, strict=False)
            for r, hz in zip(step.robots, expected, strict=True)
        )

    def targets(self) -> dict[str, bool]:
        """The expectations that apply to this run (policy dbml; urgent stream: any), by name."""
        mapped = next((u for u in self.urgent if u.name == "mapped"), None)
        urgent = {}
        if mapped is not None:
            urgent[f"urgent_p95_under_{URGENT_P95_MS:g}ms"] = (
                mapped.latency_p95_ms is not None and mapped.latency_p95_ms < URGENT_P95_MS
            )
        if self.options.policy != "dbml" or not self.steps:
            return urgent
        robots = [r for s in self.steps for r in s.robots]
        targets: dict[str, bool] = dict(urgent)
        # a token bucket's bound: one message per channel over the budget in any window, and
        # the target's name says so (it is not the budget itself)
        slack_mbit = sum(c.size_bytes for c in fleet_cameras(self.options.robots)) * 8e-6
        if self.bridges:  # over rclpy: a full link never stalls nor fails the bridges
            targets["bridge_publish_within_one_frame_time"] = all(
                b.within_one_frame for b in self.bridges
            )
            targets["bridge_publish_never_refused"] = all(b.dropped == 0 for b in self.bridges)
        returns: dict[tuple[str, float], bool] = {}  # per (scope, return): every robot back
        for r in self.recoveries:
            which = (r.scope, r.back_s)
            returns[which] = returns.get(which, True) and r.back_within(OUTAGE_RECOVERY_S)
        for (scope, back_s), every in returns.items():
            within = f"within_{OUTAGE_RECOVERY_S:g}s"
            targets[f"every_robot_back_{within}_after_{scope}_outage_at_{back_s:g}s"] = every
        for outage in self.outages:  # the release after an outage, each window on its budget
            over = outage.release_over_budget_mbit
            key = f"budget_kept_within_one_message_per_channel_after_outage_at_{outage.end_s:g}s"
            targets[key] = over is not None and over <= slack_mbit
        matches = self.allocation_matches()
        if matches is not None:
            targets["allocation_equals_allocate"] = matches
        if self.options.steady:
            targets[f"delivered_within_{RATE_TOLERANCE * 100:g}pct"] = all(
                r.within_rate() for r in robots
            )
            targets[f"p95_under_{MAX_P95_MS:g}ms"] = all(
                r.latency_p95_ms is not None and r.latency_p95_ms < MAX_P95_MS for r in robots
            )
            targets["nothing_lost"] = all(r.lost == 0 for r in robots)
            if not self.options.uplinks_mbit:  # a capped uplink leaves the shared link underused
                targets[f"goodput_at_least_{GOODPUT_FRACTION * 100:g}pct"] = all(
                    s.goodput_mbit >= GOODPUT_FRACTION * s.link_mbit for s in self.steps
                )
        for change in self.changes:
            if change.drop:
                key = f"recovered_within_{RECOVERY_S:g}s_after_{change.t_s:g}s"
                targets[key] = change.recovery_s is not None and change.recovery_s <= RECOVERY_S
            else:
                key = f"budget_back_within_{BUDGET_BACK_S:g}s_after_{change.t_s:g}s"
                reached = change.budget_recovery_s
                targets[key] = reached is not None and reached <= BUDGET_BACK_S
            if self.options.estimate and change.drop:
                at = f"after_{change.t_s:g}s"
                cut, p95 = change.first_cut_s, change.max_latency_p95_ms
                targets[f"first_cut_within_{FIRST_CUT_S * 1000:g}ms_{at}"] = (
                    cut is not None and cut <= FIRST_CUT_S
                )
                targets[f"peak_p95_under_{PEAK_P95_AFTER_DROP_MS:g}ms_{at}"] = (
                    p95 is not None and p95 < PEAK_P95_AFTER_DROP_MS
                )
                share = change.goodput_share_after
                targets[f"goodput_at_least_{GOODPUT_AFTER_FRACTION * 100:g}pct_{at}"] = (
                    share is not None and share >= GOODPUT_AFTER_FRACTION
                )
        return targets


def _netns_of(role: str) -> str:
    """The namespace a role runs in: the operator's side, or the robot's own."""
    return NETNS_OF_ROLE.get(role, role)


def _router_ep(network: Network, host: str) -> str:
    return f"tcp/{network.hosts[host].address}:{ZENOH_PORT}"


def _routers(network: Network) -> tuple[Helper, ...]:
    """``--topology router``: a router per host, each robot's connected to the operator's."""
    hub = _router_ep(network, "op")
    return tuple(
        Helper(
            name=f"router-{host}",
            argv=tuple(
                network.exec_argv(
                    host,
                    [
                        sys.executable,
                        "-m",
                        "dbml.testbed.router",
                        "--listen",
                        _router_ep(network, host),
                        *(["--connect", hub] if host != "op" else []),
                    ],
                )
            ),
        )
        for host in ("op", *network.robots)
    )


def _base_spec(options: TestbedOptions) -> RoleSpec:
    """What every role of a run is told, whatever its transport: the options' scenario."""
    return RoleSpec(
        step_s=options.step_seconds,
        managed=options.policy != "unmanaged",
        link_mbit=options.link_mbit,
        utilization=options.utilization or 1.0,
        strategy=options.strategy or Strategy.PAPER.value,
        estimate=options.estimate,
        uplinks_mbit=dict(options.uplinks_mbit),
        peer_wait_s=PEER_WAIT_S,
        robots=options.robots,
    )


def _specs(
    network: Network, options: TestbedOptions, *, config_file: str | None = None
) -> dict[str, RoleSpec]:
    """Explicit endpoints: robots connect to the operator's side, where the optimizer runs.

    Under ``--topology router`` every role is instead a client (``config_file``) of its host's
    router, and only the routers cross the shaped link.
    """
    operator_ep = f"tcp/{network.hosts['op'].address}:{ZENOH_PORT}"
    optimizer_ep = f"tcp/{network.hosts['op'].address}:{OPTIMIZER_PORT}"
    managed = options.policy != "unmanaged"
    base = replace(_base_spec(options), urgent_stream=options.urgent_stream)
    robots = [camera.robot.lower() for camera in fleet_cameras(options.robots)]
    if options.topology == "router":
        client = replace(base, config_file=config_file)
        specs = {
            role: replace(client, host=HOSTS[role], connect=(operator_ep,))
            for role in ("operator", "optimizer")
            if role == "operator" or managed
        }
        for role in robots:
            host = HOSTS.get(role, f"robot-{role}")
            specs[role] = replace(client, host=host, connect=(_router_ep(network, role),))
        return specs
    specs = {"operator": replace(base, host=HOSTS["operator"], listen=(operator_ep,))}
    if managed:
        specs["optimizer"] = replace(
            base, host=HOSTS["optimizer"], listen=(optimizer_ep,), connect=(operator_ep,)
        )
    for role in robots:
        specs[role] = replace(
            base,
            host=HOSTS.get(role, f"robot-{role}"),
            listen=(f"tcp/{network.hosts[role].address}:{ZENOH_PORT}",),
            connect=(operator_ep, *([optimizer_ep] if managed else [])),
        )
    return specs


VIEW_PORT = 8765
"""The operator's live view inside its namespace (a fresh one: the port is free there)."""


def _with_view(spec: RoleSpec, view: ViewTarget) -> RoleSpec:
    """The operator's spec with its live view: its server inside its namespace."""
    inside = None if view.endpoint is None else f"127.0.0.1:{VIEW_PORT}"
    return replace(spec, foxglove=inside, record=view.record_flag)


@contextlib.contextmanager
def _forward_view(network: Network, view: ViewTarget) -> Iterator[None]:
    """``--foxglove [HOST:]PORT`` on this machine, leading to the operator's view inside."""
    if view.endpoint is None:
        yield
        return
    try:
        forward = NetnsForward(
            network.netns_path(OPERATOR),
            host=view.endpoint.host,
            port=view.endpoint.port,
            target_port=VIEW_PORT,
        ).start()
    except OSError as err:
        raise TestbedError(f"--foxglove={view.endpoint}: {err}") from None
    log.info("live view: ws://%s:%d (the operator's, forwarded)", view.endpoint.host, forward.port)
    try:
        yield
    finally:
        forward.close()


def _change_link(
    network: Network, options: TestbedOptions, t0: float, stop: threading.Event
) -> None:
    """Apply the shared link's schedule and each robot's own, in time order, until ``stop``."""
    changes = [(at, OPERATOR, mbit) for at, mbit in options.link_schedule]
    for robot, schedule in options.robot_schedules.items():
        changes += [(at, robot.lower(), mbit) for at, mbit in schedule]
    for at, host, mbit in sorted(changes):
        if at <= 0:
            continue
        if stop.wait(max(0.0, t0 + at - time.time())):
            return
        try:
            if mbit == 0:
                network.take_link_down(host=host)
            else:
                network.set_link_rate(mbit, host=host)
        except TestbedError:
            if not stop.is_set():  # else the network is being torn down
                raise


def _expected_hz(
    options: TestbedOptions, steps: Sequence[StepResult]
) -> tuple[tuple[float, ...], ...]:
    """A fleet under dbml on a known budget: ``allocate`` on each step's implied channels."""
    known = options.policy == "dbml" and not options.estimate and not options.uplinks_mbit
    if not (options.fleet and known and options.strategy and options.utilization):
        return ()
    cameras = fleet_cameras(options.robots)
    return tuple(
        fleet_allocation(
            event_step,
            cameras,
            link_mbit=step.link_mbit,
            utilization=options.utilization,
            strategy=options.strategy,
        )
        for event_step, step in zip(fleet_steps(options.robots), steps, strict=False)
    )


def _urgent_index(options: TestbedOptions, t_s: float) -> int:
    """The robot whose channel has the highest priority ``t_s`` into the run (first on a tie)."""
    steps = fleet_steps(options.robots)
    step = steps[min(len(steps) - 1, max(0, int(t_s // options.step_seconds)))]
    return urgent_robot(step) or 0


def ros_env(network: Network, host: str, *, domain_id: int, log_dir: Path) -> dict[str, str]:
    """The environment of a ROS 2 process in ``host``'s namespace (``"op"`` or a robot's).

    ``ros2_child_env``'s (the run's domain, ROS logs in ``log_dir``, the fast-discovery Fast
    DDS profile) and what discovery needs across the router. Fast DDS finds its peers by
    multicast, which stays in its own segment (every namespace is one, and the router forwards
    no multicast): the processes of one namespace meet that way, those of two never do. So a
    robot's processes also announce themselves by unicast to the operator's address
    (``ROS_STATIC_PEERS``); the operator's, having heard them, answer and keep announcing to
    them, so one address on the robots' side is all it takes (measured: a robot's two
    publishers matched in 0.1-0.4 s, held through 40 s with the 3-s lease, and after an outage
    the robots' periodic announcements find the operator again). Robots are not told of each
    other: nothing of one robot is for another. The discovery range is the default
    (``SUBNET``), whatever this environment says, and a discovery server is not used.

    Fast DDS's shared-memory transport is off (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``), as zenoh's
    is in the testbed: ``/dev/shm`` is one for every namespace, so it is a path around the
    shaped link, and with it on, runs whose processes all ended cleanly (exit 0) still left
    port segments there (``fastdds_port7000``, ``fastdds_port7661``, ... of the operator's
    side). With UDP only, a run's processes make no ``/dev/shm/fastdds_*`` at all, and a
    robot's camera reaches its bridge over the namespace's own interfaces.
    """
    env = ros2_child_env(domain_id=domain_id, log_dir=log_dir)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
    env[BUILTIN_TRANSPORTS] = "UDPv4"
    for name in ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "ROS_LOCALHOST_ONLY"):
        env.pop(name, None)
    if host != "op":
        env["ROS_STATIC_PEERS"] = network.hosts["op"].address
    return env


def _zenoh_command(network: Network) -> Command:
    """A zenoh role's argv, run in its namespace (its environment: this process's)."""

    def command(role: str, argv: list[str]) -> tuple[list[str], Mapping[str, str] | None]:
        return network.exec_argv(_netns_of(role), argv), None

    return command


def _frame_ms(size_bytes: int, mbit: float) -> float:
    """One frame of ``size_bytes`` on a link of ``mbit``, in ms."""
    return size_bytes * 8 / (mbit * 1e6) * 1e3


@dataclass(frozen=True, slots=True)
class _RclpyRun:
    """The rclpy run's processes: the roles' specs and command, the bridges, their files."""

    specs: dict[str, RoleSpec]
    command: Command
    helpers: tuple[Helper, ...]
    stats: dict[str, Path]
    """Each bridge's statistics file, by robot (``R1``)."""


def _rclpy_run(
    network: Network, options: TestbedOptions, *, domain_id: int, run_dir: Path
) -> _RclpyRun:
    """Plain rclpy cameras and operator, dbml's bridges and optimizer, in the namespaces.

    As ``dbml demo teleop --transport rclpy``, each role in its host's namespace with
    :func:`ros_env`'s environment; the bridges (managed policies) start before the robots.
    """
    log_dir = run_dir / ROS_LOG_DIR
    envs = {
        host: ros_env(network, host, domain_id=domain_id, log_dir=log_dir) for host in network.hosts
    }
    cameras = fleet_cameras(options.robots)
    robots = [camera.robot.lower() for camera in cameras]
    managed = options.policy != "unmanaged"
    base = replace(_base_spec(options), transport="rclpy", domain_id=domain_id)
    specs = {"operator": replace(base, host=HOSTS["operator"])}
    if managed:
        specs["optimizer"] = replace(base, host=HOSTS["optimizer"])
    for role in robots:
        specs[role] = replace(base, host=HOSTS.get(role, f"robot-{role}"))
    peers = {"operator", *robots}

    def command(role: str, argv: list[str]) -> tuple[list[str], Mapping[str, str] | None]:
        if role in peers:  # the same protocol, played by plain rclpy nodes
            argv = [RCLPY_PEERS_MODULE if a == ROLES_MODULE else a for a in argv]
            if role == "operator":
                argv.append("--sample-info")  # DDS's sequence numbers and send times
        host = _netns_of(role)
        return network.exec_argv(host, argv), envs[host]

    stats = {camera.robot: run_dir / f"bridge-{camera.robot.lower()}.json" for camera in cameras}
    helpers = tuple(
        Helper(
            name=f"bridge-{role}",
            argv=tuple(
                network.exec_argv(
                    role,
                    [
                        sys.executable,
                        "-m",
                        BRIDGE_MODULE,
                        str(stats[camera.robot]),
                        camera.topic,
                        "--min-hz",
                        f"{MIN_RATE_HZ:g}",
                        "--max-hz",
                        f"{MAX_RATE_HZ:g}",
                        "--type",
                        IMAGE_TYPE,
                        "--wait",
                        f"{BRIDGE_WAIT_S:g}",
                        "--host",
                        HOSTS.get(role, f"robot-{role}"),
                        "--transport",
                        "rclpy",
                        "--domain-id",
                        str(domain_id),
                    ],
                )
            ),
            env=envs[role],
            before=robots[0],
        )
        for role, camera in zip(robots, cameras, strict=True)
        if managed
    )
    return _RclpyRun(specs, command, helpers, stats if managed else {})


def _bridges(options: TestbedOptions, stats: Mapping[str, Path]) -> tuple[BridgePublish, ...]:
    """What each bridge wrote of its publishes on ``[topic]/optimized`` (none: not known)."""
    first = link_at(options.link_schedule, 0.0, options.link_mbit)
    slowest = min([first, *(mbit for _, mbit in options.link_schedule if mbit > 0)])
    frame_ms = _frame_ms(max(c.size_bytes for c in fleet_cameras(options.robots)), slowest)
    found = []
    for robot, path in stats.items():
        rows = [r for r in read_stats(path) if str(r.get("topic", "")).endswith("/optimized")]
        if not rows:
            continue
        maxima = [float(r["max_ms"]) for r in rows if r.get("max_ms") is not None]
        p99s = [float(r["p99_ms"]) for r in rows if r.get("p99_ms") is not None]
        found.append(
            BridgePublish(
                robot=robot,
                published=sum(int(r.get("published", 0)) for r in rows),
                dropped=sum(int(r.get("dropped", 0)) for r in rows),
                max_ms=max(maxima, default=None),
                p99_ms=max(p99s, default=None),
                frame_ms=frame_ms,
            )
        )
    return tuple(found)


def _namespace_pids(network: Network) -> set[int]:
    """Every process in the run's namespaces now (``ip netns pids``)."""
    pids: set[int] = set()
    for host in network.hosts.values():
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            listed = subprocess.run(
                ["ip", "netns", "pids", host.netns],
                capture_output=True,
                text=True,
                check=False,
                timeout=5,
            )
            pids.update(int(pid) for pid in listed.stdout.split() if pid.isdigit())
    return pids


def _watch_shm(network: Network, stop: threading.Event, into: set[Path]) -> None:
    """List the Fast DDS shared memory of the run's processes now and then, until ``stop``."""
    while True:
        into.update(fastdds_shm_files(_namespace_pids(network)))
        if stop.wait(SHM_WATCH_S):
            return


def run_teleop_testbed(
    options: TestbedOptions,
    *,
    observe: Observer | None = None,
    run_dir: Path | None = None,
) -> TestbedResult:
    """Build the network, run the roles inside, remove it all; ``observe`` sees every report.

    ``run_dir``: the run's folder, kept (over rclpy its ROS logs under ``ros/`` and each
    bridge's publish statistics); None: a temporary one, removed at the end.
    """
    problem = privilege_problem()
    if problem is not None:
        raise TestbedError(f"dbml testbed needs root to build network namespaces: {problem}")
    rclpy = options.transport == "rclpy"
    if rclpy and importlib.util.find_spec("rclpy") is None:
        raise TestbedError(RCLPY_MISSING)
    cameras = fleet_cameras(options.robots)
    network = Network(
        robots=tuple(camera.robot.lower() for camera in cameras),
        link_mbit=link_at(options.link_schedule, 0.0, options.link_mbit),
        uplinks_mbit={
            robot.lower(): mbit
            for robot, mbit in {
                **options.uplinks_mbit,
                **{
                    r: link_at(own, 0.0, options.link_mbit)
                    for r, own in options.robot_schedules.items()
                },
            }.items()
        },
    )
    recording = Recording(None, (), (), interrupted=True)
    router = options.topology == "router"
    stats: dict[str, Path] = {}
    shm: set[Path] = set()
    removed: list[Path] = []
    bridges: tuple[BridgePublish, ...] = ()
    with (
        sigterm_as_interrupt(),
        contextlib.suppress(KeyboardInterrupt),
        tempfile.TemporaryDirectory(prefix="dbml-testbed-") as scratch,
        contextlib.ExitStack() as run,
    ):
        folder = Path(scratch) if run_dir is None else run_dir
        folder.mkdir(parents=True, exist_ok=True)
        client_config = f"{scratch}/client.json5"
        with open(client_config, "w", encoding="utf-8") as config:
            config.write(CLIENT_CONFIG)
        try:
            network.build()
            specs = _specs(network, options, config_file=client_config if router else None)
            if options.view is not None:
                specs["operator"] = _with_view(specs["operator"], options.view)
                run.enter_context(_forward_view(network, options.view))
            helpers = _routers(network) if router else ()
            command = _zenoh_command(network)
            if rclpy:
                ros = _rclpy_run(
                    network, options, domain_id=run.enter_context(claim_domain()), run_dir=folder
                )
                specs, command, helpers, stats = ros.specs, ros.command, ros.helpers, ros.stats

            def on_start(t0: float, stop: threading.Event) -> None:
                watch = None
                if rclpy:  # the processes' shared memory, for what a killed one leaves
                    watch = threading.Thread(
                        target=_watch_shm, args=(network, stop, shm), name="shm", daemon=True
                    )
                    watch.start()
                _change_link(network, options, t0, stop)
                if watch is not None:
                    watch.join()

            recording = run_experiment(
                specs,
                what="testbed",
                command=command,
                observe=observe,
                on_start=on_start,
                helpers=helpers,
            )
        finally:
            try:
                network.close()
            finally:  # what a killed ROS 2 process left (one that ended gracefully, nothing)
                removed = remove_fastdds_shm(sorted(shm))
                bridges = _bridges(options, stats)
    if removed:
        log.warning("removed %d Fast DDS shared-memory files of killed processes", len(removed))
    result = TestbedResult(
        options,
        network.run_id,
        interrupted=recording.interrupted,
        bridges=bridges,
        run_dir=run_dir,
        shm_files=tuple(sorted(shm)),
        shm_removed=tuple(removed),
    )
    if recording.t0 is None:
        return result
    analysis = recording.analyse(
        step_s=options.step_seconds,
        link_mbit=options.link_mbit,
        schedule=options.link_schedule,
        robots=[camera.robot for camera in cameras],
    )
    return replace(
        result,
        steps=analysis.steps,
        series=analysis.series,
        changes=analysis.changes,
        phases=analysis.phases,
        outages=outages(
            recording.arrivals,
            recording.ticks,
            robots=[camera.robot for camera in cameras],
            t0=recording.t0,
            schedule=options.link_schedule,
            urgent_at=lambda t_s: _urgent_index(options, t_s),
        ),
        recoveries=recoveries(
            recording.arrivals,
            recording.ticks,
            robots=[camera.robot for camera in cameras],
            t0=recording.t0,
            end_s=len(analysis.steps) * options.step_seconds,
            schedule=options.link_schedule,
            robot_schedules=options.robot_schedules,
        ),
        expected_hz=_expected_hz(options, analysis.steps),
        urgent=tuple(
            stream_latency(
                recording.arrivals, len(cameras) + k, name="mapped" if s.mapped else "unmapped"
            )
            for k, s in enumerate(URGENT_STREAMS)
            if options.urgent_stream
        ),
    )
