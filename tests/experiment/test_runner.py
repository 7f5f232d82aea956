"""The runner fails a run whose role exits non-zero or whose own thread dies."""

from __future__ import annotations

import logging
import sys

import pytest

from dbml.core.errors import DbmlError
from dbml.experiment.plan import Helper, Launch, Plan
from dbml.experiment.report import PublishReport, PublishTiming
from dbml.experiment.runner import run_experiment
from dbml.experiment.spec import RoleSpec
from dbml.scenarios.teleop import STEPS
from dbml.transports.registry import TRANSPORTS

STEP_S = 0.2
TOTAL_S = STEP_S * len(STEPS)

FAKE_ROLE = """
import sys, threading, time
from dbml.harness.child import serve_role

role, exit_code, total_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
stop = threading.Event()

def run(t0):
    stop.wait(max(0.0, t0 + total_s - time.time()))  # the role's schedule: to the last step
    if role == "operator":
        from dbml.harness.child import emit_json
        emit_json({"type": "done"})

serve_role(role, stop, run)
if exit_code:
    sys.stderr.write(f"{role}: a dbml thread died during the run\\n")
sys.exit(exit_code)
"""
"""A role that speaks the protocol, runs to the last step and exits with the code it is given."""
FAKE_BRIDGE = """
import sys, threading
from dbml.harness.child import Control, emit_json
stop = threading.Event()
Control(stop).start()
stop.wait()
emit_json({"type": "publish_stats", "publishers": [
    {"topic": "/r1/camera/optimized", "published": 9, "dropped": 1, "max_ms": 2.5, "p99_ms": 0.4}
]})
"""
"""A helper that reports its publishes when it is told to stop, as a bridge does."""


def fake_plan(codes: dict[str, int], *helpers: Helper) -> Plan:
    """Each role as ``FAKE_ROLE`` exiting with its code in ``codes``."""
    return Plan(
        specs={role: RoleSpec(step_s=STEP_S, transport=TRANSPORTS["memory"]) for role in codes},
        launches={
            role: Launch(argv=(sys.executable, "-c", FAKE_ROLE, role, str(code), str(TOTAL_S)))
            for role, code in codes.items()
        },
        helpers=helpers,
    )


def test_a_run_whose_roles_exit_zero_is_recorded() -> None:
    recording = run_experiment(fake_plan({"operator": 0, "r1": 0}), what="test")
    assert recording.t0 is not None
    assert not recording.interrupted
    assert recording.publishes == {}


def test_a_role_that_exits_1_at_its_end_fails_the_run() -> None:
    """Its failure comes after the last step, when an early exit is no longer looked for."""
    with pytest.raises(
        DbmlError,
        match=r"^test role r1 failed \(exit code 1\): r1: a dbml thread died during the run$",
    ):
        run_experiment(fake_plan({"operator": 0, "r1": 1}), what="test")


def test_a_dead_on_start_thread_fails_the_run(caplog: pytest.LogCaptureFixture) -> None:
    def broken(t0: float, stop: object) -> None:
        raise RuntimeError("the link cannot be shaped")

    with (
        caplog.at_level(logging.CRITICAL, logger="dbml"),
        pytest.raises(DbmlError, match=r"^test: a thread of the runner died \(see above\)$"),
    ):
        run_experiment(fake_plan({"operator": 0, "r1": 0}), what="test", on_start=broken)
    assert "on-start: the thread died" in caplog.text
    assert "RuntimeError: the link cannot be shaped" in caplog.text


def test_a_helpers_report_of_its_publishes_is_kept_with_the_recording() -> None:
    bridge = Helper(name="bridge-r1", launch=Launch(argv=(sys.executable, "-c", FAKE_BRIDGE)))
    recording = run_experiment(fake_plan({"operator": 0, "r1": 0}, bridge), what="test")
    assert recording.publishes == {
        "bridge-r1": (PublishTiming("/r1/camera/optimized", 9, 1, 2.5, 0.4),)
    }
    report = PublishReport(recording.publishes["bridge-r1"])
    assert PublishReport.decode(report.encode()) == report


def test_a_helper_that_ends_before_the_last_step_fails_the_run() -> None:
    quitter = Helper(
        name="router", launch=Launch(argv=(sys.executable, "-c", "print('bye')")), before="r1"
    )
    with pytest.raises(DbmlError, match=r"^test role router exited early"):
        run_experiment(fake_plan({"operator": 0, "r1": 0}, quitter), what="test")


def test_helpers_need_role_processes() -> None:
    helper = Helper(name="router", launch=Launch(argv=("true",)))
    with pytest.raises(DbmlError, match="helper processes need role processes, not threads"):
        Plan(specs={"operator": RoleSpec(step_s=STEP_S)}, helpers=(helper,))
