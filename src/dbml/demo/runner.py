"""``dbml demo teleop``: the live scenario on one machine, checked against Table 2.

The roles run on loopback, laid out for the transport's way of meeting (``layouts``: threads
over the memory transport, processes over zenoh, ROS 1, rmw_zenoh's ROS 2 or rclpy). Per step
and robot the result holds tc, priority, the allocated and measured rate, and whether they match
Table 2 and each other.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, replace

from dbml.core.errors import DbmlError
from dbml.demo.layouts import layout_of
from dbml.experiment.analysis import (
    RATE_TOLERANCE_HZ,
    SeriesPoint,
    StepResult,
    Window,
)
from dbml.experiment.runner import Observer, run_experiment
from dbml.experiment.spec import HOSTS, RoleSpec, transport_entry
from dbml.scenarios.reproduce import reproduce_table2
from dbml.scenarios.teleop import LINK_MBIT, ROBOTS, STEPS
from dbml.transports.registry import TRANSPORTS, TransportEntry
from dbml.view.target import ViewTarget

__all__ = ["MIN_STEP_S", "DemoOptions", "DemoResult", "DemoRobot", "DemoStep", "run_teleop_demo"]

MIN_STEP_S = 1.0
"""The shortest step that still times a 1.48 Hz stream after ``settle_s``."""


@dataclass(frozen=True, slots=True, kw_only=True)
class DemoOptions:
    """What ``dbml demo teleop`` runs; checked on creation, messages name the flag."""

    step_seconds: float = 3.0
    transport: TransportEntry = TRANSPORTS["zenoh"]
    view: ViewTarget | None = None
    """``--foxglove``/``--record``: the operator's live view (its frames, the allocation)."""

    def __post_init__(self) -> None:
        if not self.step_seconds >= MIN_STEP_S:
            raise DbmlError(
                f"--step-seconds={self.step_seconds!r} must be >= 1 (rates down to 1.48 Hz)"
            )
        name = self.transport.name
        if self.view is not None and not layout_of(self.transport).dbml_operator:
            raise DbmlError(
                f"--foxglove/--record with --transport={name!r}: the operator is a "
                "plain ROS 2 node there, without dbml's view; run the view beside it with "
                f"`dbml monitor --transport {name} --foxglove PORT`"
            )

    @classmethod
    def from_flags(
        cls, *, step_seconds: float = 3.0, transport: str = "zenoh", view: ViewTarget | None = None
    ) -> DemoOptions:
        """The options of the command line's flags; a bad one raises naming the flag."""
        return cls(step_seconds=step_seconds, transport=transport_entry(transport), view=view)


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


def run_teleop_demo(options: DemoOptions, *, observe: Observer | None = None) -> DemoResult:
    """Run the scenario live; ``observe`` sees every report of the operator (a live view)."""
    layout = layout_of(options.transport)
    layout.check()
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
    with contextlib.ExitStack() as run:
        plan = layout.plan(specs, options.transport, run)
        recording = run_experiment(plan, what="demo", observe=observe)
    if recording.t0 is None:
        return DemoResult(options, interrupted=recording.interrupted)
    analysis = recording.analyse(step_s=options.step_seconds, link_mbit=LINK_MBIT)
    return DemoResult(
        options,
        tuple(_judge(step) for step in analysis.steps),
        analysis.series,
        recording.interrupted,
    )
