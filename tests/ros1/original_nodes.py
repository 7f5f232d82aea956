"""Nodes as written for the original package, and a plain ROS publisher for ``dbml bridge``.

``python -m tests.ros1.original_nodes source TOPIC|legacy|follower TOPIC|failing TOPIC``.
"""

from __future__ import annotations

import json
import sys
import time

import rospy
from sensor_msgs.msg import Image

from dbml.core.errors import SpecError
from dbml.ros1 import DBMPublisher, DBMRate

FAILING_CALL = 3
"""``failing``'s ``get_message`` raises on this call."""
FAILURE_TIMEOUT_S = 20.0

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
    follow(publisher.name, rate)


def follow(topic: str, rate: DBMRate) -> None:
    """Print the frequency ``rate`` keeps whenever it changes, until ROS shuts down."""
    shown = None
    while not rospy.is_shutdown():
        if rate.frequency != shown:
            shown = rate.frequency
            print(json.dumps({"topic": topic, "frequency": shown}), flush=True)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


def follower(topic: str) -> None:
    """``DBMRate(topic, min, max)`` with no DBMPublisher here: it follows the parameter server."""
    rospy.init_node("follower", anonymous=True)
    follow(topic, DBMRate(topic, 1, 16))


def failing(topic: str) -> None:
    """A ``start`` whose ``get_message`` raises: reported, never silent; then misuse refused."""
    rospy.init_node("failing", anonymous=True)
    publisher = DBMPublisher(topic, Image, 1, 16)
    calls = 0

    def get_message() -> Image:
        nonlocal calls
        calls += 1
        if calls == FAILING_CALL:
            raise RuntimeError("camera unplugged")
        return IMAGE

    publisher.start(get_message)
    deadline = time.monotonic() + FAILURE_TIMEOUT_S
    while publisher.alive and time.monotonic() < deadline:
        time.sleep(0.01)
    print(json.dumps({"alive": publisher.alive, "calls": calls}), flush=True)
    try:
        publisher.start(get_message)
    except SpecError as err:
        print(json.dumps({"start": str(err)}), flush=True)
    publisher.unregister()
    try:
        DBMRate(topic)  # no DBMPublisher of it any more: the bounds are required
    except SpecError as err:
        print(json.dumps({"rate": str(err)}), flush=True)


if __name__ == "__main__":
    if sys.argv[1] == "source":
        source(sys.argv[2])
    elif sys.argv[1] == "follower":
        follower(sys.argv[2])
    elif sys.argv[1] == "failing":
        failing(sys.argv[2])
    else:
        legacy()
