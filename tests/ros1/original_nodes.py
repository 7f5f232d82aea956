"""Nodes as written for the original package, and a plain ROS publisher for ``dbml bridge``.

``python -m tests.ros1.original_nodes source TOPIC|legacy``.
"""

from __future__ import annotations

import json
import sys

import rospy
from sensor_msgs.msg import Image

from dbml.ros1 import DBMPublisher, DBMRate

IMAGE = Image(height=240, width=350, encoding="mono8", step=350, data=bytes(84_000))


def source(topic: str) -> None:
    """An unmanaged camera at 30 Hz: what ``dbml bridge`` puts under management."""
    rospy.init_node("source", anonymous=True)
    publisher = rospy.Publisher(topic, Image, queue_size=1)
    rate = rospy.Rate(30)
    while not rospy.is_shutdown():
        publisher.publish(IMAGE)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


def legacy() -> None:
    """The original's call shapes: ``start(get_message, full_rate=...)``, ``DBMRate(topic)``."""
    rospy.init_node("camera")
    publisher = DBMPublisher("camera", Image, 1, 16)
    publisher.start(lambda: IMAGE, full_rate=True)
    rate = DBMRate(rospy.resolve_name("camera"), 1, 16)
    shown = None
    while not rospy.is_shutdown():
        if publisher.frequency != shown:
            shown = publisher.frequency
            print(json.dumps({"topic": publisher.name, "frequency": shown}), flush=True)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    if sys.argv[1] == "source":
        source(sys.argv[2])
    else:
        legacy()
