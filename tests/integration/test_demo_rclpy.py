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
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dbml.harness.ros2env import fastdds_shm_files
from tests.integration.test_demo import alive, assert_matches_table2, children_of

pytestmark = pytest.mark.integration

DEMO = (sys.executable, "-m", "dbml", "demo", "teleop", "--transport", "rclpy")
DEMO_TIMEOUT_S = 240.0
PORT_FILES = ("fastdds_port", "sem.fastdds_port")
"""As for the other transports: 5 %, or 0.3 Hz for a few-Hz stream in a short step."""


def test_demo_over_rclpy_matches_table2_and_leaves_nothing(tmp_path: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    env = dict(os.environ, HOME=str(home))  # where rclpy would log without ROS_LOG_DIR
    env.pop("ROS_LOG_DIR", None)
    out, err = tmp_path / "demo.out", tmp_path / "demo.err"
    with out.open("w") as stdout_file, err.open("w") as stderr_file:  # never a full pipe
        demo = subprocess.Popen(
            [*DEMO, "--step-seconds", "1.5", "--json"],
            stdout=stdout_file,
            stderr=stderr_file,
            text=True,
            env=env,
        )
    started: set[int] = set()
    shm: set[Path] = set()
    deadline = time.monotonic() + DEMO_TIMEOUT_S
    try:
        while demo.poll() is None and time.monotonic() < deadline:
            started |= children_of(demo.pid)  # bridges, optimizer and the ROS 2 peers
            shm |= set(fastdds_shm_files(started))
            time.sleep(0.1)
        demo.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if demo.poll() is None:  # as Ctrl-C would: the demo ends its children, then itself
            demo.send_signal(signal.SIGINT)
            try:
                demo.wait(timeout=20)
            except subprocess.TimeoutExpired:
                demo.kill()
                demo.wait(timeout=10)
            for pid in started:
                if alive(pid):
                    os.kill(pid, signal.SIGKILL)
    stdout, stderr = out.read_text(), err.read_text()
    assert demo.returncode == 0, stderr[-3000:]
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
