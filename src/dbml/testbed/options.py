"""``dbml testbed teleop``'s options: the flags, checked and converted once.

``TestbedOptions.from_flags`` takes the command line's values (strings, as the flags give them)
and turns them into enums and registry entries, each bad one refused naming its flag: the
policy, the transport (one the testbed lays out: ``OFFERS``, by the way its processes meet), the
topology and the strategy; the link's schedule, the uplinks and each robot's own schedule.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from dbml.core.allocation import Strategy
from dbml.core.errors import ConfigError
from dbml.estimator.designs import DEFAULT_DESIGN, Design
from dbml.experiment.spec import Frames
from dbml.scenarios.fleet import MAX_ROBOTS, MIN_ROBOTS, fleet_cameras
from dbml.scenarios.teleop import ROBOTS
from dbml.scenarios.traces import LinkTrace, load_trace
from dbml.testbed.netns import TestbedError, shaper_queue_bytes
from dbml.transports.registry import TRANSPORTS as REGISTRY
from dbml.transports.registry import Discovery, TransportEntry
from dbml.view.target import ViewTarget

__all__ = [
    "DEFAULT_UTILIZATION",
    "MIN_STEP_S",
    "OFFERS",
    "PAPER_STATIC_UTILIZATION",
    "POLICIES",
    "TOPOLOGIES",
    "TRANSPORTS",
    "Offers",
    "Policy",
    "TestbedOptions",
    "Topology",
    "parse_robot_schedules",
    "parse_schedule",
    "parse_uplinks",
]

MIN_STEP_S = 1.0
"""The shortest step that still times a 1 Hz stream."""
DEFAULT_UTILIZATION = 0.92
"""dbml's budget as a share of the shaped rate: TCP/IP and Ethernet headers take ~4.3 % of the
wire (measured: raw TCP gets 95.7 % of a tbf rate), the rest is margin."""
PAPER_STATIC_UTILIZATION = 1.0
"""The paper's static baseline splits the whole 11 Mbit/s: 13.1 Hz per camera."""


class Policy(enum.StrEnum):
    """Who sets the rates: dbml's optimizer, the paper's static split, or nobody."""

    DBML = "dbml"
    STATIC = "static"
    UNMANAGED = "unmanaged"


class Topology(enum.StrEnum):
    """How a testbed's zenoh sessions meet.

    As peers on explicit endpoints (the default), or through a zenoh router per host meshed
    across the shaped link, as ROS 2 fleets run rmw_zenoh's.
    """

    PEER = "peer"
    ROUTER = "router"


POLICIES = tuple(policy.value for policy in Policy)
TOPOLOGIES = tuple(topology.value for topology in Topology)


@dataclass(frozen=True, slots=True, kw_only=True)
class Offers:
    """What the testbed offers over one way of meeting, checked against the flags."""

    topologies: tuple[Topology, ...]
    priority_links: bool
    """Whether ``--urgent-stream`` can run (it measures zenoh's priority links)."""
    live_view: bool
    """Whether the operator is dbml's, with its view (``--foxglove``, ``--record``)."""
    meets_over: str
    operator: str
    """Who plays the operator, for a message."""


OFFERS: Mapping[Discovery, Offers] = {
    Discovery.ZENOH: Offers(
        topologies=tuple(Topology),
        priority_links=True,
        live_view=True,
        meets_over="zenoh",
        operator="dbml's operator",
    ),
    Discovery.DDS: Offers(
        topologies=(Topology.PEER,),
        priority_links=False,
        live_view=False,
        meets_over="DDS discovery",
        operator="a plain rclpy node",
    ),
}
"""The ways of meeting the testbed lays out (``testbed.layout.LAYOUTS``), and what each offers."""
TRANSPORTS = tuple(name for name, entry in REGISTRY.items() if entry.discovery in OFFERS)
"""What a testbed's processes speak: zenoh (dbml's own roles, the default) or real ROS 2 through
rclpy (plain rclpy cameras and operator, dbml's bridges and optimizer, over Fast DDS)."""


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


def _trace(path: str | None, schedule: str | None) -> LinkTrace | None:
    """``--link-trace``'s trace, checked for what the testbed can replay."""
    if path is None:
        return None
    if schedule:
        raise TestbedError("--link-trace and --link-schedule both set the link: give one")
    try:
        trace = load_trace(path)
    except ConfigError as err:
        raise TestbedError(f"--link-trace={path!r}: {err}") from None
    if trace.impaired:
        raise TestbedError(
            f"--link-trace={path!r}: its entries ask for loss, delay or jitter, which need "
            "netem (sch_netem); the testbed replays capacity only"
        )
    if trace.first_up_mbit is None:
        raise TestbedError(f"--link-trace={path!r}: the link is never up")
    return trace


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

    policy: Policy = Policy.DBML
    link_mbit: float = 11.0
    step_seconds: float = 6.0
    link_schedule: tuple[tuple[float, float], ...] = ()
    link_trace: LinkTrace | None = None
    """``--link-trace``: the recorded trace ``link_schedule`` was made of (its every change)."""
    estimate: bool = False
    estimator_design: Design = DEFAULT_DESIGN
    uplinks_mbit: Mapping[str, float] = field(default_factory=dict)
    robot_schedules: Mapping[str, tuple[tuple[float, float], ...]] = field(default_factory=dict)
    """Per robot, its own radio's schedule (``--uplink-schedule R1=SPEC``): 0 takes only that
    robot's link down, a rate shapes its uplink at it."""
    urgent_stream: bool = False
    """R1 adds a 1,000-byte 20 Hz urgent stream twice, mapped and unmapped (see ``roles``)."""
    robots: int = len(ROBOTS)
    """Robots r1..rN, each in its own namespace (``dbml.scenarios.fleet``: two is Table 2)."""
    topology: Topology = Topology.PEER
    strategy: Strategy | None = Strategy.PAPER
    """None under ``unmanaged``: no optimizer runs."""
    utilization: float | None = DEFAULT_UTILIZATION
    transport: TransportEntry = REGISTRY["zenoh"]
    """``zenoh``, or ``rclpy``: real ROS 2 (see ``rclpy_layout``)."""
    view: ViewTarget | None = None
    """``--foxglove``/``--record``: the operator's live view, its server reached from here."""
    frames: Frames = Frames.SYNTHETIC
    """``--frames photos``: cameras over real photographs, as JPEG (``dbml.runtime.camera``)."""
    ladder: bool = True
    """With photos: rate and quality together (False, ``--rate-only``: one JPEG quality)."""

    @classmethod
    def from_flags(
        cls,
        *,
        policy: str = Policy.DBML.value,
        link_mbit: float = 11.0,
        step_seconds: float = 6.0,
        link_schedule: str | None = None,
        link_trace: str | None = None,
        estimate: bool = False,
        estimator_design: str = DEFAULT_DESIGN.value,
        uplinks: Sequence[str] = (),
        uplink_schedules: Sequence[str] = (),
        strategy: str | None = None,
        utilization: float | None = None,
        urgent_stream: bool = False,
        robots: int = len(ROBOTS),
        topology: str = TOPOLOGIES[0],
        transport: str = TRANSPORTS[0],
        view: ViewTarget | None = None,
        frames: str = Frames.SYNTHETIC.value,
        rate_only: bool = False,
    ) -> TestbedOptions:
        """The options of the command line's flags; a bad one raises naming the flag."""
        if frames not in {f.value for f in Frames}:
            raise TestbedError(f"--frames={frames!r} is not one of: synthetic, photos")
        if Frames(frames) is Frames.PHOTOS and (transport != "zenoh" or policy != "dbml"):
            raise TestbedError(
                "--frames photos runs dbml's own roles: --transport zenoh and --policy dbml"
            )
        if rate_only and Frames(frames) is not Frames.PHOTOS:
            raise TestbedError("--rate-only compares real frames: it needs --frames photos")
        if policy not in POLICIES:
            raise TestbedError(f"--policy={policy!r} is not one of: {', '.join(POLICIES)}")
        if transport not in TRANSPORTS:
            raise TestbedError(f"--transport={transport!r} is not one of: {', '.join(TRANSPORTS)}")
        entry = REGISTRY[transport]
        offers = OFFERS[entry.discovery]
        if topology not in TOPOLOGIES:
            raise TestbedError(f"--topology={topology!r} is not one of: {', '.join(TOPOLOGIES)}")
        if topology not in offers.topologies:
            raise TestbedError(
                f"--topology={topology} is zenoh-only (a zenoh router per host): "
                f"--transport {transport} meets over {offers.meets_over}"
            )
        if not offers.live_view and view is not None:
            raise TestbedError(
                f"--foxglove/--record with --transport {transport}: the operator is "
                f"{offers.operator} there, without dbml's view"
            )
        if not offers.priority_links and urgent_stream:
            raise TestbedError(
                "--urgent-stream is zenoh-only (it measures zenoh's priority links): "
                f"not with --transport {transport}"
            )
        if isinstance(robots, bool) or not isinstance(robots, int):
            raise TestbedError(f"--robots={robots!r} must be an integer")
        if not MIN_ROBOTS <= robots <= MAX_ROBOTS:
            raise TestbedError(f"--robots={robots!r} must be in {MIN_ROBOTS}..{MAX_ROBOTS}")
        if urgent_stream and Topology(topology) is not Topology.PEER:
            # A router forwards every class on its one link: the measurement needs peers' links.
            raise TestbedError(f"--urgent-stream needs --topology {TOPOLOGIES[0]}, not {topology}")
        if not link_mbit > 0:
            raise TestbedError(f"--link-mbit={link_mbit!r} must be > 0")
        if estimator_design not in {d.value for d in Design}:
            raise TestbedError(
                f"--estimator-design={estimator_design!r} is not one of: "
                f"{', '.join(d.value for d in Design)}"
            )
        trace = _trace(link_trace, link_schedule)
        if not step_seconds >= MIN_STEP_S:
            raise TestbedError(f"--step-seconds={step_seconds!r} must be >= 1")
        common = cls(
            policy=Policy(policy),
            link_mbit=link_mbit,
            step_seconds=step_seconds,
            link_schedule=(
                trace.schedule
                if trace is not None
                else parse_schedule(link_schedule)
                if link_schedule
                else ()
            ),
            link_trace=trace,
            estimate=estimate,
            estimator_design=Design(estimator_design),
            uplinks_mbit=parse_uplinks(uplinks, [c.robot for c in fleet_cameras(robots)]),
            robot_schedules=parse_robot_schedules(
                uplink_schedules, [c.robot for c in fleet_cameras(robots)]
            ),
            urgent_stream=urgent_stream,
            robots=robots,
            topology=Topology(topology),
            transport=entry,
            view=view,
            frames=Frames(frames),
            ladder=not rate_only,
        )
        both = sorted(set(common.uplinks_mbit) & set(common.robot_schedules))
        if both:
            raise TestbedError(f"--uplink and --uplink-schedule both shape {both}: give one")
        if common.policy is Policy.UNMANAGED:
            for flag, given in (
                ("--estimate", estimate),
                ("--strategy", strategy),
                ("--utilization", utilization),
            ):
                if given:
                    raise TestbedError(f"{flag} needs an optimizer: --policy=unmanaged has none")
            return replace(common, strategy=None, utilization=None)
        if common.policy is Policy.STATIC:
            if strategy not in (None, Strategy.STATIC.value):
                raise TestbedError(f"--strategy={strategy!r}: --policy=static is the static one")
            return replace(
                common,
                strategy=Strategy.STATIC,
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
        return replace(common, strategy=Strategy(chosen), utilization=util)

    @property
    def steady(self) -> bool:
        """Whether the link keeps its rate the whole run."""
        return not self.robot_schedules and all(
            mbit == self.link_mbit for _, mbit in self.link_schedule
        )

    @property
    def link_queue_bytes(self) -> int | None:
        """The shared link's queue in bytes through a recorded trace; None: the shaper's own.

        A radio's buffer does not shrink in a fade: a trace's link keeps the queue its usual
        (median) rate fills in the shaper's 200 ms, as OpenNetLab's gym, where its traces come
        from, keeps one drop-tail queue of fixed bytes. A schedule's link is re-shaped at each
        rate (``Network(queue_bytes=None)``).
        """
        usual = None if self.link_trace is None else self.link_trace.median_up_mbit
        return None if usual is None else shaper_queue_bytes(usual)

    @property
    def fleet(self) -> bool:
        """More robots than the paper's two: judged by ``allocate``, not by Table 2's rows."""
        return self.robots > len(ROBOTS)
