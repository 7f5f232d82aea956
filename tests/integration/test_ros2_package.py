"""The ROS 2 package ``ros2/dbml_ros``: built by colcon, started as ``ros2 run`` starts it.

ros2cli and launch are not installable here, so the test does what they do: it sources the
colcon install's ``setup.sh`` and runs ``install/dbml_ros/lib/dbml_ros/<executable>`` with the
``--ros-args`` a launch file would give (``-r __node:=``, ``-r __ns:=``, ``--params-file``);
and it checks each launch file against what is installed. Two plain rclpy cameras publish the
paper's frame sizes; a plain rclpy subscriber measures the optimized topics: the params file's
Table 1 gives Table 2's first step while the optimizer, a managed node, is active, and each
channel's minimum while it is inactive; its transitions are the ``lifecycle_msgs`` calls Nav2's
lifecycle manager makes.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dbml.experiment.analysis import RATE_TOLERANCE_HZ
from dbml.harness.ros2env import claim_domain, ros2_child_env
from dbml.harness.supervisor import Supervisor
from dbml.protocol.schema import GLOBAL_PREFIX
from dbml.scenarios.teleop import MAX_RATE_HZ, MIN_RATE_HZ, ROBOTS, STEPS
from dbml.transports.rclpy.rosargs import channel_bounds, overrides
from tests.conftest import wait_for
from tests.integration.procs import ROOT, start_rclpy_cameras
from tests.integration.test_demo import RATE_TOLERANCE, TABLE2_HZ

pytest.importorskip("rclpy")
pytest.importorskip("colcon_core")

from lifecycle_msgs.msg import Transition
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dbml.harness.ros2node import private_node
from tests.rclpy_tools import lifecycle_change, lifecycle_state

pytestmark = [pytest.mark.integration, pytest.mark.alone]
"""Alone: 84,000-byte Images at 16 Hz through real ROS 2 and two bridges. Beside a testbed run
(CI's second phase), R1 delivered 8.2 and 8.5 Hz of its 12.37 in two runs; here, alone or beside
two busy loops, 12.37."""

PACKAGE = "dbml_ros"
SOURCE = ROOT / "ros2" / PACKAGE
EXECUTABLES = ("optimizer", "bridge", "monitor")
BUILD_TIMEOUT_S = 120.0
SETTLE_S = 3.0
"""From when the rates moved (the allocation or the fail-safe took effect) to the measurement."""
MEASURE_S = 4.0
RECENT_S = 2.0
"""The span whose frames say a topic's rate of the moment (two frames at the 1-Hz minimum)."""
START_TIMEOUT_S = 60.0
OPTIMIZER_NODE = "dbml_optimizer"


@pytest.fixture(scope="module")
def install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package built by colcon, as ``colcon build`` in a workspace would."""
    base = tmp_path_factory.mktemp("colcon")
    colcon = shutil.which("colcon", path=str(Path(sys.executable).parent))
    assert colcon is not None, "colcon is installed with the dev extra"
    build = subprocess.run(
        [
            colcon,
            "--log-base",
            str(base / "log"),
            "build",
            "--base-paths",
            str(SOURCE),
            "--build-base",
            str(base / "build"),
            "--install-base",
            str(base / "install"),
        ],
        capture_output=True,
        text=True,
        timeout=BUILD_TIMEOUT_S,
        check=False,
    )
    assert build.returncode == 0, build.stdout + build.stderr
    return base / "install"


def test_colcon_installs_the_executables_launch_files_and_params(install: Path) -> None:
    share = install / PACKAGE / "share" / PACKAGE
    for executable in EXECUTABLES:
        assert (install / PACKAGE / "lib" / PACKAGE / executable).is_file()
    assert (install / PACKAGE / "share/ament_index/resource_index/packages" / PACKAGE).exists()
    assert {p.name for p in (share / "launch").iterdir()} == {
        "teleop.launch.xml",
        "teleop.launch.py",
    }
    assert (share / "config" / "teleop.yaml").is_file()


def _xml_nodes(path: Path) -> Iterator[tuple[str, str, str]]:
    """Each ``<node>`` of an XML launch file: package, executable, namespace."""
    for node in ET.parse(path).getroot().iter("node"):
        yield node.get("pkg", ""), node.get("exec", ""), node.get("namespace", "")


def _python_nodes(path: Path) -> Iterator[tuple[str, str, list[str]]]:
    """Each ``Node(...)`` of a Python launch file: package, executable, namespaces it takes."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    robots: list[str] = []
    for statement in tree.body:  # ROBOTS = ("r1", "r2"): the namespaces a comprehension gives
        if isinstance(statement, ast.Assign) and isinstance(statement.value, ast.Tuple):
            robots = [ast.literal_eval(e) for e in statement.value.elts]
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", "") == "Node":
            words = {k.arg: k.value for k in call.keywords}
            package = ast.literal_eval(words["package"])
            executable = ast.literal_eval(words["executable"])
            namespace = words.get("namespace")
            if namespace is None:
                yield package, executable, [""]
            elif isinstance(namespace, ast.Constant):
                yield package, executable, [str(namespace.value)]
            else:
                yield package, executable, robots


def test_every_launch_file_starts_what_is_installed_with_the_schemas_parameters(
    install: Path,
) -> None:
    """What ``ros2 launch`` would check at run time, checked here (ros2 launch is not here)."""
    share = install / PACKAGE / "share" / PACKAGE
    params = share / "config" / "teleop.yaml"
    values = overrides(["--params-file", str(params)])  # every key one the schema declares
    started: dict[str, list[tuple[str, str]]] = {}
    xml = [(p, e, [ns]) for p, e, ns in _xml_nodes(share / "launch" / "teleop.launch.xml")]
    for name, nodes in (
        ("teleop.launch.xml", xml),
        ("teleop.launch.py", list(_python_nodes(share / "launch" / "teleop.launch.py"))),
    ):
        started[name] = []
        for package, executable, namespaces in nodes:
            assert package == PACKAGE
            assert (install / PACKAGE / "lib" / PACKAGE / executable).is_file(), executable
            started[name] += [(executable, ns) for ns in namespaces]
            if executable == "bridge":  # each bridge finds its robot's channels in the file
                for namespace in namespaces:
                    assert channel_bounds(values, namespace=f"/{namespace}")
    expected = [("optimizer", ""), ("bridge", "r1"), ("bridge", "r2")]
    assert started == {"teleop.launch.xml": expected, "teleop.launch.py": expected}
    # The file is the paper's Table 1 and the priorities of Table 2's first step (eq. 7).
    assert values[f"{GLOBAL_PREFIX}/max_bandwidth_in_mbit"] == 11.0
    for camera, event in zip(ROBOTS, STEPS[0].events, strict=True):
        assert values[f"{camera.topic}/dbm/frequency/min"] == MIN_RATE_HZ
        assert values[f"{camera.topic}/dbm/frequency/max"] == MAX_RATE_HZ
        assert values[f"{camera.topic}/dbm/priority"] == pytest.approx(event.priority)


def _ros2_run(
    children: Supervisor,
    name: str,
    *,
    install: Path,
    executable: str,
    ros_args: list[str],
    env: dict[str, str],
    own: tuple[str, ...] = (),
) -> None:
    """What ``ros2 run dbml_ros EXECUTABLE [OWN] --ros-args ...`` starts, the install sourced."""
    script = f'. "{install}/setup.sh" && exec "{install}/{PACKAGE}/lib/{PACKAGE}/$0" "$@"'
    argv = ["bash", "-c", script, executable, *own, "--ros-args", *ros_args]
    children.start(name, argv, env=env, stdin=False)


def test_ros2_run_with_the_params_file_gives_table_2s_first_step_while_active(
    install: Path, tmp_path: Path
) -> None:
    """The optimizer as a managed node, driven as Nav2's lifecycle manager drives one.

    Active, the params file's Table 1 gives Table 2's first step; inactive, every channel runs
    at its minimum, as it does with no optimizer at all (the fail-safe); shut down, it exits 0.
    """
    params = str(install / PACKAGE / "share" / PACKAGE / "config" / "teleop.yaml")
    topics = [f"{c.topic}/optimized" for c in ROBOTS]
    with claim_domain() as domain_id, Supervisor(logs=tmp_path / "logs") as children:
        env = ros2_child_env(domain_id=domain_id, log_dir=tmp_path / "ros")
        start_rclpy_cameras(children, env)
        _ros2_run(
            children,
            "optimizer",
            install=install,
            executable="optimizer",
            own=("--lifecycle",),
            ros_args=["-r", f"__node:={OPTIMIZER_NODE}", "--params-file", params],
            env=env,
        )
        for camera in ROBOTS:
            namespace = camera.topic.rsplit("/", 1)[0]
            _ros2_run(
                children,
                f"bridge-{camera.robot}",
                install=install,
                executable="bridge",
                ros_args=[
                    *("-r", "__node:=dbml_bridge", "--params-file", params),
                    *("-r", f"__ns:={namespace}"),
                ],
                env=env,
            )
        target = f"/{OPTIMIZER_NODE}"
        with private_node("operator", domain_id=domain_id) as operator:
            meter = _Meter(operator, topics, children)
            assert lifecycle_state(operator, target, wait_s=START_TIMEOUT_S) == "unconfigured"
            assert lifecycle_change(operator, target, Transition.TRANSITION_CONFIGURE)
            assert lifecycle_state(operator, target) == "inactive"
            assert lifecycle_change(operator, target, Transition.TRANSITION_ACTIVATE)
            # the allocation took effect: each topic within 10 % of step 1 over the last 2 s (in
            # three CI runs R1 read 8.1-8.5 Hz of 12.37 over a window from 5-7 s after the
            # activation; why is not known, so this waits for the rate itself)
            meter.wait(
                lambda hz: all(
                    abs(h - t) <= 0.1 * t for h, t in zip(hz, TABLE2_HZ[0], strict=True)
                ),
                what="Table 2's step 1",
            )
            active = meter.rates(settle_s=SETTLE_S)
            assert lifecycle_change(operator, target, Transition.TRANSITION_DEACTIVATE)
            meter.wait(lambda hz: all(h < 2 * MIN_RATE_HZ for h in hz), what="the fail-safe")
            inactive = meter.rates(settle_s=SETTLE_S)
            assert lifecycle_change(operator, target, Transition.TRANSITION_INACTIVE_SHUTDOWN)
            optimizer = children.children["optimizer"]
            wait_for(
                lambda: optimizer.poll() is not None, timeout_s=10, what="the optimizer's exit"
            )
            assert optimizer.poll() == 0, optimizer.log_tail()
    for measured, table2_hz in zip(active, TABLE2_HZ[0], strict=True):
        assert measured == pytest.approx(table2_hz, rel=RATE_TOLERANCE), active
    for measured in inactive:  # no allocation heard: each channel's fail-safe minimum
        assert measured == pytest.approx(MIN_RATE_HZ, abs=RATE_TOLERANCE_HZ), inactive


class _Meter:
    """A plain rclpy subscriber of each topic, timing its frames."""

    def __init__(self, node: Any, topics: list[str], children: Supervisor) -> None:
        from sensor_msgs.msg import Image

        self._topics = topics
        self._children = children
        self._lock = threading.Lock()
        self._arrivals: dict[str, list[float]] = {topic: [] for topic in topics}
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        for topic in topics:
            node.create_subscription(
                Image, topic, lambda _m, topic=topic: self._heard(topic), qos, raw=True
            )

    def _heard(self, topic: str) -> None:
        with self._lock:
            self._arrivals[topic].append(time.monotonic())

    def _flowing(self) -> bool:
        for child in self._children.children.values():
            assert child.poll() is None, f"{child.name} ended: {child.log_tail()}"
        with self._lock:
            return all(self._arrivals.values())

    def wait(self, done: Callable[[list[float]], bool], *, what: str) -> None:
        """Wait until ``done`` holds of each topic's frames a second over the last ``RECENT_S``."""

        def recent() -> list[float]:
            now = time.monotonic()
            with self._lock:
                return [
                    sum(1 for t in self._arrivals[topic] if t > now - RECENT_S) / RECENT_S
                    for topic in self._topics
                ]

        wait_for(lambda: self._flowing() and done(recent()), timeout_s=START_TIMEOUT_S, what=what)

    def rates(self, *, settle_s: float) -> list[float]:
        """Each topic's rate over ``MEASURE_S``, from ``settle_s`` after all have sent frames."""
        wait_for(self._flowing, timeout_s=START_TIMEOUT_S, what="frames on every topic")
        start = time.monotonic() + settle_s
        end = start + MEASURE_S
        wait_for(lambda: time.monotonic() > end + 0.5, timeout_s=settle_s + MEASURE_S + 5)
        with self._lock:
            windows = [
                [t for t in self._arrivals[topic] if start <= t < end] for topic in self._topics
            ]
        return [(len(w) - 1) / (w[-1] - w[0]) if len(w) > 1 else 0.0 for w in windows]
