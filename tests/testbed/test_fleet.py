"""``dbml testbed teleop --robots 8`` for real, in both topologies: a fleet on one shaped link.

Eight robots, each in its own namespace with its own uplink, Table 2's events rotating among
them, short steps (2 s) so a run takes about half a minute. The allocation is judged against
``allocate`` on the priorities the events imply (computed here, independently of the run).
"""

from __future__ import annotations

import itertools

import pytest

from dbml.cli import documents
from dbml.experiment.analysis import MAX_P95_MS
from dbml.scenarios.fleet import fleet_allocation, fleet_cameras, fleet_steps, urgent_robot
from dbml.testbed import leftover_namespaces
from dbml.testbed.options import TestbedOptions
from dbml.testbed.result import TestbedResult
from dbml.testbed.runner import run_teleop_testbed

pytestmark = [pytest.mark.integration, pytest.mark.alone]

ROBOTS = 8
STEP_S = 2.0
PAYLOAD_SHARE = 0.957
"""What TCP payload gets of a tbf rate (headers), measured in test_netns."""
FAST_HZ = 4.0
"""At or above this a stream has enough frames in a step's 1.3 s window to time to 15 %."""
FAST_TOLERANCE = 0.15
RUN_TOLERANCE = 0.1
"""Every stream's delivered rate summed over the steps, against its allocations summed: a
1 Hz stream has one or two frames in a step's window, so it is judged over the run."""
STEP_GOODPUT_SLACK = 1.1
"""A step's goodput comes from inter-arrival times, which a burst of queued frames inflates."""
MAX_LOST_PER_RUN = 2
"""Frames a run may lose (of about 700): data is sent with zenoh's DROP congestion control, so
a TCP connection that stalls on the saturated link (a tbf drop, then a retransmission timeout)
fills zenoh's queue and the newest frame is dropped rather than queued stale. Measured: one
84,000-byte frame (R3 at 10.5 Hz, step 6) in one of about ten 8-robot router runs, none in
peer runs."""


@pytest.fixture(scope="module", params=["peer", "router"])
def fleet_run(request: pytest.FixtureRequest, netns_privilege: None) -> TestbedResult:
    options = TestbedOptions.from_flags(
        step_seconds=STEP_S, robots=ROBOTS, topology=str(request.param)
    )
    result = run_teleop_testbed(options)
    assert not result.interrupted
    assert leftover_namespaces(f"dbml-{result.run_id}-") == []
    assert len(result.steps) == len(fleet_steps(ROBOTS))
    return result


def test_the_allocation_is_allocates_for_the_implied_priorities(fleet_run: TestbedResult) -> None:
    options = fleet_run.options
    assert options.utilization is not None
    assert options.strategy is not None
    cameras = fleet_cameras(ROBOTS)
    for events, step in zip(fleet_steps(ROBOTS), fleet_run.steps, strict=True):
        expected = fleet_allocation(
            events,
            cameras,
            link_mbit=options.link_mbit,
            utilization=options.utilization,
            strategy=options.strategy,
        )
        allocated = [r.allocated_hz for r in step.robots]
        assert allocated == pytest.approx(expected, abs=0.01), step.step
    assert fleet_run.targets()["allocation_equals_allocate"]


def test_every_robot_delivers_its_allocation(fleet_run: TestbedResult) -> None:
    """Fast streams per step; every stream over the run (a short step times 1 Hz poorly)."""
    lost = [(step.step, r.robot, r.lost) for step in fleet_run.steps for r in step.robots if r.lost]
    assert sum(n for _, _, n in lost) <= MAX_LOST_PER_RUN, lost
    for step in fleet_run.steps:
        for robot in step.robots:
            assert robot.allocated_hz is not None
            if robot.allocated_hz >= FAST_HZ:
                error = abs(robot.delivered_hz - robot.allocated_hz)
                assert error <= FAST_TOLERANCE * robot.allocated_hz, (step.step, robot)
    for k, camera in enumerate(fleet_cameras(ROBOTS)):
        windows = [step.robots[k] for step in fleet_run.steps]
        assert all(w.robot == camera.robot for w in windows)
        allocated = sum(w.allocated_hz or 0.0 for w in windows)
        delivered = sum(w.delivered_hz for w in windows)
        assert delivered == pytest.approx(allocated, rel=RUN_TOLERANCE), camera.robot


def test_every_robot_meets_the_latency_target_in_every_step(fleet_run: TestbedResult) -> None:
    """p95 under 200 ms for every robot in every step, peers as routers.

    It held only while the robots' 1 Hz frames stayed apart: a push that slowed several
    robots at once used to restart their slow schedules together, and three 84,000-byte
    frames leaving within 30 ms overflowed the shared queue (p95 up to 345 ms, both
    topologies). The managed publisher's loop keeps its own phase across rate changes.
    """
    late = [
        (step.step, r.robot, r.latency_p95_ms)
        for step in fleet_run.steps
        for r in step.robots
        if r.latency_p95_ms is None or r.latency_p95_ms >= MAX_P95_MS
    ]
    assert not late, late


def test_the_fleet_fits_the_shared_link(fleet_run: TestbedResult) -> None:
    (phase,) = fleet_run.phases  # bytes that arrived over the whole run, not an estimate
    assert phase.goodput_mbit <= phase.link_mbit * PAYLOAD_SHARE, phase
    assert phase.goodput_mbit >= 0.8 * phase.link_mbit, phase
    for step in fleet_run.steps:
        assert step.goodput_mbit <= step.link_mbit * PAYLOAD_SHARE * STEP_GOODPUT_SLACK, step


def test_the_urgent_robot_rotates_and_is_served(fleet_run: TestbedResult) -> None:
    cameras = fleet_cameras(ROBOTS)
    urgent = fleet_run.urgent_robots()
    assert urgent == tuple(
        None if (k := urgent_robot(s)) is None else cameras[k].robot for s in fleet_steps(ROBOTS)
    )
    named = [u for u in urgent if u is not None]
    assert len(set(named)) >= ROBOTS - 1  # nearly every robot is the urgent one once
    assert all(a != b for a, b in itertools.pairwise(named))
    for step, name in zip(fleet_run.steps, urgent, strict=True):
        if name is None:
            continue
        (mine,) = [r for r in step.robots if r.robot == name]
        size = next(c.size_bytes for c in cameras if c.robot == name)
        peers = [
            r
            for r, c in zip(step.robots, cameras, strict=True)
            if c.size_bytes == size and r.robot != name
        ]
        assert mine.allocated_hz is not None
        assert all(mine.allocated_hz >= (p.allocated_hz or 0.0) for p in peers), step


def test_the_document_names_the_fleet(fleet_run: TestbedResult) -> None:
    document = documents.testbed_document(fleet_run)
    assert document["robots"] == ROBOTS
    assert document["topology"] == fleet_run.options.topology
    first = document["steps"][0]
    assert first["urgent_robot"] == fleet_run.urgent_robots()[0]
    assert [r["robot"] for r in first["robots"]] == [c.robot for c in fleet_cameras(ROBOTS)]
    assert all("expected_hz" in r for r in first["robots"])
