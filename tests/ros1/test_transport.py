"""The ros1 transport against a real master.

``dbml`` node processes on their own ROS hosts, checked with the real parameter server,
``rosparam`` and ``rostopic``.
"""

from __future__ import annotations

import signal
import time

import pytest

from dbml.runtime.priority import PRIORITY_INTERVAL_S
from dbml.transports.ros1.master import MasterClient
from dbml.transports.ros1.params import Ros1Params
from tests.conftest import wait_for
from tests.integration.procs import Proc, publish_argv
from tests.ros1.rosnet import RosNet

pytestmark = pytest.mark.integration

OPTIMIZER, ROBOT, OPERATOR = "127.0.0.1", "127.0.0.2", "127.0.0.3"
CAMERA = "/r1/camera"
SIZE = 84_000
PRIORITY_NODE = "tests.ros1.priority_node"


def hz_for(budget_mbit: float, size_bytes: int = SIZE) -> float:
    """What one managed channel gets: the budget divided by its message size."""
    return budget_mbit * 1e6 / 8 / size_bytes


def close_to(expected: float, rel: float = 1e-6) -> object:
    return lambda v: isinstance(v, float) and v == pytest.approx(expected, rel=rel)


def start_camera(ros: RosNet, topic: str = CAMERA, size: int = SIZE, *more: str) -> Proc:
    return ros.node(*publish_argv(topic, size, "--transport", "ros1", *more), host=ROBOT)


def start_viewer(ros: RosNet, topic: str = CAMERA, host: str = OPERATOR) -> Proc:
    return ros.node("subscribe", topic, "--transport", "ros1", "--json", host=host)


def start_optimizer(ros: RosNet) -> Proc:
    return ros.node("optimizer", "--transport", "ros1", host=OPTIMIZER)


def first_variant(proc: Proc) -> str:
    for line in proc.json_lines(timeout_s=20):
        return str(line["variant"])
    pytest.fail(f"subscriber printed nothing:\n{proc.stderr()}")


def test_parameters_live_on_the_parameter_server_under_the_papers_names(ros: RosNet) -> None:
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "11")
    start_optimizer(ros)
    # A lone channel with a priority gets its maximum (10.75 Mbit/s) first: feasible at 11.
    start_camera(ros, CAMERA, SIZE, "--priority", "0.5")
    start_viewer(ros)
    ros.wait_param(f"{CAMERA}/dbm/managed", lambda v: v is True, what="managed")
    ros.wait_param(f"{CAMERA}/dbm/frequency/current_value", lambda v: v == 16.0, what="16 Hz")

    # Every name of the paper, read back with the real rosparam tool.
    assert float(ros.rosparam("get", "/dbm/max_bandwidth_in_mbit")) == 11.0
    assert float(ros.rosparam("get", "/dbm/max_bandwidth_utilization")) == 1.0
    assert float(ros.rosparam("get", "/dbm/optimization_rate_in_seconds")) == 1.0
    assert float(ros.rosparam("get", f"{CAMERA}/dbm/frequency/min")) == 1.0
    assert float(ros.rosparam("get", f"{CAMERA}/dbm/frequency/max")) == 16.0
    assert int(ros.rosparam("get", f"{CAMERA}/dbm/message_size_in_bytes")) == SIZE
    assert float(ros.rosparam("get", f"{CAMERA}/dbm/priority")) == 0.5
    assert ros.rosparam("get", "/dbm/status") == "optimal"
    # The topics are real ROS topics of a real message class.
    assert ros.rostopic("type", f"{CAMERA}/optimized") == "sensor_msgs/Image"
    assert ros.rostopic("type", CAMERA) == "sensor_msgs/Image"

    # A budget below every minimum is reported, and the rates still fit in it.
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "0.1")
    ros.wait_param("/dbm/status", lambda v: v == "infeasible", what="infeasible")
    message = ros.param("/dbm/status_message")
    assert isinstance(message, str)
    assert message
    rate = ros.wait_param(
        f"{CAMERA}/dbm/frequency/current_value", lambda v: v < 1.0, what="a rate below min"
    )
    assert isinstance(rate, float)
    assert rate * SIZE * 8 <= 0.1e6 * (1 + 1e-9)

    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "11")
    ros.wait_param("/dbm/status", lambda v: v == "optimal", what="optimal again")


def test_the_optimized_topic_runs_at_the_allocated_rate(ros: RosNet) -> None:
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "6")
    start_optimizer(ros)
    start_camera(ros)
    start_viewer(ros)
    topic = f"{CAMERA}/optimized"
    allocated = ros.wait_param(
        f"{CAMERA}/dbm/frequency/current_value", close_to(hz_for(6)), what="6 Mbit/s"
    )
    assert isinstance(allocated, float)
    measured = ros.rostopic_hz(topic, window=15, timeout_s=30)
    assert measured == pytest.approx(allocated, rel=0.05)

    # A new budget set with rosparam reaches the publisher at once, and the topic follows.
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "3")
    allocated = ros.wait_param(
        f"{CAMERA}/dbm/frequency/current_value", close_to(hz_for(3)), timeout_s=3, what="3"
    )
    assert isinstance(allocated, float)
    ros.wait_param(
        f"{CAMERA}/dbm/frequency/applied_value", close_to(allocated), timeout_s=3, what="ack"
    )
    measured = ros.rostopic_hz(topic, window=10, timeout_s=30)
    assert measured == pytest.approx(allocated, rel=0.05)


def test_a_remote_subscriber_makes_a_topic_managed_and_its_departure_frees_it(
    ros: RosNet,
) -> None:
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "4")
    start_optimizer(ros)
    start_camera(ros)
    current = f"{CAMERA}/dbm/frequency/current_value"
    ros.wait_param(current, lambda v: v == 16.0, what="max without subscribers")

    # A subscriber on the publisher's host takes the full topic: still unmanaged.
    local = start_viewer(ros, host=ROBOT)
    assert first_variant(local) == "full"
    assert ros.param(f"{CAMERA}/dbm/managed") is False
    assert ros.param(current) == 16.0

    # One on another host takes /optimized, which makes the topic managed.
    remote = start_viewer(ros)
    assert first_variant(remote) == "optimized"
    ros.wait_param(current, close_to(hz_for(4)), what="the managed rate")
    assert ros.param(f"{CAMERA}/dbm/managed") is True

    remote.stop(signal.SIGTERM)  # it unregisters on the way out
    ros.wait_param(current, lambda v: v == 16.0, what="max after it left")
    assert ros.param(f"{CAMERA}/dbm/managed") is False

    # A subscriber killed outright never unregisters: the master keeps it, dbml sees it gone.
    killed = start_viewer(ros)
    assert first_variant(killed) == "optimized"
    ros.wait_param(current, close_to(hz_for(4)), what="managed again")
    killed.stop(signal.SIGKILL)
    ros.wait_param(current, lambda v: v == 16.0, what="max after a kill")


def test_rosparam_set_of_a_priority_moves_the_bandwidth(ros: RosNet) -> None:
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "11")
    # A 30 s period: only the change itself can trigger the new allocations in time.
    ros.rosparam("set", "/dbm/optimization_rate_in_seconds", "30")
    start_optimizer(ros)
    start_camera(ros, "/r1/camera", 84_000)
    start_camera(ros, "/r2/camera", 21_000)
    start_viewer(ros, "/r1/camera")
    start_viewer(ros, "/r2/camera")
    budget = 11e6 / 8
    for robot in ("r1", "r2"):
        ros.wait_param(f"/{robot}/camera/dbm/managed", lambda v: v is True, what=f"{robot} managed")
        ros.wait_param(f"/{robot}/camera/dbm/message_size_in_bytes", bool, what=f"{robot} size")

    ros.rosparam("set", "/r1/camera/dbm/priority", "1.0")
    # R1 first gets its maximum; R2 the rest (the paper's Table 2, steps 3-5: 16 and 1.48 Hz).
    r1, r2 = "/r1/camera/dbm/frequency/current_value", "/r2/camera/dbm/frequency/current_value"
    ros.wait_param(r1, lambda v: v == 16.0, timeout_s=2, what="R1 max")
    ros.wait_param(r2, close_to((budget - 16 * 84_000) / 21_000), timeout_s=2, what="R2 the rest")

    ros.rosparam("set", "/r1/camera/dbm/priority", "0.0")
    ros.rosparam("set", "/r2/camera/dbm/priority", "1.0")
    # Now R2 first: 16 Hz, and R1 the rest (steps 1, 8-10: 12.37 Hz).
    ros.wait_param(r2, lambda v: v == 16.0, timeout_s=2, what="R2 max")
    ros.wait_param(r1, close_to((budget - 16 * 21_000) / 84_000), timeout_s=2, what="R1 the rest")


def test_a_float64_on_the_priority_topic_sets_the_priority_and_a_flood_keeps_the_rule(
    ros: RosNet,
) -> None:
    """``rostopic pub`` (or a mission node) of ``std_msgs/Float64`` on ``[topic]/dbm/priority``."""
    name = f"{CAMERA}/dbm/priority"
    camera = start_camera(ros)
    ros.wait_param(f"{CAMERA}/dbm/frequency/max", lambda v: v == 16.0, what="the camera up")
    client = MasterClient(ros.master.uri, caller_id="/priority_test")
    watcher = Ros1Params(client, "/priority_test", "127.0.0.1", "127.0.0.1")
    writes: list[tuple[float, object]] = []
    watcher.replica.watch(lambda n, v: writes.append((time.monotonic(), v)) if n == name else None)
    try:
        node = ros.node(f"{CAMERA}/dbm/priority", "0.7", "1.5", module=PRIORITY_NODE, host=OPERATOR)
        ros.wait_param(name, lambda v: v == 0.7, what="the Float64's priority")
        wait_for(
            lambda: f"ignoring a priority: {name}=1.5 must be within [0, 1]" in camera.stderr(),
            timeout_s=10,
            what="the bad one refused, named",
        )
        node.stop()
        assert ros.param(name) == 0.7
        flood = [round(0.001 * i, 3) for i in range(1, 1_000)]
        started = time.monotonic()
        node = ros.node(
            f"{CAMERA}/dbm/priority", *map(str, flood), module=PRIORITY_NODE, host=OPERATOR
        )
        ros.wait_param(name, lambda v: v == flood[-1], what="the flood's newest, at its end")
        node.stop()
        during = [(t, v) for t, v in writes if t >= started]
        span_s = during[-1][0] - during[0][0]
        # One write per interval at most (the first at once; its spacing seen here jitters by
        # a write's trip through the master): far fewer than the messages.
        assert len(during) <= span_s / PRIORITY_INTERVAL_S + 2, (len(during), span_s)
        assert len(during) < len(flood) / 10
        assert during[-1][1] == flood[-1]
    finally:
        watcher.close()
        client.close()


def test_bad_input_is_one_line_and_exit_2(ros: RosNet) -> None:
    proc = ros.node("optimizer", "--transport", "ros1", "--estimate", host=OPTIMIZER)
    assert proc.wait(30) == 2
    lines = [line for line in proc.stderr().splitlines() if line.strip()]
    assert len(lines) == 1
    assert "--estimate" in lines[0]
    proc = ros.node(
        "subscribe", CAMERA, "--transport", "ros1", "--connect", "tcp/127.0.0.1:1", host=OPERATOR
    )
    assert proc.wait(30) == 2
    assert "transport='ros1' takes no endpoints" in proc.stderr()


def test_no_master_is_a_clear_error(ros: RosNet) -> None:
    dead = dict(ros.env, ROS_MASTER_URI="http://127.0.0.1:9/")
    broken = Proc(["monitor", "--transport", "ros1", "--duration", "1"], dead)
    ros.procs.append(broken)
    assert broken.wait(30) == 2
    assert "no ROS master at ROS_MASTER_URI=http://127.0.0.1:9/" in broken.stderr()
