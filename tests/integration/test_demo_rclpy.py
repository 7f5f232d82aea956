"""``dbml demo teleop --transport rclpy``: plain rclpy robots and operator, dbml's bridges.

The robots and the operator are plain rclpy nodes (``dbml.experiment.rclpypeers``: no dbml in
their data path); a ``dbml bridge`` per camera and the optimizer are dbml's. Every process is a
real one, on real ROS 2 (Fast DDS), in a domain of the demo's own; none is left behind, and
neither are its shared-memory files or ROS logs.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest

from dbml.harness.ros2env import fastdds_shm_files
from dbml.harness.supervisor import Supervisor
from tests.integration.test_demo import (
    alive,
    assert_matches_table2,
    children_of,
    stdout_of,
    why_failed,
)

pytestmark = [pytest.mark.integration, pytest.mark.alone]

DEMO = (sys.executable, "-m", "dbml", "demo", "teleop", "--transport", "rclpy")
DEMO_TIMEOUT_S = 240.0
PORT_FILES = ("fastdds_port", "sem.fastdds_port")
"""As for the other transports: 5 %, or 0.3 Hz for a few-Hz stream in a short step."""


def test_demo_over_rclpy_matches_table2_and_leaves_nothing(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    env = dict(os.environ, HOME=str(home))  # where rclpy would log without ROS_LOG_DIR
    env.pop("ROS_LOG_DIR", None)
    started: set[int] = set()
    shm: set[Path] = set()
    deadline = time.monotonic() + DEMO_TIMEOUT_S
    with Supervisor() as children:
        demo = children.start("demo", [*DEMO, "--step-seconds", "1.5", "--json"], env=env)
        try:
            while demo.poll() is None and time.monotonic() < deadline:
                started |= children_of(demo.pid)  # bridges, optimizer and the ROS 2 peers
                shm |= set(fastdds_shm_files(started))
                time.sleep(0.1)
        finally:
            if demo.poll() is None:  # as Ctrl-C would: the demo ends its children, then itself
                demo.send_signal(signal.SIGINT)
                if demo.wait(20) is None:
                    demo.kill()
                for pid in started:
                    if alive(pid):
                        os.kill(pid, signal.SIGKILL)
        stdout = stdout_of(demo, timeout_s=10)
        code, stderr = demo.wait(10), demo.log_tail(3000)
    assert code == 0, why_failed(stdout, stderr)
    assert len(started) >= 6, "2 bridges, optimizer, operator and 2 robots"
    assert not [pid for pid in started if alive(pid)], "every process ended by the demo"
    assert shm, "the processes' Fast DDS shared memory was seen while they ran"
    # A port's segment is shared by every participant that used the port, in any process (this
    # one's own, of an earlier test in the same domain): it may outlive the demo's processes.
    # Their own segments and every lock they held must be gone.
    own = [p for p in shm if p.name.endswith("_el") or not p.name.startswith(PORT_FILES)]
    assert own, "the processes' own segments were seen"
    assert not [path for path in own if path.exists()], "no shared memory of theirs left behind"
    assert not (home / ".ros").exists(), "ROS logs went to the run's folder, not ~/.ros"
    assert_matches_table2(json.loads(stdout))
