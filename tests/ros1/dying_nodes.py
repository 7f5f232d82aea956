"""A node whose dbml thread dies while ``DBMOptimizer.spin`` runs.

``python -m tests.ros1.dying_nodes TOPIC``: a ``DBMPublisher.start`` whose ``get_message`` raises
once the optimizer's first round is done; it prints ``{"alive": ...}`` as the spin ends.
"""

from __future__ import annotations

import json
import sys

import rospy
from sensor_msgs.msg import Image

from dbml.ros1 import DBMOptimizer, DBMPublisher

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


if __name__ == "__main__":
    dying(sys.argv[1])
