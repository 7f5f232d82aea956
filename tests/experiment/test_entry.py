"""The one entry of a run's children: its kinds, and one rule for exit codes and errors."""

from __future__ import annotations

import sys
import threading

import pytest

from dbml.experiment import entry, roles
from dbml.experiment.entry import ENTRY_MODULE, Kind, child_argv
from dbml.experiment.spec import RoleSpec
from dbml.harness.child import RoleError
from dbml.transports.registry import TRANSPORTS

SPEC = RoleSpec(step_s=1.0, transport=TRANSPORTS["memory"], host="robot-r1").to_json()


def test_a_child_runs_this_interpreter_on_the_entry_module() -> None:
    assert child_argv(Kind.ROLE, "r1", "{}") == (
        sys.executable,
        "-m",
        ENTRY_MODULE,
        "role",
        "r1",
        "{}",
    )


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (["role", "r9", SPEC], "r9: role='r9' is not one of operator, optimizer, r1, r2"),
        (["role", "r1", "[]"], "r1: spec='[]' is not a JSON object"),
        (["role", "r1", '{"step_s": 1, "strategy": "best"}'], "strategy='best'"),
        (["role", "r1", '{"step_s": 1, "transport": "carrier-pigeon"}'], "carrier-pigeon"),
        (["ros2-peer", "r1", SPEC], "r1: spec.connect=(): the ROS 2 peers need the router's"),
        (["bridge", '{"topic": "/r1/camera", "transport": "dds"}'], "bridge: --transport='dds'"),
    ],
)
def test_what_cannot_start_is_one_line_and_exit_2(
    argv: list[str], line: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert entry.main(argv) == entry.EXIT_USAGE
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1
    assert line in captured.err


def test_a_run_that_fails_once_under_way_exits_1(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def failing(role: str, spec: RoleSpec, stop: threading.Event) -> int:
        raise RoleError(f"role {role}: a dbml thread died during the run (see above)")

    monkeypatch.setattr(roles, "serve", failing)
    assert entry.main(["role", "r1", SPEC]) == entry.EXIT_FAILED
    assert capsys.readouterr().err == (
        "r1: role r1: a dbml thread died during the run (see above)\n"
    )


def test_an_unknown_kind_is_argparses_refusal() -> None:
    with pytest.raises(SystemExit) as ended:
        entry.main(["pigeon"])
    assert ended.value.code == 2
