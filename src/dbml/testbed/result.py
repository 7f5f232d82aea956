"""A testbed run's result: what it measured, in a few numbers, and the targets that apply.

``TestbedResult`` holds per step and robot the allocated and delivered rates, latency, losses
and goodput; the recovery after each link change and outage; over rclpy, how the bridges'
publishes went (``BridgePublish``). ``summary()`` and ``targets()`` judge it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from statistics import median

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
)
from dbml.harness.sniffer import WindowStats
from dbml.scenarios.fleet import fleet_cameras, fleet_steps, urgent_robot
from dbml.testbed.options import Policy, TestbedOptions

__all__ = [
    "ALLOCATION_TOLERANCE_HZ",
    "URGENT_P95_MS",
    "BridgePublish",
    "LinkTiming",
    "Summary",
    "TestbedResult",
    "UplinkUse",
]

ALLOCATION_TOLERANCE_HZ = 0.01
"""A fleet's allocation equals ``allocate``'s when every rate is within this (rounding)."""
URGENT_P95_MS = 120.0
"""The mapped urgent stream's p95 bound: two camera frame times (84 KB at 11 Mbit/s: 61 ms)."""


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
class LinkTiming:
    """How the run's link changes went: each ``tc`` call's time and how late it started.

    A recorded trace changes the link every 200 ms: a change that takes a share of that, or
    starts late, moves the link off the trace.
    """

    changes: int
    call_ms_p50: float
    call_ms_max: float
    late_ms_p50: float
    late_ms_max: float

    @classmethod
    def of(cls, calls: Sequence[tuple[float, float]]) -> LinkTiming | None:
        """From ``(late_s, call_s)`` per change; None without a change."""
        if not calls:
            return None
        late = [max(0.0, lag) * 1e3 for lag, _ in calls]
        took = [call * 1e3 for _, call in calls]
        return cls(len(calls), median(took), max(took), median(late), max(late))


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
    wire: WindowStats | None = None
    """What arrived at the operator in sliding 1-s windows, from the first step's settling, on
    a steady link (None otherwise): ``limit_bytes`` is the budget plus the largest frame."""
    limit_bytes: float | None = None
    link_timing: LinkTiming | None = None
    """The link's changes as applied (None: it never changed)."""

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
        if self.options.policy is not Policy.DBML or not self.steps:
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
