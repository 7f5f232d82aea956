"""The control traffic of the sent rate (``[topic]/dbm/frequency/sent_value``) over real ROS 2.

The paper's two cameras as plain rclpy drivers (84,000 and 21,000-byte Images at 16 Hz), a
``dbml bridge`` per robot and ``dbml optimizer``, all ``--transport rclpy`` from the ROS 2
package's params file (Table 1, Table 2's first priorities), and a plain rclpy consumer of
each optimized topic, so both channels are managed. This process counts the parameter events
on ``/parameter_events`` (each serialised, its bytes counted): over a steady window, and over
the seconds after one driver ends. Reference, in the same run: the optimizer's heartbeat
(``round``, one event a period), the traffic that exists without the sent rate.

    python bench/sent_rate_traffic.py [--steady-s 20] [--settle-s 15]
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import ParameterEvent
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from dbml.harness.ros2env import claim_domain, ros2_child_env
from dbml.harness.ros2node import private_node
from dbml.harness.supervisor import ProcessChild, Supervisor
from dbml.scenarios.teleop import MAX_RATE_HZ, ROBOTS

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ROOT / "ros2" / "dbml_ros" / "config" / "teleop.yaml"
AFTER_DEATH_S = 5.0
"""How long the events after a driver's end are counted."""


class Events:
    """Parameter events as heard: (time, parameter names, serialised bytes)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._heard: list[tuple[float, list[str], int]] = []

    def heard(self, event: Any) -> None:
        names = [p.name for p in (*event.new_parameters, *event.changed_parameters)]
        size = len(serialize_message(event))
        with self._lock:
            self._heard.append((time.monotonic(), names, size))

    def window(self, start: float, end: float, field: str) -> dict[str, int]:
        """Events naming ``field`` in ``[start, end)``, and their bytes."""
        with self._lock:
            inside = [(n, b) for t, n, b in self._heard if start <= t < end and field in n]
        return {"events": len(inside), "bytes": sum(b for _n, b in inside)}


def _start(children: Supervisor, env: dict[str, str]) -> dict[str, ProcessChild]:
    """The cameras, the optimizer and the bridges; the cameras by topic."""
    cameras = {  # the tests' plain rclpy driver, run from the repository
        camera.topic: children.start(
            f"camera-{camera.robot}",
            [
                sys.executable,
                *("-m", "tests.integration.rclpy_camera", camera.topic),
                *(str(MAX_RATE_HZ), str(camera.size_bytes)),
            ],
            env=env,
            cwd=ROOT,
            stdin=False,
        )
        for camera in ROBOTS
    }
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
    return cameras


def measure(*, settle_s: float, steady_s: float) -> dict[str, Any]:
    """The steady window's and the driver's end's events, with the heartbeat's beside them."""
    events = Events()
    stop = threading.Event()
    with (
        tempfile.TemporaryDirectory() as tmp,
        claim_domain() as domain_id,
        Supervisor(logs=Path(tmp) / "logs") as children,
    ):
        env = ros2_child_env(domain_id=domain_id, log_dir=Path(tmp) / "ros")
        cameras = _start(children, env)
        with private_node("probe", domain_id=domain_id) as node:
            consumer = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
            for camera in ROBOTS:
                topic = f"{camera.topic}/optimized"
                node.create_subscription(Image, topic, lambda _m: None, consumer, raw=True)
            node.create_subscription(ParameterEvent, "/parameter_events", events.heard, 100)
            stop.wait(settle_s)  # a bench, not a test: the run settles for a fixed time
            start = time.monotonic()
            stop.wait(steady_s)
            end = time.monotonic()
            cameras[ROBOTS[1].topic].send_signal(signal.SIGTERM)
            died = time.monotonic()
            stop.wait(AFTER_DEATH_S)
            after = time.monotonic()
    return {
        "steady_s": round(end - start, 1),
        "steady": {
            "sent_value": events.window(start, end, "frequency.sent_value"),
            "reference_round": events.window(start, end, "round"),
        },
        "after_driver_end_s": round(after - died, 1),
        "after_driver_end": {
            "sent_value": events.window(died, after, "frequency.sent_value"),
            "reference_round": events.window(died, after, "round"),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steady-s", type=float, default=20.0)
    parser.add_argument("--settle-s", type=float, default=15.0)
    args = parser.parse_args()
    print(json.dumps(measure(settle_s=args.settle_s, steady_s=args.steady_s), indent=2))


if __name__ == "__main__":
    main()
