"""The ROS 1 messages dbml makes itself are what rospy serialises."""

from __future__ import annotations

import pytest

from dbml.transports.codecs import ROS1_FLOAT64, ROS1_IMAGE, ROS1_IMAGE_OVERHEAD_BYTES
from tests.ros1.rosnet import require_ros1


@pytest.fixture(autouse=True)
def _ros1() -> None:
    require_ros1()


@pytest.mark.parametrize("size_bytes", [ROS1_IMAGE_OVERHEAD_BYTES, 21_000, 84_000])
def test_a_camera_frame_is_rospys_image_of_that_size(size_bytes: int) -> None:
    from sensor_msgs.msg import Image

    from dbml.transports.ros1.transport import serialize

    pixels = size_bytes - ROS1_IMAGE_OVERHEAD_BYTES
    image = Image(height=1, width=pixels, step=pixels, encoding="mono8", data=bytes(pixels))
    assert ROS1_IMAGE.encode(size_bytes) == serialize(image)
    assert ROS1_IMAGE.msg_type == Image._type


def test_a_float64_is_rospys() -> None:
    from std_msgs.msg import Float64

    from dbml.transports.ros1.transport import serialize

    assert ROS1_FLOAT64.encode(0.8) == serialize(Float64(data=0.8))
    assert ROS1_FLOAT64.decode(serialize(Float64(data=0.25))) == 0.25
    assert ROS1_FLOAT64.msg_type == Float64._type
