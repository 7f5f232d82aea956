"""Scenarios as pure data and rules: the paper's teleoperation (robots, events, Table 2)."""

from dbml.scenarios.reproduce import RobotRow, reproduce_table2
from dbml.scenarios.teleop import (
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
    "RobotRow",
    "Step",
    "reproduce_table2",
    "step_problem",
]
