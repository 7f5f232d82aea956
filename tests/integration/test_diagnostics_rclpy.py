"""``/diagnostics`` from ``dbml optimizer --transport rclpy``, read by a plain rclpy subscriber.

Real processes on real ROS 2: two plain rclpy cameras of the paper's frame sizes, a ``dbml
bridge`` per robot and the optimizer, all from the ROS 2 package's params file (Table 1).
One status per managed channel and the optimizer's: OK in Table 2's first step, WARN once the
budget cannot hold the minimums, ERROR for a channel within 3 periods of its driver's death.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from dbml.harness.ros2env import claim_domain, ros2_child_env
from dbml.harness.supervisor import Supervisor
from dbml.runtime.diagnostics import OPTIMIZER_NAME, Level, channel_name
from dbml.scenarios.teleop import ROBOTS
from tests.conftest import wait_for
from tests.integration.procs import ROOT, start_rclpy_cameras

pytest.importorskip("rclpy")
pytest.importorskip("diagnostic_msgs")

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from dbml.harness.ros2node import private_node
from tests.rclpy_tools import param_set

pytestmark = pytest.mark.integration

PARAMS = ROOT / "ros2" / "dbml_ros" / "config" / "teleop.yaml"
PERIOD_S = 1.0
"""The params file's optimization_rate_in_seconds."""
START_TIMEOUT_S = 60.0
CHANGE_TIMEOUT_S = 15.0
INFEASIBLE_MBIT = 0.5
"""Below the minimums' 0.84 Mbit/s (84,000 + 21,000 B at 1 Hz)."""
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)


class Statuses:
    """The newest level and message of each status name on ``/diagnostics``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._levels: dict[str, tuple[Level, str]] = {}
        self._sent: dict[str, tuple[str, str]] = {}
        """Each channel's sent and allocated rates, as the newest status says them."""

    def heard(self, array: Any) -> None:
        with self._lock:
            for status in array.status:
                self._levels[status.name] = (Level(status.level[0]), status.message)
                values = {v.key: v.value for v in status.values}
                self._sent[status.name] = (
                    values.get("sent_hz", ""),
                    values.get("allocated_hz", ""),
                )

    def sending(self, name: str) -> bool:
        """Whether the channel's publisher said it sends at least half its allocation.

        What it said last sets how soon a silence is a stop (two of its intervals): said during
        the infeasible step (about 1 Hz) and not since, a dead driver is said 2 s later.
        """
        with self._lock:
            sent, allocated = self._sent.get(name, ("", ""))
        return bool(sent and allocated) and float(sent) >= 0.5 * float(allocated)

    def level(self, name: str) -> Level | None:
        with self._lock:
            found = self._levels.get(name)
        return None if found is None else found[0]

    def snapshot(self) -> dict[str, tuple[Level, str]]:
        with self._lock:
            return dict(self._levels)


def test_diagnostics_say_ok_then_warn_then_error_for_a_dead_driver(tmp_path: Path) -> None:
    with claim_domain() as domain_id, Supervisor(logs=tmp_path / "logs") as children:
        env = ros2_child_env(domain_id=domain_id, log_dir=tmp_path / "ros")
        cameras = start_rclpy_cameras(children, env)
        dbml = [sys.executable, "-m", "dbml"]
        ros = ["--ros-args", "--params-file", str(PARAMS)]
        children.start(
            "optimizer", [*dbml, "optimizer", "--transport", "rclpy", *ros], env=env, stdin=False
        )
        for camera in ROBOTS:
            namespace = camera.topic.rsplit("/", 1)[0]
            children.start(
                f"bridge-{camera.robot}",
                [*dbml, "bridge", "--transport", "rclpy", *ros, "-r", f"__ns:={namespace}"],
                env=env,
                stdin=False,
            )
        statuses = Statuses()
        names = [OPTIMIZER_NAME, *(channel_name(c.topic) for c in ROBOTS)]
        with private_node("operator", domain_id=domain_id) as operator:
            operator.create_subscription(DiagnosticArray, "/diagnostics", statuses.heard, 10)
            for camera in ROBOTS:  # a remote consumer: each channel is managed
                operator.create_subscription(
                    Image, f"{camera.topic}/optimized", lambda _m: None, BEST_EFFORT, raw=True
                )

            def all_at(level: Level, *which: str) -> bool:
                for child in children.children.values():
                    assert child.poll() is None, f"{child.name} ended: {child.log_tail()}"
                return all(statuses.level(name) is level for name in which)

            wait_for(
                lambda: all_at(Level.OK, *names),
                timeout_s=START_TIMEOUT_S,
                what="every status OK",
            )
            result = param_set(operator, "/dbm", "max_bandwidth_in_mbit", INFEASIBLE_MBIT)
            assert result.successful, result.reason
            wait_for(
                lambda: all_at(Level.WARN, *names),
                timeout_s=CHANGE_TIMEOUT_S,
                what="every status WARN",
            )
            assert "infeasible" in statuses.snapshot()[OPTIMIZER_NAME][1]
            result = param_set(operator, "/dbm", "max_bandwidth_in_mbit", 11.0)
            assert result.successful, result.reason
            wait_for(
                lambda: all_at(Level.OK, *names) and all(map(statuses.sending, names[1:])),
                timeout_s=CHANGE_TIMEOUT_S,
                what="every status OK again, each channel said to send its allocation",
            )
            dead = ROBOTS[1].topic
            driver = cameras.pop(dead)
            driver.send_signal(signal.SIGTERM)  # a driver that ends (and cleans up after itself)
            died = time.monotonic()
            assert driver.wait(5.0) is not None
            wait_for(
                lambda: statuses.level(channel_name(dead)) is Level.ERROR,
                timeout_s=CHANGE_TIMEOUT_S,
                what=f"ERROR for {dead}",
            )
            elapsed_s = time.monotonic() - died
            assert statuses.level(channel_name(ROBOTS[0].topic)) is Level.OK, statuses.snapshot()
        assert elapsed_s <= 3 * PERIOD_S, elapsed_s
