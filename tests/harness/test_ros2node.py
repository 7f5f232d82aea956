"""The receive stamp of a ROS 2 message on the callback's monotonic clock."""

from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

from dbml.harness.ros2node import received_monotonic

WALL_NS = 1_700_000_000_000_000_000


def test_a_message_received_before_its_callback_is_stamped_then() -> None:
    info = {"received_timestamp": WALL_NS - 250_000_000}  # 0.25 s before the callback
    assert received_monotonic(info, now=100.0, wall_ns=WALL_NS) == pytest.approx(99.75)


@pytest.mark.parametrize(
    "info",
    [
        {},
        {"received_timestamp": WALL_NS + 1},
        {"received_timestamp": 0},
        {"received_timestamp": "x"},
    ],
)
def test_a_missing_or_implausible_stamp_is_the_callbacks_time(info: dict[str, object]) -> None:
    assert received_monotonic(info, now=100.0, wall_ns=WALL_NS) == 100.0
