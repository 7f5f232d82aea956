"""A node whose dbml thread dies while ``DBMOptimizer.spin`` runs, and one that merely stops.

``python -m tests.ros1.dying_nodes TOPIC``: a ``DBMPublisher.start`` whose ``get_message`` raises
once the optimizer's first round is done; it prints ``{"alive": ...}`` as the spin ends.

``python -m tests.ros1.dying_nodes TOPIC stopping``: ROS shuts down (as on Ctrl-C) while the
``start`` thread is between its check and its call, and rospy raises in that call; it prints
``{"alive": ..., "deaths": ...}`` once the thread has ended, and exits as the spin says.
"""

from __future__ import annotations

import json
import sys

import rospy
from sensor_msgs.msg import Image

from dbml.ros1 import DBMOptimizer, DBMPublisher
from dbml.transports.worker import death_count

IMAGE = Image(height=240, width=350, encoding="mono8", step=350, data=bytes(84_000))


def dying(topic: str) -> None:
    """The optimizer spins; the camera's ``start`` thread dies during the spin."""
    rospy.init_node("dying", anonymous=True)
    optimizer = DBMOptimizer()
    publisher = DBMPublisher(topic, Image, 1, 16)

    def get_message() -> Image:
        if optimizer.last_round is not None:  # only once spin() runs the rounds
            raise RuntimeError("camera unplugged")
        return IMAGE

    publisher.start(get_message)
    try:
        optimizer.spin()
    finally:
        print(json.dumps({"alive": publisher.alive}), flush=True)


def stopping(topic: str) -> None:
    """The optimizer spins; ROS shuts down under the ``start`` thread, which raises (rospy's)."""
    rospy.init_node("stopping", anonymous=True)
    optimizer = DBMOptimizer()
    publisher = DBMPublisher(topic, Image, 1, 16)

    def get_message() -> Image:
        if optimizer.last_round is not None:  # only once spin() runs the rounds
            rospy.signal_shutdown("keyboard interrupt")  # what Ctrl-C does
            raise rospy.ROSException("publish() to a closed topic")  # what rospy says then
        return IMAGE

    publisher.start(get_message)
    try:
        optimizer.spin()
    finally:
        publisher.unregister()  # waits for the start thread's end
        print(json.dumps({"alive": publisher.alive, "deaths": death_count()}), flush=True)


if __name__ == "__main__":
    if sys.argv[2:] == ["stopping"]:
        stopping(sys.argv[1])
    else:
        dying(sys.argv[1])
