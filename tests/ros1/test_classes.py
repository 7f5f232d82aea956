"""The paper's classes in user-written node processes, on a real master."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from tests.integration.procs import Proc
from tests.ros1.rosnet import RosNet

pytestmark = pytest.mark.integration

MODULE = "tests.ros1.paper_nodes"


def lines(proc: Proc, count: int) -> list[dict[str, object]]:
    got = []
    for line in proc.json_lines(timeout_s=30):
        got.append(line)
        if len(got) == count:
            return got
    pytest.fail(f"{proc.args}: {len(got)} of {count} lines:\n{proc.stderr()}")


def test_dbm_classes_allocate_throttle_and_deliver_images(ros: RosNet) -> None:
    from sensor_msgs.msg import Image

    image = Image(height=240, width=350, encoding="mono8", step=350, data=bytes(84_000))
    wire = io.BytesIO()
    image.serialize(wire)
    size = len(wire.getvalue())  # the serialised size, as rospy sends it

    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "4")
    ros.node("optimizer", host="127.0.0.1", module=MODULE)
    camera = ros.node("camera", host="127.0.0.2", module=MODULE, env={"ROS_NAMESPACE": "/r1"})
    remote = ros.node("viewer", "/r1/camera", host="127.0.0.3", module=MODULE)

    # The relative name resolved in the node's namespace; the parameters are absolute.
    assert lines(camera, 1)[0]["topic"] == "/r1/camera"
    expected_hz = 4e6 / 8 / size
    ros.wait_param(
        "/r1/camera/dbm/frequency/current_value",
        lambda v: v == pytest.approx(expected_hz),
        what="the allocation",
    )
    assert ros.param("/r1/camera/dbm/message_size_in_bytes") == size
    assert ros.param("/dbm/optimization_rate_in_seconds") == 1.0  # the optimizer's default
    # DBMRate follows the allocation: the publisher announces the new frequency.
    for line in camera.json_lines(timeout_s=20):
        if line["frequency"] == pytest.approx(expected_hz):
            break
    else:
        pytest.fail(f"camera never ran at {expected_hz} Hz:\n{camera.stderr()}")

    seen = lines(remote, 3)
    assert all(
        s == {"label": "seen", "width": 350, "bytes": 84_000, "optimized": True} for s in seen
    )
    assert ros.rostopic("type", "/r1/camera/optimized") == "sensor_msgs/Image"
    measured = ros.rostopic_hz("/r1/camera/optimized", window=10, timeout_s=30)
    assert measured == pytest.approx(expected_hz, rel=0.05)

    # On the camera's own host the subscriber takes the full-rate topic.
    local = ros.node("viewer", "/r1/camera", host="127.0.0.2", module=MODULE)
    assert lines(local, 1)[0]["optimized"] is False


def test_a_start_thread_that_dies_ends_the_spinning_node_with_exit_code_1(ros: RosNet) -> None:
    """A node whose camera thread died must not look alive: a supervisor restarts it."""
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "4")
    node = ros.node("/r1/camera", host="127.0.0.2", module="tests.ros1.dying_nodes")
    code = node.wait(60)
    if code is None:
        pytest.fail(f"the node still runs after its thread died:\n{node.stderr()}")
    assert code == 1, node.stderr()
    assert lines(node, 1) == [{"alive": False}]
    # rospy sends Python logging to the node's log file, where a ROS user looks.
    logs = Path(ros.env["ROS_LOG_DIR"]).glob("dying_*.log")
    text = "".join(log.read_text(errors="replace") for log in logs)
    assert text.count("dbm-publisher /r1/camera: the thread died") == 1  # said once
    assert "RuntimeError: camera unplugged" in text
    assert "a worker thread died (see above); exiting so a supervisor restarts it" in text


def test_a_start_thread_stopped_by_ros_shutdown_is_no_death_and_the_node_exits_0(
    ros: RosNet,
) -> None:
    """Ctrl-C shuts ROS down between the thread's check and its call: rospy raises, no death."""
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "4")
    node = ros.node("/r1/camera", "stopping", host="127.0.0.2", module="tests.ros1.dying_nodes")
    code = node.wait(60)
    if code is None:
        pytest.fail(f"the node still runs after ROS shut down:\n{node.stderr()}")
    assert code == 0, node.stderr()
    assert lines(node, 1) == [{"alive": False, "deaths": 0}]
    logs = Path(ros.env["ROS_LOG_DIR"]).glob("stopping_*.log")
    text = "".join(log.read_text(errors="replace") for log in logs)
    assert "signal_shutdown [keyboard interrupt]" in text  # the node's log, as it ended
    assert "the thread died" not in text
    assert "a worker thread died" not in text
