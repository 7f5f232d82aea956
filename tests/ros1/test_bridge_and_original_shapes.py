"""``dbml bridge --transport ros1`` and the original package's call shapes, on a real master."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from tests.ros1.rosnet import RosNet
from tests.ros1.test_classes import lines

pytestmark = pytest.mark.integration

NODES = "tests.ros1.original_nodes"
PAPER = "tests.ros1.paper_nodes"


def image_size() -> int:
    from tests.ros1.original_nodes import IMAGE

    wire = io.BytesIO()
    IMAGE.serialize(wire)
    return len(wire.getvalue())


def test_bridge_manages_a_plain_ros_topic(ros: RosNet) -> None:
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "4")
    ros.node("optimizer", host="127.0.0.1", module=PAPER)
    ros.node("source", "/r1/camera", host="127.0.0.2", module=NODES)
    bridge = ros.node(
        "bridge",
        "/r1/camera",
        "--min-hz",
        "1",
        "--max-hz",
        "16",
        "--transport",
        "ros1",
        host="127.0.0.2",
    )
    viewer = ros.node("viewer", "/r1/camera", host="127.0.0.3", module=PAPER)
    expected_hz = 4e6 / 8 / image_size()
    ros.wait_param(
        "/r1/camera/dbm/frequency/current_value",
        lambda v: v == pytest.approx(expected_hz),
        timeout_s=30,
        what=f"the allocation ({bridge.stderr()})",
    )
    assert ros.param("/r1/camera/dbm/message_size_in_bytes") == image_size()
    seen = lines(viewer, 3)
    assert all(s["optimized"] is True and s["width"] == 350 for s in seen)
    assert ros.rostopic("type", "/r1/camera/optimized") == "sensor_msgs/Image"
    # The full-rate topic keeps its one publisher: the bridge only subscribes to it.
    info = ros.rostopic("info", "/r1/camera")
    assert info.split("Subscribers:")[0].count(" * ") == 1, info
    rate = ros.rostopic_hz("/r1/camera/optimized", window=8, timeout_s=20)
    assert rate == pytest.approx(expected_hz, rel=0.3)


def test_a_node_written_for_the_original_runs_with_its_import_changed(ros: RosNet) -> None:
    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "4")
    ros.node("optimizer", host="127.0.0.1", module=PAPER)
    camera = ros.node("legacy", host="127.0.0.2", module=NODES, env={"ROS_NAMESPACE": "/r1"})
    viewer = ros.node("viewer", "/r1/camera", host="127.0.0.3", module=PAPER)
    expected_hz = 4e6 / 8 / image_size()
    ros.wait_param(
        "/r1/camera/dbm/frequency/current_value",
        lambda v: v == pytest.approx(expected_hz),
        timeout_s=30,
        what="the allocation",
    )
    for line in camera.json_lines(timeout_s=20):
        if line["frequency"] == pytest.approx(expected_hz):
            break
    else:
        pytest.fail(f"DBMRate('/r1/camera', 1, 16) never followed {expected_hz} Hz")
    seen = lines(viewer, 3)
    assert all(s["optimized"] is True and s["bytes"] == 84_000 for s in seen)


def test_dbm_rate_of_a_topic_without_a_publisher_follows_the_parameter_server(
    ros: RosNet,
) -> None:
    """The original's ``DBMRate(topic_name, min, max)`` in a process with no DBMPublisher."""
    follower = ros.node("follower", "/r1/camera", host="127.0.0.2", module=NODES)
    assert lines(follower, 1)[0]["frequency"] == 1.0  # the minimum before an allocation
    ros.wait_param("/r1/camera/dbm/frequency/max", lambda v: v == 16.0, what="its bounds")
    assert ros.param("/r1/camera/dbm/frequency/min") == 1.0
    # Above the maximum: capped. Below the minimum (an infeasible budget's share): kept, so the
    # budget still holds.
    for allocated, kept in ((5.0, 5.0), (50.0, 16.0), (0.5, 0.5)):
        ros.rosparam("set", "/r1/camera/dbm/frequency/current_value", str(allocated))
        for line in follower.json_lines(timeout_s=20):
            if line["frequency"] == kept:
                break
        else:
            pytest.fail(f"DBMRate never kept {kept} Hz for {allocated}:\n{follower.stderr()}")


def test_a_failing_start_thread_is_reported_and_misuse_is_refused(ros: RosNet) -> None:
    node = ros.node("failing", "/r1/camera", host="127.0.0.2", module=NODES)
    status, again, rate = lines(node, 3)
    assert status == {"alive": False, "calls": 3}
    assert again == {"start": "DBMPublisher('/r1/camera').start(): already started"}
    assert "min_frequency and max_frequency are required" in str(rate["rate"])
    # rospy sends Python logging to the node's log file, where a ROS user looks.
    logs = Path(ros.env["ROS_LOG_DIR"]).glob("failing_*.log")
    text = "".join(log.read_text(errors="replace") for log in logs)
    assert text.count("dbm-publisher /r1/camera: the thread died") == 1  # said once
    assert text.count("RuntimeError: camera unplugged") == 1
