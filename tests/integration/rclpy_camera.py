"""A camera driver that knows nothing of dbml: plain rclpy rgb8 ``sensor_msgs/msg/Image``.

``python -m tests.integration.rclpy_camera TOPIC HZ``: 640x480 frames of a camera moving over
the photographs of ``dbml.media.photos``, ``header.stamp`` their capture time; with a third
argument SIZE_BYTES, frames of no picture that serialise to exactly that size. Runs until
SIGTERM (bounded: an hour), then shuts its context down (no shared memory left).
"""

from __future__ import annotations

import signal
import sys
import threading
import time

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import Image

from dbml.experiment.rclpypeers import image_message
from dbml.media.photos import PanCamera

MAX_RUN_S = 3600.0


def main() -> None:
    topic, rate_hz = sys.argv[1], float(sys.argv[2])
    size_bytes = int(sys.argv[3]) if len(sys.argv) > 3 else None
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = Node("camera_driver", context=context)
    publisher = node.create_publisher(Image, topic, 5)
    camera = PanCamera(640, 480) if size_bytes is None else None
    image = Image(height=480, width=640, encoding="rgb8", step=640 * 3)
    if size_bytes is not None:
        image = image_message(size_bytes)
    image.header.frame_id = "camera"
    started = time.monotonic()
    sent = 0
    print("ready", flush=True)
    while not stop.is_set() and time.monotonic() - started < MAX_RUN_S:
        image.header.stamp = node.get_clock().now().to_msg()
        if camera is not None:
            image.data = camera.frame().tobytes()
        publisher.publish(image)
        sent += 1
        stop.wait(max(0.0, started + sent / rate_hz - time.monotonic()))
    node.destroy_node()
    rclpy.try_shutdown(context=context)


if __name__ == "__main__":
    main()
