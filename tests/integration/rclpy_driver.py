"""A camera driver that knows nothing of dbml: plain rclpy ``sensor_msgs/msg/Image`` at a rate.

``python -m tests.integration.rclpy_driver TOPIC SIZE_BYTES HZ {reliable,best_effort}``: each
message is exactly ``SIZE_BYTES`` serialised, ``header.stamp`` its send time. Runs until SIGTERM
(bounded: an hour), then shuts its context down (no shared memory left).
"""

from __future__ import annotations

import signal
import sys
import threading
import time

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import Image

from dbml.transports.codecs import IMAGE_OVERHEAD_BYTES

MAX_RUN_S = 3600.0


def main() -> None:
    topic, size_bytes, rate_hz, qos = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = Node("camera_driver", context=context)
    reliability = ReliabilityPolicy.RELIABLE if qos == "reliable" else ReliabilityPolicy.BEST_EFFORT
    publisher = node.create_publisher(Image, topic, QoSProfile(depth=5, reliability=reliability))
    pixels = size_bytes - IMAGE_OVERHEAD_BYTES
    image = Image(height=1, width=pixels, encoding="mono8", step=pixels, data=bytes(pixels))
    image.header.frame_id = "camera"
    started = time.monotonic()
    sent = 0
    print("ready", flush=True)
    while not stop.is_set() and time.monotonic() - started < MAX_RUN_S:
        image.header.stamp = node.get_clock().now().to_msg()
        publisher.publish(image)
        sent += 1
        stop.wait(max(0.0, started + sent / rate_hz - time.monotonic()))
    node.destroy_node()
    rclpy.try_shutdown(context=context)


if __name__ == "__main__":
    main()
