"""The paper's teleoperation scenario (section 4): two robots, one camera each, 11 Mbit.

Events are replayed as distance and speed per step (eq. 6); they reproduce the time to collision
of every row of Table 2 within the paper's sensor limits (2 m range, 0.5 m/s top speed).
"""

from __future__ import annotations

from dataclasses import dataclass

from dbml.core.priority import collision_priority, time_to_collision_s
from dbml.core.spec import ChannelSpec, Problem

__all__ = [
    "LINK_MBIT",
    "PAPER_TABLE2",
    "ROBOTS",
    "STEPS",
    "PaperCell",
    "RobotCamera",
    "RobotEvent",
    "Step",
    "step_problem",
]

LINK_MBIT = 11.0
"""The shared link of the paper's experiment (Table 1)."""
MIN_RATE_HZ = 1.0
"""Every camera's minimum rate (Table 1)."""
MAX_RATE_HZ = 16.0
"""Every camera's maximum rate (Table 1)."""


@dataclass(frozen=True, slots=True)
class RobotCamera:
    """A robot's camera stream: 640x480 (84 KB) for R1, 160x120 (21 KB) for R2."""

    robot: str
    topic: str
    size_bytes: int
    width: int = 640
    height: int = 480
    """The camera's resolution, where it sends real frames (``dbml demo --frames photos``)."""


@dataclass(frozen=True, slots=True)
class RobotEvent:
    """What a robot senses in one step: distance to the nearest obstacle and its speed."""

    distance_m: float
    speed_m_per_s: float

    @property
    def tc_s(self) -> float:
        """Time to collision (eq. 6), infinity when standing still."""
        return time_to_collision_s(self.distance_m, self.speed_m_per_s)

    @property
    def priority(self) -> float:
        """The camera's raw priority (eq. 7)."""
        return collision_priority(self.tc_s)


@dataclass(frozen=True, slots=True)
class Step:
    """One step of Table 2: what each robot senses, in ``ROBOTS`` order."""

    number: int
    events: tuple[RobotEvent, ...]


ROBOTS = (
    RobotCamera("R1", "/r1/camera", 84_000),
    RobotCamera("R2", "/r2/camera", 21_000, 160, 120),
)


def _step(number: int, r1: tuple[float, float], r2: tuple[float, float]) -> Step:
    return Step(number, (RobotEvent(*r1), RobotEvent(*r2)))


# (distance_m, speed_m_per_s) per robot; tc = distance / speed gives Table 2's tc column.
STEPS = (
    _step(1, (1.25, 0.0625), (1.25, 0.125)),  # tc 20 / 10
    _step(2, (1.875, 0.0625), (1.25, 0.0625)),  # tc 30 / 20
    _step(3, (0.75, 0.125), (1.5625, 0.015625)),  # tc 6 / 100
    _step(4, (1.25, 0.125), (2.0, 0.0)),  # tc 10 / inf (R2 stopped)
    _step(5, (1.25, 0.25), (2.0, 0.0)),  # tc 5 / inf
    _step(6, (1.875, 0.125), (1.875, 0.125)),  # tc 15 / 15
    _step(7, (1.25, 0.5), (2.0, 0.0)),  # tc 2.5 / inf
    _step(8, (1.125, 0.03125), (1.25, 0.125)),  # tc 36 / 10
    _step(9, (1.25, 0.03125), (0.875, 0.125)),  # tc 40 / 7
    _step(10, (1.5625, 0.03125), (0.375, 0.125)),  # tc 50 / 3
)


def step_problem(step: Step) -> Problem:
    """The allocation problem of one step: Table 1's settings with each camera's priority."""
    return Problem(
        channels=tuple(
            ChannelSpec(camera.topic, MIN_RATE_HZ, MAX_RATE_HZ, camera.size_bytes, event.priority)
            for camera, event in zip(ROBOTS, step.events, strict=True)
        ),
        bandwidth_mbit=LINK_MBIT,
    )


@dataclass(frozen=True, slots=True)
class PaperCell:
    """One robot's row of the paper's Table 2, as printed (tc None for infinity, share in %)."""

    tc_s: float | None
    priority: float
    rate_hz: float
    share_percent: float


# Table 2 of the paper, typed from the printed page: (R1, R2) per step.
PAPER_TABLE2: tuple[tuple[PaperCell, PaperCell], ...] = (
    (PaperCell(20, 0.00, 12.37, 75.56), PaperCell(10, 0.59, 16, 24.44)),
    (PaperCell(30, 0.00, 12.37, 75.56), PaperCell(20, 0.00, 16, 24.44)),
    (PaperCell(6, 0.82, 16, 97.75), PaperCell(100, 0.00, 1.48, 2.25)),
    (PaperCell(10, 0.59, 16, 97.75), PaperCell(None, 0.00, 1.48, 2.25)),
    (PaperCell(5, 0.88, 16, 97.75), PaperCell(None, 0.00, 1.48, 2.25)),
    (PaperCell(15, 0.29, 13, 79.42), PaperCell(15, 0.29, 13.48, 20.58)),
    (PaperCell(2.5, 1.00, 16, 97.75), PaperCell(None, 0.00, 1.48, 2.25)),
    (PaperCell(36, 0.00, 12.37, 75.56), PaperCell(10, 0.59, 16, 24.44)),
    (PaperCell(40, 0.00, 12.37, 75.56), PaperCell(7, 0.76, 16, 24.44)),
    (PaperCell(50, 0.00, 12.37, 75.56), PaperCell(3, 1.00, 16, 24.44)),
)
