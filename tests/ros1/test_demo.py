"""``dbml demo teleop --transport ros1``: the scenario on a real master.

The demo starts one when none answers and stops it after; and the master helper's reuse rule.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dbml.harness.rosmaster import RosMaster
from dbml.transports.ros1.master import MasterClient
from tests.ros1.rosnet import RosNet, require_ros1

pytestmark = pytest.mark.integration


def rosmasters(ros_home: Path) -> set[int]:
    """PIDs of the rosmaster processes running now with this ``ROS_HOME`` (this test's own).

    Other tests may run masters on this machine at the same time: only ours are counted.
    """
    found = set()
    marker = b"ROS_HOME=" + bytes(ros_home)
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            argv = cmdline.read_bytes().split(b"\0")
            environ = (cmdline.parent / "environ").read_bytes().split(b"\0")
        except OSError:
            continue  # ended meanwhile
        if any(arg.endswith(b"rosmaster") for arg in argv[:2]) and marker in environ:
            found.add(int(cmdline.parent.name))
    return found


def test_demo_over_ros1_matches_table2_and_stops_the_master_it_started(tmp_path: Path) -> None:
    require_ros1()
    env = dict(
        os.environ,
        ROS_MASTER_URI="http://127.0.0.1:9/",  # nothing answers there: the demo starts its own
        ROS_HOME=str(tmp_path),
        ROS_LOG_DIR=str(tmp_path),
    )
    argv = ["demo", "teleop", "--transport", "ros1", "--step-seconds", "2", "--json"]
    done = subprocess.run(
        [sys.executable, "-m", "dbml", *argv],
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert result["transport"] == "ros1"
    assert result["ok"] is True
    assert len(result["steps"]) == 10
    for step in result["steps"]:
        for robot in step["robots"]:
            assert robot["variant"] == "optimized"  # the operator is another ROS host
            assert robot["matches_table2"]
            assert robot["within_tolerance"]
    assert rosmasters(tmp_path) == set()  # the master it started is gone


def test_a_running_master_is_reused_and_left_running(
    ros: RosNet, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("ROS_MASTER_URI", ros.master.uri)
    reused = RosMaster.reuse_or_start()
    assert reused.reused
    assert reused.uri == ros.master.uri
    reused.stop()
    with MasterClient(ros.master.uri) as client:
        assert client.reachable()
