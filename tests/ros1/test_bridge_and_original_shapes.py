"""``dbml bridge --transport ros1`` and the original package's call shapes, on a real master."""

from __future__ import annotations

import io

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
