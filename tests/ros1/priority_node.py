"""A ROS 1 node that publishes ``std_msgs/Float64`` priorities, as a user's mission node would.

``python -m tests.ros1.priority_node TOPIC VALUE...``: waits for a subscriber of ``TOPIC``,
publishes each value as fast as it can, prints one JSON line (how many, in how long), and spins
until it is stopped (so its connection outlives the last message's delivery).
"""

from __future__ import annotations

import json
import sys
import time

import rospy
from std_msgs.msg import Float64

CONNECT_TIMEOUT_S = 20.0


def main(topic: str, values: list[float]) -> int:
    rospy.init_node("mission", anonymous=True)
    publisher = rospy.Publisher(topic, Float64, queue_size=len(values))
    deadline = time.monotonic() + CONNECT_TIMEOUT_S
    while publisher.get_num_connections() == 0:
        if time.monotonic() > deadline:
            print(json.dumps({"error": f"no subscriber of {topic}"}), flush=True)
            return 1
        time.sleep(0.05)
    started = time.monotonic()
    for value in values:
        publisher.publish(Float64(data=value))
    seconds = time.monotonic() - started
    print(json.dumps({"sent": len(values), "seconds": seconds}), flush=True)
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], [float(v) for v in sys.argv[2:]]))
