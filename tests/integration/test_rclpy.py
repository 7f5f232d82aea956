"""dbml on real ROS 2 (rclpy, Fast DDS) as real processes: driver, bridge, optimizer, viewers.

The driver is a plain rclpy node (``rclpy_driver``); ``dbml bridge`` and ``dbml optimizer`` run
with ``--transport rclpy``; the operator's side is plain rclpy in this process: the budget set
as ``ros2 param set`` sets it (``SetParameters``), and an rviz-like raw subscriber measuring
what arrives as ``ros2 topic hz`` would, counting bytes per sliding 1-s window by publisher.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from dbml.harness.ros2env import claim_domain, ros2_child_env
from tests.conftest import wait_for
from tests.integration.procs import Proc

pytest.importorskip("rclpy")

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import Float64

from dbml.harness.ros2node import private_node, received_monotonic
from dbml.transports.rclpy import RclpyTransport
from tests.rclpy_tools import param_set

pytestmark = pytest.mark.integration

CAMERA = "/r1/camera"
SIZE_BYTES = 84_000
DRIVER_HZ = 16.0
BUDGET_MBIT = 5
"""An integer, as ``ros2 param set /dbm max_bandwidth_in_mbit 5`` sends it."""
EXPECTED_HZ = BUDGET_MBIT * 1e6 / 8 / SIZE_BYTES
"""7.44 Hz: the whole budget to the one managed channel (the paper's utilisation of 1)."""
TOLERANCE = 0.05
WINDOW_S = 1.0
MEASURE_S = 4.0
START_S = 30.0
"""Discovery, the bridge's first frame and the first allocations, generously."""


@dataclass
class Viewer:
    """Arrivals of one topic by publisher GID: (monotonic time, bytes)."""

    arrivals: dict[bytes, list[tuple[float, int]]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    subscription: Any = None

    def heard(self, data: bytes, info: Any) -> None:
        """Stamped when DDS received it: windows by the callback's time also count its lag."""
        received = received_monotonic(info, now=time.monotonic(), wall_ns=time.time_ns())
        gid = bytes(info["publisher_gid"]["data"])[:16] if info.get("publisher_gid") else b""
        with self.lock:
            self.arrivals.setdefault(gid, []).append((received, len(data)))

    def since(self, start: float) -> dict[bytes, list[tuple[float, int]]]:
        with self.lock:
            return {g: [a for a in got if a[0] >= start] for g, got in self.arrivals.items()}


def rate_hz(arrivals: list[tuple[float, int]], span_s: float) -> float:
    return len(arrivals) / span_s


def worst_window_bytes(arrivals: list[tuple[float, int]]) -> int:
    """The most bytes in any 1-s window starting at an arrival."""
    times = [t for t, _ in arrivals]
    worst = 0
    for i, start in enumerate(times):
        worst = max(worst, sum(n for t, n in arrivals[i:] if t < start + WINDOW_S))
    return worst


@dataclass
class Ros2Run:
    env: dict[str, str]
    domain_id: int
    procs: list[Proc]

    def start(self, *args: str, module: str = "dbml") -> Proc:
        proc = Proc(list(args), self.env, module=module)
        self.procs.append(proc)
        return proc


@pytest.fixture
def ros2(tmp_path: Path) -> Iterator[Ros2Run]:
    with claim_domain() as domain_id:
        run = Ros2Run(ros2_child_env(domain_id=domain_id, log_dir=tmp_path / "ros"), domain_id, [])
        try:
            yield run
        finally:
            for proc in run.procs:
                proc.stop()


def _start_managed(ros2: Ros2Run, qos: str) -> None:
    ros2.start(
        CAMERA, str(SIZE_BYTES), str(DRIVER_HZ), qos, module="tests.integration.rclpy_driver"
    )
    ros2.start("optimizer", "--transport", "rclpy", "--host", "ground")
    ros2.start(
        "bridge", CAMERA, "--transport", "rclpy", "--host", "r1", "--min-hz", "1", "--max-hz", "16"
    )


def _viewer(node: Node, reliability: ReliabilityPolicy) -> Viewer:
    viewer = Viewer()
    viewer.subscription = node.create_subscription(
        Image,
        f"{CAMERA}/optimized",
        viewer.heard,
        QoSProfile(depth=10, reliability=reliability),
        raw=True,
    )
    return viewer


def _set_budget(node: Node) -> None:
    """``ros2 param set /dbm max_bandwidth_in_mbit 5`` once the optimizer's node answers."""
    result = param_set(node, "/dbm", "max_bandwidth_in_mbit", BUDGET_MBIT, wait_s=START_S)
    assert result.successful, result.reason


def _measure(viewer: Viewer) -> dict[bytes, list[tuple[float, int]]]:
    """Wait until the rate has settled at the allocation, then measure ``MEASURE_S``."""
    wait_for(
        lambda: any(
            abs(rate_hz(a, 2.0) - EXPECTED_HZ) <= EXPECTED_HZ * TOLERANCE
            for a in viewer.since(time.monotonic() - 2.0).values()
        ),
        timeout_s=START_S,
        what=f"{CAMERA}/optimized at {EXPECTED_HZ:.2f} Hz",
    )
    start = time.monotonic()
    wait_for(lambda: time.monotonic() >= start + MEASURE_S, timeout_s=MEASURE_S + 1, what="span")
    return viewer.since(start)


@pytest.mark.parametrize("qos", ["reliable", "best_effort"])
def test_a_driver_is_managed_at_the_allocated_rate(ros2: Ros2Run, qos: str) -> None:
    """A reliable and a best-effort driver both: the bridge matches its QoS."""
    _start_managed(ros2, qos)
    with private_node("operator", domain_id=ros2.domain_id) as operator:
        viewer = _viewer(operator, ReliabilityPolicy.RELIABLE)
        _set_budget(operator)
        got = _measure(viewer)
        assert len(got) == 1, "one publisher of the optimized copy: the bridge"
        arrivals = next(iter(got.values()))
        assert rate_hz(arrivals, MEASURE_S) == pytest.approx(EXPECTED_HZ, rel=TOLERANCE)
        assert all(size == SIZE_BYTES for _t, size in arrivals)
        budget_bytes = BUDGET_MBIT * 1e6 / 8
        assert worst_window_bytes(arrivals) <= budget_bytes + SIZE_BYTES
        # The remote consumer leaves: the channel is no longer managed (back to its maximum).
        with RclpyTransport(host="observer", domain_id=ros2.domain_id) as observer:
            managed = f"{CAMERA}/dbm/managed"
            wait_for(lambda: observer.params.get(managed) is True, timeout_s=10, what="managed")
            operator.destroy_subscription(viewer.subscription)
            wait_for(lambda: observer.params.get(managed) is False, timeout_s=10, what="unmanaged")


def test_hostile_nodes_leave_the_budget_on_the_wire_intact(ros2: Ros2Run) -> None:
    """Hostile nodes change nothing: the bridge's bytes still fit the budget.

    Bad values through the services, a foreign publisher of the optimized copy, a flood of
    priorities.
    """
    _start_managed(ros2, "reliable")
    with (
        private_node("operator", domain_id=ros2.domain_id) as operator,
        private_node("hostile", domain_id=ros2.domain_id) as hostile,
    ):
        viewer = _viewer(operator, ReliabilityPolicy.BEST_EFFORT)
        _set_budget(operator)
        _measure(viewer)
        for name, value in (
            ("max_bandwidth_in_mbit", -3),
            ("max_bandwidth_in_mbit", "lots"),
            ("max_bandwidth_utilization", 7.0),
            ("status", "optimal"),
        ):
            assert not param_set(hostile, "/dbm", name, value).successful, (name, value)
        for name, value in (("frequency.max", 1000.0), ("frequency.current_value", 16.0)):
            assert not param_set(hostile, f"{CAMERA}/dbm", name, value).successful, (name, value)
        impostor = hostile.create_publisher(Image, f"{CAMERA}/optimized", 10)
        flood = hostile.create_publisher(Float64, f"{CAMERA}/dbm/priority", 10)
        stop = threading.Event()

        def attack() -> None:
            junk = Image(height=1, width=1000, encoding="mono8", step=1000, data=bytes(1000))
            for n in range(20_000):  # bounded: about 10 s
                if stop.wait(0.0005):
                    return
                flood.publish(Float64(data=(n % 100) / 100.0))
                if n % 10 == 0:
                    impostor.publish(junk)

        thread = threading.Thread(target=attack, daemon=True)
        thread.start()
        try:
            start = time.monotonic()
            wait_for(
                lambda: time.monotonic() >= start + MEASURE_S, timeout_s=MEASURE_S + 1, what="span"
            )
            got = viewer.since(start)
        finally:
            stop.set()
            thread.join(5.0)
        impostors = {
            bytes(info.endpoint_gid)[:16]
            for info in hostile.get_publishers_info_by_topic(f"{CAMERA}/optimized")
            if info.node_name == "hostile"
        }
        assert impostors, "the impostor was in the graph"
        assert any(got.get(g) for g in impostors), "the impostor's frames were heard"
        bridge = {g: a for g, a in got.items() if a and g not in impostors}
        assert len(bridge) == 1, "the bridge kept publishing"
        arrivals = next(iter(bridge.values()))
        assert worst_window_bytes(arrivals) <= BUDGET_MBIT * 1e6 / 8 + SIZE_BYTES
        assert rate_hz(arrivals, MEASURE_S) <= EXPECTED_HZ * (1 + TOLERANCE)


def test_a_type_whose_package_is_missing_names_what_to_install(ros2: Ros2Run) -> None:
    bridge = ros2.start(
        "bridge",
        "/r1/costmap",
        "--type",
        "nav2_msgs/msg/Costmap",
        "--transport",
        "rclpy",
        "--min-hz",
        "1",
        "--max-hz",
        "5",
    )
    assert bridge.wait(START_S) == 2
    bridge.stop()
    assert bridge.stderr() == (
        "dbml: error: type='nav2_msgs/msg/Costmap': Python package 'nav2_msgs' is missing: "
        "pip install ros-nav2-msgs (or source the ROS 2 that has it)\n"
    )
