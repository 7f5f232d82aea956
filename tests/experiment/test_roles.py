"""A role that loses a dbml thread ends early, without ``done``, and its process exits 1."""

from __future__ import annotations

import logging
import sys
import threading
import time
from typing import Any

import pytest

from dbml.core.errors import DbmlError
from dbml.experiment import roles
from dbml.experiment.roles import run_role
from dbml.experiment.spec import RoleSpec
from dbml.harness.supervisor import Supervisor
from dbml.runtime.optimizer import OptimizerNode
from dbml.runtime.reception import ReceptionReporter
from dbml.scenarios.teleop import STEPS
from dbml.transports.memory import MemoryNetwork, MemoryTransport
from dbml.transports.registry import TRANSPORTS
from dbml.transports.worker import death_count

STEP_S = 3.0
"""Long enough that a role ending at its last step (30 s) is told from one ending early."""
EARLY_S = STEP_S * len(STEPS) / 2
"""A role that lost a thread ends well before this (within a period of the death)."""
TIMEOUT_S = 60.0
"""How long the role process test waits for a process that should end within seconds."""
MEMORY = TRANSPORTS["memory"]


def run(role: str, spec: RoleSpec) -> tuple[list[dict[str, Any]], float]:
    """Run ``role`` over the memory transport from now: its reports, and how long it ran.

    It must raise ``DbmlError`` naming the role and a dead thread.
    """
    reports: list[dict[str, Any]] = []
    transport = MemoryTransport(MemoryNetwork(), host=spec.host)
    started = time.monotonic()
    try:
        with pytest.raises(DbmlError, match=rf"^role {role}: a dbml thread died during the run"):
            run_role(
                role,
                transport,
                spec,
                t0=time.time(),
                stop=threading.Event(),
                emit=reports.append,
            )
    finally:
        transport.close()
    return reports, time.monotonic() - started


def test_a_robot_whose_events_thread_dies_ends_early_and_fails(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    class BrokenPriority:
        def update(self, distance_m: float, speed_m_per_s: float) -> None:
            raise RuntimeError("no collision estimate")

    monkeypatch.setattr(roles, "collision_priority_source", lambda *_: BrokenPriority())
    deaths = death_count()
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        _, took_s = run("r1", RoleSpec(step_s=STEP_S, transport=MEMORY, host="robot-r1"))
    assert took_s < EARLY_S
    assert death_count() == deaths + 1
    assert "events-R1: the thread died" in caplog.text
    assert "RuntimeError: no collision estimate" in caplog.text


def test_a_robot_whose_urgent_streams_die_ends_early_and_fails(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(*_: object, **__: object) -> None:
        raise RuntimeError("no urgent link")

    monkeypatch.setattr(roles, "_urgent_streams", broken)
    spec = RoleSpec(step_s=STEP_S, transport=MEMORY, host="robot-r1", urgent_stream=True)
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        _, took_s = run("r1", spec)
    assert took_s < EARLY_S
    assert "urgent: the thread died" in caplog.text


def test_an_operator_that_loses_a_thread_ends_without_done(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken_flush(self: ReceptionReporter) -> int:
        raise SystemExit("a tick that ends the thread")  # not retried: the thread dies

    monkeypatch.setattr(ReceptionReporter, "flush", broken_flush)
    spec = RoleSpec(step_s=STEP_S, transport=MEMORY, host="operator", estimate=True)
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        reports, took_s = run("operator", spec)
    assert took_s < EARLY_S
    assert "dbml-reception: the thread died" in caplog.text
    assert all(report.get("type") != "done" for report in reports)


def test_an_optimizer_whose_node_dies_fails(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken_round(self: OptimizerNode) -> None:
        raise SystemExit("a round that ends the thread")

    monkeypatch.setattr(OptimizerNode, "_round", broken_round)
    spec = RoleSpec(step_s=STEP_S, transport=MEMORY, host="base-station")
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        _, took_s = run("optimizer", spec)
    assert took_s < EARLY_S
    assert "dbml-optimizer: the thread died" in caplog.text


ROLE_PROCESS = """
import sys
from dbml.experiment import entry, roles

def broken(*_, **__):
    raise RuntimeError("no urgent link")

roles._urgent_streams = broken
sys.exit(entry.main(["role", "r1", sys.argv[1]]))
"""
"""Robot R1 as a process whose urgent streams' thread dies."""


def role_process(script: str, spec: RoleSpec) -> tuple[int, str, str, float]:
    """Run ``script`` (a role's entry) given ``start`` now: its code, stdout, stderr, time.

    Its stdin stays open: EOF would end the role (its parent gone) before the death.
    """
    started = time.monotonic()
    with Supervisor() as children:
        child = children.start("r1", [sys.executable, "-c", script, spec.to_json()])
        child.send(f"start {time.time()!r}")
        lines = []
        while (line := child.next(timeout_s=TIMEOUT_S)) is not None and not line.ended:
            lines.append(line.text)
        code = child.wait(TIMEOUT_S)
        assert code is not None, "the role did not end"
        stderr = child.log()
    stdout = "".join(text + "\n" for text in lines)
    return code, stdout, stderr, time.monotonic() - started


def test_a_role_process_that_loses_a_thread_exits_1() -> None:
    spec = RoleSpec(step_s=STEP_S, transport=MEMORY, host="robot-r1", urgent_stream=True)
    code, stdout, stderr, took_s = role_process(ROLE_PROCESS, spec)
    assert code == 1, stderr
    assert took_s < EARLY_S
    assert '{"type": "ready", "role": "r1"}' in stdout
    assert "urgent: the thread died" in stderr
    assert "RuntimeError: no urgent link" in stderr
    assert "r1: role r1: a dbml thread died during the run (see above)" in stderr


EARLY_DEATH = """
import logging, sys
from dbml.experiment import entry, roles
from dbml.transports.worker import BackgroundThread

opened = roles._open

def open_and_lose_a_thread(role, spec, network):
    def fail():
        raise RuntimeError("lost before the start")
    BackgroundThread(fail, name="early", log=logging.getLogger("dbml.test")).start().join()
    return opened(role, spec, network)

roles._open = open_and_lose_a_thread
sys.exit(entry.main(["role", "r1", sys.argv[1]]))
"""
"""Robot R1 as a process that loses a thread while it opens its transport, before the run."""


def test_a_role_process_that_lost_a_thread_before_its_run_exits_1() -> None:
    spec = RoleSpec(step_s=0.1, transport=MEMORY, host="robot-r1")
    code, _, stderr, _ = role_process(EARLY_DEATH, spec)
    assert code == 1, stderr
    assert "early: the thread died" in stderr
    assert "a worker thread died (see above); exiting so a supervisor restarts it" in stderr
