"""Nodes written as a ROS 1 user writes them, with the paper's classes.

``python -m tests.ros1.paper_nodes camera|viewer TOPIC|optimizer``; each prints JSON lines.
"""

from __future__ import annotations

import json
import sys

import rospy
from sensor_msgs.msg import Image

from dbml.ros1 import DBMOptimizer, DBMPublisher, DBMRate, DBMSubscriber


def camera() -> None:
    rospy.init_node("camera")
    publisher = DBMPublisher("camera", Image, 1, 16)  # relative: in the node's namespace
    rate = DBMRate(publisher)
    image = Image(height=240, width=350, encoding="mono8", step=350, data=bytes(84_000))
    shown = None
    while not rospy.is_shutdown():
        publisher.publish(image)
        if publisher.frequency != shown:
            shown = publisher.frequency
            print(json.dumps({"topic": publisher.name, "frequency": shown}), flush=True)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


def viewer(topic: str) -> None:
    rospy.init_node("viewer", anonymous=True)

    def on_image(image: Image, label: str) -> None:
        line = {"label": label, "width": image.width, "bytes": len(image.data)}
        print(json.dumps({**line, "optimized": subscriber.optimized}), flush=True)

    subscriber = DBMSubscriber(topic, Image, on_image, "seen")
    rospy.spin()


def optimizer() -> None:
    rospy.init_node("dbm_optimizer")
    DBMOptimizer().spin()


if __name__ == "__main__":
    role = sys.argv[1]
    if role == "camera":
        camera()
    elif role == "viewer":
        viewer(sys.argv[2])
    else:
        optimizer()
