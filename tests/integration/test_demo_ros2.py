"""``dbml demo teleop --transport ros2``: plain ROS 2 robots and operator, dbml's bridges.

The robots and the operator are zenoh-ros2-sdk nodes (no dbml); a ``dbml bridge`` per camera,
the optimizer and a ``dbml router`` are dbml's. Every process is a real one on loopback.
"""

from __future__ import annotations

import json
import sys
import time

import pytest

from dbml.cli.main import main
from dbml.harness.supervisor import Supervisor
from tests.integration.test_demo import (
    alive,
    assert_matches_table2,
    children_of,
    stdout_of,
    why_failed,
)

pytestmark = pytest.mark.integration

DEMO_TIMEOUT_S = 240.0
"""As for the other transports: 5 %, or 0.3 Hz for a few-Hz stream in a short step."""


def test_demo_over_ros2_matches_table2_and_ends_every_process() -> None:
    argv = [sys.executable, "-m", "dbml", "demo", "teleop", "--transport", "ros2"]
    started: set[int] = set()
    deadline = time.monotonic() + DEMO_TIMEOUT_S
    with Supervisor() as children:
        demo = children.start("demo", [*argv, "--step-seconds", "1.5", "--json"], stdin=False)
        while demo.poll() is None and time.monotonic() < deadline:
            started |= children_of(demo.pid)  # router, bridges, optimizer and the ROS 2 peers
            time.sleep(0.1)
        stdout = stdout_of(demo, timeout_s=max(1.0, deadline - time.monotonic()))
        code, stderr = demo.wait(1.0), demo.log_tail(3000)
    assert code == 0, why_failed(stdout, stderr)
    assert len(started) >= 7, "router, 2 bridges, optimizer, operator and 2 robots"
    assert not [pid for pid in started if alive(pid)], "every process ended by the demo"
    assert_matches_table2(json.loads(stdout))


def test_demo_over_ros2_without_the_sdk_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "zenoh_ros2_sdk", None)  # as if not installed
    assert main(["demo", "teleop", "--transport", "ros2", "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1
    install = f"zenoh-ros2-sdk, which {sys.executable} cannot import: pip install 'dbml[ros2]'"
    assert lines[0].endswith(install)
