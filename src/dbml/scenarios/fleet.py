"""The teleoperation scenario for a fleet: N robots, Table 2's events rotating among them.

With two robots it is the paper's scenario unchanged. With more, robot ``k`` (from 0) carries
the paper's two camera models in turn (84,000 bytes for even ``k``, 21,000 for odd ``k``), and
at step ``s`` (from 0) the paper's R1 event falls on robot ``2s mod N`` and R2's on robot
``2s + 1 mod N``; every other robot is calm (nothing within its sensor's range). With an even N
each step's pair is therefore exactly the paper's pair (R1's event on an 84 KB camera, R2's on a
21 KB one) while the urgent robot moves on at every step, and two robots reduce to Table 2.

The expected allocation of a step is :func:`dbml.allocate` on the channels the events imply,
in topic order (the order the optimizer node declares them in), so a fleet run is judged by the
optimizer's own rule computed independently, not by Table 2's two-robot numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from dbml.core.allocation import Allocation, Strategy, allocate
from dbml.core.errors import SpecError
from dbml.core.spec import ChannelSpec, Problem
from dbml.scenarios.teleop import (
    MAX_RATE_HZ,
    MIN_RATE_HZ,
    ROBOTS,
    STEPS,
    RobotCamera,
    RobotEvent,
    Step,
)

__all__ = [
    "CALM_EVENT",
    "MAX_ROBOTS",
    "MIN_ROBOTS",
    "fleet_allocation",
    "fleet_cameras",
    "fleet_problem",
    "fleet_steps",
    "robot_role",
    "urgent_robot",
]

MIN_ROBOTS = 2
"""The paper's two robots: fewer leaves nothing to share."""
MAX_ROBOTS = 20
"""A fleet the control plane converges for in seconds (measured: 20 robots in 6.3 s)."""
SENSOR_RANGE_M = 2.0
"""The paper's sensor range: nothing closer is seen."""
CALM_SPEED_M_PER_S = 0.0625
"""A calm robot moves slowly with nothing in range: tc = 32 s > 20 s, so priority 0 (eq. 7)."""
CALM_EVENT = RobotEvent(SENSOR_RANGE_M, CALM_SPEED_M_PER_S)
"""What a robot without one of the paper's events senses."""


def robot_role(index: int) -> str:
    """The role (and namespace) name of robot ``index`` from 0: ``"r1"``, ``"r2"``, ..."""
    return f"r{index + 1}"


def _check(robots: int) -> int:
    if isinstance(robots, bool) or not isinstance(robots, int):
        raise SpecError(f"robots={robots!r} must be an integer")
    if not MIN_ROBOTS <= robots <= MAX_ROBOTS:
        raise SpecError(f"robots={robots!r} must be in {MIN_ROBOTS}..{MAX_ROBOTS}")
    return robots


def fleet_cameras(robots: int) -> tuple[RobotCamera, ...]:
    """One camera per robot, the paper's two sizes alternating; two robots are ``ROBOTS``."""
    if _check(robots) == len(ROBOTS):
        return ROBOTS
    return tuple(
        replace(
            ROBOTS[k % len(ROBOTS)], robot=robot_role(k).upper(), topic=f"/{robot_role(k)}/camera"
        )
        for k in range(robots)
    )


def fleet_steps(robots: int) -> tuple[Step, ...]:
    """Table 2's steps with their two events rotated over ``robots`` (``STEPS`` for two)."""
    if _check(robots) == len(ROBOTS):
        return STEPS
    steps = []
    for s, step in enumerate(STEPS):
        events = [CALM_EVENT] * robots
        for j, event in enumerate(step.events):
            events[(len(step.events) * s + j) % robots] = event
        steps.append(Step(step.number, tuple(events)))
    return tuple(steps)


def urgent_robot(step: Step) -> int | None:
    """The robot with the highest raw priority (the first on a tie); None when all are calm."""
    top = max(event.priority for event in step.events)
    if top <= 0:
        return None
    return next(k for k, event in enumerate(step.events) if event.priority == top)


def fleet_problem(
    step: Step,
    cameras: Sequence[RobotCamera],
    *,
    link_mbit: float,
    utilization: float,
) -> Problem:
    """The allocation problem of one step, channels in topic order (the optimizer's order)."""
    channels = sorted(
        (
            ChannelSpec(camera.topic, MIN_RATE_HZ, MAX_RATE_HZ, camera.size_bytes, event.priority)
            for camera, event in zip(cameras, step.events, strict=True)
        ),
        key=lambda channel: channel.topic,
    )
    return Problem(tuple(channels), link_mbit, utilization)


def fleet_allocation(
    step: Step,
    cameras: Sequence[RobotCamera],
    *,
    link_mbit: float,
    utilization: float,
    strategy: Strategy | str,
) -> tuple[float, ...]:
    """What ``allocate`` gives each camera in one step, in ``cameras`` order (Hz)."""
    problem = fleet_problem(step, cameras, link_mbit=link_mbit, utilization=utilization)
    result: Allocation = allocate(problem, strategy=strategy)
    rates = {channel.topic: channel.rate_hz for channel in result.channels}
    return tuple(rates[camera.topic] for camera in cameras)
