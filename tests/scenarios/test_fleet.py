"""The fleet scenario: two robots are Table 2, more rotate its events among them."""

from __future__ import annotations

import pytest

from dbml.core.errors import SpecError
from dbml.scenarios.fleet import (
    CALM_EVENT,
    fleet_allocation,
    fleet_cameras,
    fleet_steps,
    urgent_robot,
)
from dbml.scenarios.teleop import ROBOTS, STEPS


def test_two_robots_are_the_papers_scenario() -> None:
    assert fleet_cameras(2) == ROBOTS
    assert fleet_steps(2) == STEPS


def test_eight_robots_carry_the_papers_pair_on_a_rotating_pair_of_robots() -> None:
    cameras = fleet_cameras(8)
    assert [c.size_bytes for c in cameras] == [84_000, 21_000] * 4
    assert [c.topic for c in cameras] == [f"/r{k}/camera" for k in range(1, 9)]
    for s, (step, paper) in enumerate(zip(fleet_steps(8), STEPS, strict=True)):
        first = 2 * s % 8
        assert step.events[first] == paper.events[0]
        assert step.events[first + 1] == paper.events[1]
        calm = [e for k, e in enumerate(step.events) if k not in (first, first + 1)]
        assert calm == [CALM_EVENT] * 6
        assert CALM_EVENT.priority == 0.0


def test_the_urgent_robot_changes_at_every_step() -> None:
    cameras = fleet_cameras(8)
    urgent = [urgent_robot(s) for s in fleet_steps(8)]
    names = [None if k is None else cameras[k].robot for k in urgent]
    assert names == ["R2", None, "R5", "R7", "R1", "R3", "R5", "R8", "R2", "R4"]


def test_the_expected_allocation_favours_the_urgent_robot_within_the_budget() -> None:
    cameras = fleet_cameras(8)
    step = fleet_steps(8)[2]  # R5 (84 KB) at tc 6 s: priority 0.82, everyone else calm
    rates = fleet_allocation(step, cameras, link_mbit=11, utilization=0.92, strategy="paper")
    assert rates[4] == pytest.approx((1_265_000 - 3 * 84_000 - 4 * 21_000) / 84_000)
    assert [r for k, r in enumerate(rates) if k != 4] == [1.0] * 7
    assert sum(r * c.size_bytes for r, c in zip(rates, cameras, strict=True)) <= 1_265_000 + 1e-6


@pytest.mark.parametrize("robots", [1, 21, True])
def test_a_fleet_size_out_of_range_names_the_value(robots: int) -> None:
    with pytest.raises(SpecError, match=rf"robots={robots!r}"):
        fleet_cameras(robots)
