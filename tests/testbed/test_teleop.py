"""``dbml testbed teleop`` for real: namespaces, tc-shaped links, the runtime over zenoh.

Short runs (2 s steps) keep CI fast; the README shows a full run.
"""

from __future__ import annotations

import math
import os
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest

from dbml.experiment.analysis import RECOVERED_P95_MS, StepResult
from dbml.harness.supervisor import ProcessChild, Supervisor
from dbml.scenarios.teleop import ROBOTS
from dbml.testbed import leftover_namespaces
from dbml.testbed.options import TestbedOptions
from dbml.testbed.result import TestbedResult
from dbml.testbed.runner import run_teleop_testbed
from tests.conftest import wait_for

pytestmark = pytest.mark.integration

STEP_S = 2.0
PAYLOAD_SHARE = 0.957  # what TCP payload gets of a tbf rate (headers), measured in test_netns


def _run(**options: Any) -> TestbedResult:
    result = run_teleop_testbed(TestbedOptions.from_flags(step_seconds=STEP_S, **options))
    assert not result.interrupted
    assert leftover_namespaces(f"dbml-{result.run_id}-") == []
    assert len(result.steps) == 10
    return result


@pytest.fixture(scope="module")
def dbml_run(netns_privilege: None) -> TestbedResult:
    return _run(policy="dbml")


@pytest.fixture(scope="module")
def unmanaged_run(netns_privilege: None) -> TestbedResult:
    return _run(policy="unmanaged")


def assert_fits_the_link(result: TestbedResult) -> None:
    """A managed run that fits its link, over zenoh or rclpy.

    Each step's goodput near the link's rate and within what its payload gets of it
    (``PAYLOAD_SHARE``; DDS over UDP has fewer headers, so the bound holds for rclpy too), no
    frame lost, p95 latency under 200 ms, each robot at its allocated rate.
    """
    for step in result.steps:
        assert step.goodput_mbit >= 0.9 * step.link_mbit, step
        assert step.goodput_mbit <= step.link_mbit * PAYLOAD_SHARE * 1.05, step
        for robot in step.robots:
            assert robot.lost == 0, step
            assert robot.latency_p95_ms is not None
            assert robot.latency_p95_ms < 200, step
            allocated = robot.allocated_hz
            assert allocated is not None
            # a 1 Hz stream has one or two frames in a 1.3 s window: judge fast ones at 5 %
            tolerance = 0.05 * allocated if allocated >= 4 else 1.0
            assert abs(robot.delivered_hz - allocated) <= tolerance, step
    assert result.summary().lost == 0


def test_dbml_fits_the_link(dbml_run: TestbedResult) -> None:
    assert_fits_the_link(dbml_run)


def test_unmanaged_overloads_the_link(
    dbml_run: TestbedResult, unmanaged_run: TestbedResult
) -> None:
    managed, unmanaged = dbml_run.summary(), unmanaged_run.summary()
    assert all(r.allocated_hz == 16.0 for s in unmanaged_run.steps for r in s.robots)
    # 16 Hz of both cameras is 13.4 Mbit/s into an 11 Mbit/s link: it queues or drops
    assert managed.latency_p95_ms_max is not None
    assert unmanaged.lost > 0 or (
        unmanaged.latency_p95_ms_max is not None
        and unmanaged.latency_p95_ms_max > 2 * managed.latency_p95_ms_max
    )


@pytest.mark.alone  # each 1-s window's p95 under 250 ms: R2's frame waits ~200 behind R1's
def test_a_rate_drop_with_and_without_estimation(netns_privilege: None) -> None:
    schedule = "0:11,8:5"
    estimating = _run(policy="dbml", link_schedule=schedule, estimate=True)
    constant = _run(policy="dbml", link_schedule=schedule)
    (drop,) = estimating.changes
    assert drop.to_mbit == 5.0
    # p95 under 250 ms and no loss from then on
    assert drop.recovery_s is not None, _after(estimating, drop.t_s)
    assert drop.recovery_s <= 3.0, (drop, _after(estimating, drop.t_s))
    budget = estimating.steps[-1].budget_mbit
    assert budget is not None
    assert budget < 5.0  # the estimate followed the link down
    # the paper's constant budget keeps sending 10 Mbit/s into 5: it never recovers
    (unestimated,) = constant.changes
    assert unestimated.recovery_s is None
    assert unestimated.max_latency_p95_ms is not None
    assert drop.max_latency_p95_ms is not None
    assert unestimated.max_latency_p95_ms > 2 * drop.max_latency_p95_ms


MAX_LATE_LINES = 40
"""Enough of a failed run's late windows to read its cause, few enough to read."""


def _after(result: TestbedResult, t_s: float) -> list[str]:
    """The windows from ``t_s`` on that were late or lost frames, with the budget and why.

    A failed drop test then says whether the budget stood above the link and what the estimator
    read, which a run on another machine may not reproduce.
    """
    late = [
        f"{point.t_s:.2f} s: budget {point.budget_mbit} ({point.estimator}); "
        + ", ".join(
            f"{w.robot} {w.allocated_hz} Hz p95 {w.latency_p95_ms} lost {w.lost}"
            for w in point.robots
        )
        for point in result.series
        if point.t_s >= t_s
        and any((w.latency_p95_ms or 0.0) >= RECOVERED_P95_MS or w.lost for w in point.robots)
    ]
    return late[:MAX_LATE_LINES]


def _windows(step: StepResult) -> str:
    """A step's robots in full: pytest cuts a long repr short, and the figures are at its end."""
    return f"step {step.step}: " + "; ".join(
        f"{r.robot} allocated {r.allocated_hz:.2f} Hz, delivered {r.delivered_hz:.2f}, "
        f"lost {r.lost}, p50 {r.latency_p50_ms} ms, p95 {r.latency_p95_ms} ms"
        for r in step.robots
    )


UPLINK_MBIT = 4.0
STALL_MS = 150.0
"""What a stall of a robot's process may add to its frames' latency on a link it nearly fills.

The pacer catches up a tick late by up to 50 ms (``caught_up_periods``): the next frame then
waits up to 50 ms less the link's slack behind the late one. A stall of the operator's process
delays the arrivals it stamps as much as it lasts. Before the pacer stopped catching up stalls,
one of 150 ms (SIGSTOP of R1's role) put a frame 126 ms behind the one before."""


def test_an_uplink_limit_is_kept(netns_privilege: None) -> None:
    result = _run(policy="dbml", uplinks=[f"R1={UPLINK_MBIT:g}"])
    assert result.options.strategy == "lp"
    # R1's 84,000-B frame takes 176 ms to cross its uplink alone: only 24 ms of the shared
    # link's 200-ms target is left for queueing, less than one stall of R1's own process on a
    # busy machine (a step at p95 207 ms, twice in CI beside the other lane). Each of R1's
    # steps is judged on that crossing plus one stall, and most on the 200 ms themselves: a
    # standing queue (the uplink over-allocated) grows through the run and fails both.
    frame_ms = ROBOTS[0].size_bytes * 8 / (UPLINK_MBIT * 1e3 * PAYLOAD_SHARE)
    for step in result.steps:
        r1, r2 = step.robots
        # the allocation keeps R1's uplink; a backlog drains at the uplink's full rate, which
        # a 1.3-s window's fitted arrival rate reads within a percent or two
        assert r1.allocated_hz is not None
        assert result.options.utilization is not None
        r1_mbit = r1.allocated_hz * ROBOTS[0].size_bytes * 8 / 1e6
        assert r1_mbit <= UPLINK_MBIT * result.options.utilization * (1 + 1e-9), step
        assert r1.goodput_mbit <= UPLINK_MBIT * PAYLOAD_SHARE * 1.02, step
        assert step.goodput_mbit <= step.link_mbit * PAYLOAD_SHARE * 1.05, step
        assert r1.lost == 0, _windows(step)
        assert r2.lost == 0, _windows(step)
        assert r1.latency_p95_ms is not None
        assert r2.latency_p95_ms is not None
        assert r1.latency_p95_ms < frame_ms + STALL_MS, _windows(step)
        assert r2.latency_p95_ms < 200, _windows(step)
    r1_p95_ms = [step.robots[0].latency_p95_ms or math.inf for step in result.steps]
    assert statistics.median(r1_p95_ms) < 200, [_windows(step) for step in result.steps]


# -- cleanup, driven through the CLI as a user would ----------------------------------------


@pytest.fixture
def testbed_cli(netns_privilege: None) -> Iterator[tuple[ProcessChild, str]]:
    """A running ``dbml testbed teleop`` and its run id, once its roles are up."""
    before = set(leftover_namespaces())
    with Supervisor() as children:  # killed by its PID if a test leaves it running
        process = children.start(
            "testbed",
            [sys.executable, "-m", "dbml", "testbed", "teleop", "--step-seconds", "3", "--json"],
            stdin=False,
            stop_signal=signal.SIGKILL,
        )
        wait_for(
            lambda: len(set(leftover_namespaces()) - before) >= 4,
            timeout_s=20,
            what="the testbed's namespaces",
        )
        run_id = sorted(set(leftover_namespaces()) - before)[0].split("-")[1]
        wait_for(
            lambda: len(_pids(f"dbml-{run_id}-op")) >= 2,
            timeout_s=20,
            what="the operator and optimizer processes",
        )
        yield process, run_id


def _pids(netns: str) -> list[int]:
    out = subprocess.run(
        ["ip", "netns", "pids", netns], capture_output=True, text=True, check=False, timeout=5
    )
    return [int(pid) for pid in out.stdout.split()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_ctrl_c_removes_every_namespace_and_process(
    testbed_cli: tuple[ProcessChild, str],
) -> None:
    process, run_id = testbed_cli
    roles = [pid for role in ("op", "r1", "r2") for pid in _pids(f"dbml-{run_id}-{role}")]
    process.send_signal(signal.SIGINT)
    assert process.wait(30) == 130
    assert leftover_namespaces(f"dbml-{run_id}-") == []
    wait_for(lambda: not any(_alive(pid) for pid in roles), timeout_s=5, what="roles gone")


def test_a_failing_role_removes_every_namespace_and_process(
    testbed_cli: tuple[ProcessChild, str],
) -> None:
    process, run_id = testbed_cli
    robots = _pids(f"dbml-{run_id}-r1") + _pids(f"dbml-{run_id}-r2")
    for pid in _pids(f"dbml-{run_id}-op"):  # the operator's side dies
        os.kill(pid, signal.SIGKILL)
    started = time.monotonic()
    code = process.wait(60)
    stderr = process.log()
    assert code == 2
    assert "exited early" in stderr
    assert stderr.count("\n") == 1  # one line, no traceback
    assert time.monotonic() - started < 30
    assert leftover_namespaces(f"dbml-{run_id}-") == []
    wait_for(lambda: not any(_alive(pid) for pid in robots), timeout_s=5, what="robots gone")
