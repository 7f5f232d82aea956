"""``dbml testbed teleop``: the paper's teleoperation scenario over a real, shaped network.

Robots R1 and R2 and the operator are network namespaces; their traffic to the operator shares
one ``tc``-shaped link (and, with ``--uplink``, a robot's own slower uplink). The experiment's
roles run inside: zenoh on explicit endpoints with shared memory off, the optimizer on the
operator's side (policies ``dbml`` and ``static``; none under ``unmanaged``). The link's rate
changes on schedule; the result holds, per step and robot, allocated and delivered rates,
latency, losses and goodput, the recovery after each link change, and the targets that apply.

Every namespace and process is removed at the end, also on error, Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from dbml.core.allocation import Strategy
from dbml.experiment.analysis import (
    BUDGET_BACK_S,
    FIRST_CUT_S,
    GOODPUT_AFTER_FRACTION,
    GOODPUT_FRACTION,
    MAX_P95_MS,
    PEAK_P95_AFTER_DROP_MS,
    RATE_TOLERANCE,
    RECOVERY_S,
    LinkChange,
    LinkPhase,
    SeriesPoint,
    StepResult,
    StreamLatency,
    link_at,
    stream_latency,
)
from dbml.experiment.roles import HOSTS, URGENT_STREAMS, RoleSpec
from dbml.experiment.runner import Observer, Recording, run_experiment, sigterm_as_interrupt
from dbml.scenarios.teleop import ROBOTS
from dbml.testbed.netns import Network, TestbedError, privilege_problem

__all__ = [
    "POLICIES",
    "URGENT_P95_MS",
    "Summary",
    "TestbedOptions",
    "TestbedResult",
    "parse_schedule",
    "parse_uplinks",
    "run_teleop_testbed",
]

POLICIES = ("dbml", "static", "unmanaged")
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


def parse_schedule(text: str) -> tuple[tuple[float, float], ...]:
    """``"0:11,20:5,40:11"`` -> ((0, 11), (20, 5), (40, 11)): seconds -> Mbit/s, increasing."""
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
        if not (math.isfinite(mbit) and mbit > 0):
            raise TestbedError(f"--link-schedule={text!r}: rate {rate!r} must be > 0")
        if entries and t_s <= entries[-1][0]:
            raise TestbedError(f"--link-schedule={text!r}: times must increase ({at!r})")
        entries.append((t_s, mbit))
    return tuple(entries)


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
    urgent_stream: bool = False
    """R1 adds a 1,000-byte 20 Hz urgent stream twice, mapped and unmapped (see ``roles``)."""
    strategy: str | None = Strategy.PAPER.value
    """None under ``unmanaged``: no optimizer runs."""
    utilization: float | None = DEFAULT_UTILIZATION

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
        strategy: str | None = None,
        utilization: float | None = None,
        urgent_stream: bool = False,
    ) -> TestbedOptions:
        """The options of the command line's flags; a bad one raises naming the flag."""
        if policy not in POLICIES:
            raise TestbedError(f"--policy={policy!r} is not one of: {', '.join(POLICIES)}")
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
            uplinks_mbit=parse_uplinks(uplinks, [c.robot for c in ROBOTS]),
            urgent_stream=urgent_stream,
        )
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
        return all(mbit == self.link_mbit for _, mbit in self.link_schedule)


@dataclass(frozen=True, slots=True)
class UplinkUse:
    """A robot's own shaped uplink and the most it carried in a step."""

    robot: str
    capacity_mbit: float
    goodput_mbit_max: float | None


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
    urgent: tuple[StreamLatency, ...] = ()
    """With ``urgent_stream``: the mapped and the unmapped copy, over the whole run."""
    """Between link changes: utilisation, p95 and losses (RFC 8867's per-phase figures)."""

    def summary(self) -> Summary:
        """The run in a few numbers."""
        robots = [r for s in self.steps for r in s.robots]
        fractions = [s.goodput_mbit / s.link_mbit for s in self.steps]
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


def _specs(network: Network, options: TestbedOptions) -> dict[str, RoleSpec]:
    """Explicit endpoints: robots connect to the operator's side, where the optimizer runs."""
    operator_ep = f"tcp/{network.hosts['op'].address}:{ZENOH_PORT}"
    optimizer_ep = f"tcp/{network.hosts['op'].address}:{OPTIMIZER_PORT}"
    managed = options.policy != "unmanaged"
    base = RoleSpec(
        step_s=options.step_seconds,
        managed=managed,
        link_mbit=options.link_mbit,
        utilization=options.utilization or 1.0,
        strategy=options.strategy or Strategy.PAPER.value,
        estimate=options.estimate,
        uplinks_mbit=dict(options.uplinks_mbit),
        peer_wait_s=PEER_WAIT_S,
        urgent_stream=options.urgent_stream,
    )
    specs = {"operator": replace(base, host=HOSTS["operator"], listen=(operator_ep,))}
    if managed:
        specs["optimizer"] = replace(
            base, host=HOSTS["optimizer"], listen=(optimizer_ep,), connect=(operator_ep,)
        )
    for role in ("r1", "r2"):
        specs[role] = replace(
            base,
            host=HOSTS[role],
            listen=(f"tcp/{network.hosts[role].address}:{ZENOH_PORT}",),
            connect=(operator_ep, *([optimizer_ep] if managed else [])),
        )
    return specs


def _change_link(
    network: Network, schedule: Sequence[tuple[float, float]], t0: float, stop: threading.Event
) -> None:
    for at, mbit in schedule:
        if at <= 0:
            continue
        if stop.wait(max(0.0, t0 + at - time.time())):
            return
        with contextlib.suppress(TestbedError):  # the network is being torn down
            network.set_link_rate(mbit)


def run_teleop_testbed(
    options: TestbedOptions, *, observe: Observer | None = None
) -> TestbedResult:
    """Build the network, run the roles inside, remove it all; ``observe`` sees every report."""
    problem = privilege_problem()
    if problem is not None:
        raise TestbedError(f"dbml testbed needs root to build network namespaces: {problem}")
    network = Network(
        robots=("r1", "r2"),
        link_mbit=link_at(options.link_schedule, 0.0, options.link_mbit),
        uplinks_mbit={robot.lower(): mbit for robot, mbit in options.uplinks_mbit.items()},
    )
    recording = Recording(None, (), (), interrupted=True)
    with sigterm_as_interrupt(), contextlib.suppress(KeyboardInterrupt):
        try:
            network.build()
            recording = run_experiment(
                _specs(network, options),
                what="testbed",
                command=lambda role, argv: (network.exec_argv(NETNS_OF_ROLE[role], argv), None),
                observe=observe,
                on_start=lambda t0, stop: _change_link(network, options.link_schedule, t0, stop),
            )
        finally:
            network.close()
    result = TestbedResult(options, network.run_id, interrupted=recording.interrupted)
    if recording.t0 is None:
        return result
    analysis = recording.analyse(
        step_s=options.step_seconds, link_mbit=options.link_mbit, schedule=options.link_schedule
    )
    return replace(
        result,
        steps=analysis.steps,
        series=analysis.series,
        changes=analysis.changes,
        phases=analysis.phases,
        urgent=tuple(
            stream_latency(
                recording.arrivals, len(ROBOTS) + k, name="mapped" if s.mapped else "unmapped"
            )
            for k, s in enumerate(URGENT_STREAMS)
            if options.urgent_stream
        ),
    )
