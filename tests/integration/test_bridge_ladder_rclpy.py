"""A plain ROS 2 camera through ``dbml bridge --transport rclpy --ladder``: JPEG that decodes.

Real processes on real ROS 2 (rclpy, Fast DDS): a plain rclpy driver of rgb8
``sensor_msgs/msg/Image`` (``rclpy_camera``), ``dbml bridge --ladder`` and ``dbml optimizer``;
the operator is plain rclpy in this process, subscribed to ``[topic]/optimized/compressed`` as
``sensor_msgs/msg/CompressedImage`` (as rqt_image_view's compressed transport is), decoding
every JPEG. The budget is tight enough that the ladder must give up detail to keep 16 Hz.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from dbml.harness.ros2env import claim_domain, ros2_child_env
from tests.conftest import wait_for
from tests.integration.procs import Proc

pytest.importorskip("rclpy")
pytest.importorskip("simplejpeg")

from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.subscription import MessageInfo
from sensor_msgs.msg import CompressedImage

from dbml.harness.ros2node import private_node
from dbml.media.jpeg import decode_jpeg
from dbml.protocol import names
from dbml.protocol.ladders import decode_rungs, parse_encoding
from dbml.transports.rclpy import RclpyTransport
from tests.rclpy_tools import param_set

pytestmark = pytest.mark.integration

CAMERA = "/r1/camera"
DRIVER_HZ = 16.0
BUDGET_MBIT = 3
"""375 kB/s: 16 frames of 640x480 fit only below about 23 kB, JPEG quality 30-50 here."""
MEASURE_S = 4.0
START_S = 40.0
TOLERANCE = 0.1


def test_a_plain_ros2_camera_arrives_as_compressed_jpeg_at_the_allocated_rate_and_rung(
    tmp_path: Path,
) -> None:
    with claim_domain() as domain_id:
        env = ros2_child_env(domain_id=domain_id, log_dir=tmp_path / "ros")
        procs = [
            Proc([CAMERA, str(DRIVER_HZ)], env, module="tests.integration.rclpy_camera"),
            Proc(["optimizer", "--transport", "rclpy", "--host", "ground"], env),
            Proc(
                [
                    "bridge",
                    CAMERA,
                    "--transport",
                    "rclpy",
                    "--host",
                    "r1",
                    "--min-hz",
                    "1",
                    "--max-hz",
                    "16",
                    "--ladder",
                ],
                env,
            ),
        ]
        try:
            _operate(domain_id)
        finally:
            for proc in procs:
                proc.stop()


def _operate(domain_id: int) -> None:
    lock = threading.Lock()
    arrivals: list[tuple[float, int, str, tuple[int, ...], float]] = []

    def heard(message: CompressedImage, info: MessageInfo) -> None:
        data = bytes(message.data)
        shape = decode_jpeg(data).shape  # every JPEG that arrives decodes
        sent_s = info["source_timestamp"] / 1e9  # the writer's clock as it sent (this machine's)
        with lock:
            arrivals.append((time.monotonic(), len(data), message.format, shape, sent_s))

    with (
        private_node("operator", domain_id=domain_id) as operator,
        RclpyTransport(host="observer", domain_id=domain_id) as observer,
    ):
        operator.create_subscription(
            CompressedImage,
            f"{CAMERA}/optimized/compressed",
            heard,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
        )
        result = param_set(operator, "/dbm", "max_bandwidth_in_mbit", BUDGET_MBIT, wait_s=START_S)
        assert result.successful, result.reason

        def settled() -> bool:
            label = observer.params.get(names.encoding_applied(CAMERA))
            return isinstance(label, str) and observer.params.get(names.ladder(CAMERA)) is not None

        wait_for(settled, timeout_s=START_S, what="a rung applied and a ladder published")
        wait_for(lambda: len(arrivals) > 10, timeout_s=START_S, what="compressed frames")
        start = time.monotonic()
        wait_for(
            lambda: time.monotonic() >= start + MEASURE_S, timeout_s=MEASURE_S + 1, what="span"
        )
        with lock:
            got = [a for a in arrivals if a[0] >= start]
        rate = observer.params.get(names.current_value(CAMERA))
        label = observer.params.get(names.encoding(CAMERA))
        ladder = decode_rungs(observer.params.get(names.ladder(CAMERA)))
    assert isinstance(rate, float)
    assert isinstance(label, str)
    scale, quality = parse_encoding(label)
    assert quality is not None
    assert quality < 95  # the budget does not fit the default quality at 16 Hz: detail went
    assert len(got) / MEASURE_S == pytest.approx(rate, rel=TOLERANCE)
    assert {fmt for _, _, fmt, _, _ in got} == {"rgb8; jpeg compressed bgr8"}
    assert {shape for _, _, _, shape, _ in got} == {(round(480 * scale), round(640 * scale), 3)}
    rung = next(r for r in ladder if (r.scale, r.jpeg_quality) == (scale, quality))
    mean_bytes = sum(n for _, n, *_ in got) / len(got)
    assert mean_bytes == pytest.approx(rung.size_bytes, rel=0.3)  # the rung the ladder says
    # The budget's 1-s windows by send time: a receiver that stalled and took a burst late
    # (this process, beside another test) says nothing of what the bridge sent. The budget and
    # the two frames a limiter banks (a late frame and its catch-up: 17 frames in a second of a
    # 16-Hz camera's, 1.2 % over their count, came to 403,209 B once in CI).
    sends = sorted((sent_s, n) for _, n, _, _, sent_s in got)
    worst = max(
        sum(n for t, n in sends[i:] if t < first + 1.0) for i, (first, _) in enumerate(sends)
    )
    assert worst <= BUDGET_MBIT * 1e6 / 8 + 2 * max(n for _, n in sends)
