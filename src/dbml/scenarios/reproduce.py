"""Reproduce the paper's Table 2: our allocation of every step beside the printed numbers."""

from __future__ import annotations

import math
from dataclasses import dataclass

from dbml.core.allocation import Strategy, allocate
from dbml.scenarios.teleop import PAPER_TABLE2, ROBOTS, STEPS, PaperCell, step_problem

__all__ = ["RobotRow", "reproduce_table2"]


@dataclass(frozen=True, slots=True)
class RobotRow:
    """One robot in one step: what dbml computes, what the paper printed, and whether they match."""

    step: int
    robot: str
    topic: str
    tc_s: float
    priority: float
    rate_hz: float
    share: float
    static_rate_hz: float
    paper: PaperCell

    @property
    def tc_match(self) -> bool:
        """Time to collision as printed (None for infinity)."""
        if self.paper.tc_s is None:
            return math.isinf(self.tc_s)
        return math.isclose(self.tc_s, self.paper.tc_s)

    @property
    def priority_match(self) -> bool:
        """Priority to the printed two decimals."""
        return round(self.priority, 2) == self.paper.priority

    @property
    def rate_match(self) -> bool:
        """Rate to the printed two decimals."""
        return round(self.rate_hz, 2) == self.paper.rate_hz

    @property
    def share_match(self) -> bool:
        """Bandwidth share to the printed two decimals of a percent."""
        return round(self.share * 100, 2) == self.paper.share_percent

    @property
    def match(self) -> bool:
        """Every printed cell matches."""
        return self.tc_match and self.priority_match and self.rate_match and self.share_match


def reproduce_table2(*, strategy: Strategy = Strategy.PAPER) -> list[list[RobotRow]]:
    """Every step of Table 2 allocated with ``strategy``, beside the paper's printed row."""
    steps: list[list[RobotRow]] = []
    for step, paper_row in zip(STEPS, PAPER_TABLE2, strict=True):
        problem = step_problem(step)
        ours = allocate(problem, strategy=strategy).channels
        static = allocate(problem, strategy=Strategy.STATIC).channels
        steps.append(
            [
                RobotRow(
                    step=step.number,
                    robot=camera.robot,
                    topic=camera.topic,
                    tc_s=event.tc_s,
                    priority=event.priority,
                    rate_hz=row.rate_hz,
                    share=row.share,
                    static_rate_hz=static_row.rate_hz,
                    paper=paper,
                )
                for camera, event, row, static_row, paper in zip(
                    ROBOTS, step.events, ours, static, paper_row, strict=True
                )
            ]
        )
    return steps
