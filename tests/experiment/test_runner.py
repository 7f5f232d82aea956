"""The runner fails a run whose role exits non-zero or whose own thread dies."""

from __future__ import annotations

import logging
import sys

import pytest

from dbml.core.errors import DbmlError
from dbml.experiment.roles import RoleSpec
from dbml.experiment.runner import Command, run_experiment
from dbml.scenarios.teleop import STEPS

STEP_S = 0.2
TOTAL_S = STEP_S * len(STEPS)

FAKE_ROLE = """
import sys, threading, time
from dbml.harness.processes import emit_json, serve_role

role, exit_code, total_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
stop = threading.Event()

def run(t0):
    stop.wait(max(0.0, t0 + total_s - time.time()))  # the role's schedule: to the last step
    if role == "operator":
        emit_json({"type": "done"})

serve_role(role, stop, run)
if exit_code:
    sys.stderr.write(f"{role}: a dbml thread died during the run\\n")
sys.exit(exit_code)
"""
"""A role that speaks the protocol, runs to the last step and exits with the code it is given."""


def fake_roles(codes: dict[str, int]) -> Command:
    """Each role as ``FAKE_ROLE`` exiting with its code in ``codes``."""

    def command(role: str, argv: list[str]) -> tuple[list[str], None]:
        return [sys.executable, "-c", FAKE_ROLE, role, str(codes[role]), str(TOTAL_S)], None

    return command


def specs(*roles: str) -> dict[str, RoleSpec]:
    return {role: RoleSpec(step_s=STEP_S, transport="memory") for role in roles}


def test_a_run_whose_roles_exit_zero_is_recorded() -> None:
    command = fake_roles({"operator": 0, "r1": 0})
    recording = run_experiment(specs("operator", "r1"), what="test", command=command)
    assert recording.t0 is not None
    assert not recording.interrupted


def test_a_role_that_exits_1_at_its_end_fails_the_run() -> None:
    """Its failure comes after the last step, when an early exit is no longer looked for."""
    command = fake_roles({"operator": 0, "r1": 1})
    with pytest.raises(
        DbmlError,
        match=r"^test role r1 failed \(exit code 1\): r1: a dbml thread died during the run$",
    ):
        run_experiment(specs("operator", "r1"), what="test", command=command)


def test_a_dead_on_start_thread_fails_the_run(caplog: pytest.LogCaptureFixture) -> None:
    def broken(t0: float, stop: object) -> None:
        raise RuntimeError("the link cannot be shaped")

    command = fake_roles({"operator": 0, "r1": 0})
    with (
        caplog.at_level(logging.CRITICAL, logger="dbml"),
        pytest.raises(DbmlError, match=r"^test: a thread of the runner died \(see above\)$"),
    ):
        run_experiment(specs("operator", "r1"), what="test", command=command, on_start=broken)
    assert "on-start: the thread died" in caplog.text
    assert "RuntimeError: the link cannot be shaped" in caplog.text
