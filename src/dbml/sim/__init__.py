"""Scenarios: the paper's teleoperation experiment, replayed as events."""

from dbml.sim.teleop import (
    PAPER_TABLE2,
    ROBOTS,
    STEPS,
    PaperCell,
    RobotCamera,
    RobotEvent,
    Step,
    step_problem,
)

__all__ = [
    "PAPER_TABLE2",
    "ROBOTS",
    "STEPS",
    "PaperCell",
    "RobotCamera",
    "RobotEvent",
    "Step",
    "step_problem",
]
