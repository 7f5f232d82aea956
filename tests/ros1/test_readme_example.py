"""The README's ROS 1 example node, run as written beside the optimizer node and an operator."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.integration.procs import ROOT
from tests.ros1.rosnet import RosNet

pytestmark = pytest.mark.integration


def readme_node() -> str:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    ros1 = [b for b in blocks if "import rospy" in b]
    assert len(ros1) == 1
    return str(ros1[0])


def test_readme_example_is_short_and_runs_managed(ros: RosNet, tmp_path: Path) -> None:
    source = readme_node()
    assert len(source.splitlines()) <= 15
    (tmp_path / "readme_camera.py").write_text(source)

    ros.rosparam("set", "/dbm/max_bandwidth_in_mbit", "5")
    ros.node("optimizer", "--transport", "ros1", host="127.0.0.1")
    env = {"ROS_NAMESPACE": "/r1", "PYTHONPATH": str(tmp_path)}
    ros.node(host="127.0.0.2", module="readme_camera", env=env)
    viewer = ros.node("subscribe", "/r1/camera", "--transport", "ros1", "--json", host="127.0.0.3")

    size = ros.wait_param("/r1/camera/dbm/message_size_in_bytes", bool, what="a size")
    assert isinstance(size, int)
    assert size > 84_000  # the pixels and the Image's header fields
    expected = 5e6 / 8 / size
    ros.wait_param(
        "/r1/camera/dbm/frequency/current_value",
        lambda v: v == pytest.approx(expected),
        what="the allocation",
    )
    for line in viewer.json_lines(timeout_s=20):
        if line["variant"] == "optimized" and line["rate_hz"] == pytest.approx(expected, rel=0.1):
            break
    else:
        pytest.fail(f"the operator never received ~{expected:.2f} Hz:\n{viewer.stderr()}")
