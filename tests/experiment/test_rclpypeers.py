"""The plain rclpy peers, as real processes, checked from a plain rclpy node of the test's own.

The test's node lives in a private context of its own (as another process's would), in a ROS 2
domain claimed for the test; every peer process gets that domain and logs under ``tmp_path``.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dbml.cli.main import main
from dbml.core.errors import DbmlError
from dbml.experiment import entry
from dbml.experiment.analysis import Arrival
from dbml.experiment.entry import Kind
from dbml.experiment.peers import OPTIMIZED_SUFFIX, PRIORITY_SUFFIX, step_priority
from dbml.experiment.rclpypeers import RCLPY_MISSING, image_message, image_stamp_ns
from dbml.experiment.report import OperatorReport
from dbml.experiment.spec import TICK_S, RoleSpec
from dbml.harness.ros2env import claim_domain, fastdds_shm_files, ros2_child_env
from dbml.protocol import names
from dbml.scenarios.teleop import MAX_RATE_HZ, ROBOTS, STEPS
from dbml.transports.codecs import image_cdr
from dbml.transports.registry import TRANSPORTS, open_transport
from tests.conftest import wait_for
from tests.experiment.peer_process import Peer

rclpy = pytest.importorskip("rclpy")

from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402

from dbml.harness.ros2node import PrivateRos  # noqa: E402

READY_TIMEOUT_S = 30.0
"""A peer imports rclpy, starts its context and declares its endpoints within this."""
MATCH_TIMEOUT_S = 15.0
"""DDS discovery between the test's participant and a peer's (seconds at worst by default)."""
REPORT_TIMEOUT_S = 10.0
RATE_WINDOW_S = 2.0
RATE_TOLERANCE = 0.05
MEASURE_S = 4.0
"""How long frames are collected: every 2-s window that fits is measured."""
STEP_S = 2.0
OPERATOR_FRAMES = 20
"""Frames per robot the operator must report."""
BUDGET_MBIT = 7.5


def image_bytes(camera_size_bytes: int, stamp_ns: int) -> bytes:
    image = image_message(camera_size_bytes)
    image.header.stamp.sec, image.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    data: bytes = serialize_message(image)
    return data


@pytest.mark.parametrize("camera", ROBOTS, ids=lambda c: c.robot)
def test_an_image_serialises_through_rclpy_to_the_camera_size(camera: Any) -> None:
    stamp_ns = 1_795_454_170_709_408_768
    payload = image_bytes(camera.size_bytes, stamp_ns)
    assert len(payload) == camera.size_bytes
    message = deserialize_message(payload, Image)
    assert (message.header.frame_id, message.encoding, message.height) == ("camera", "mono8", 1)
    assert message.width == message.step == len(message.data)
    assert image_stamp_ns(payload) == stamp_ns
    assert deserialize_message(image_cdr(camera.size_bytes, stamp_ns=stamp_ns), Image) == message


def test_the_stamp_is_read_in_either_byte_order_and_only_from_plain_cdr() -> None:
    little = image_bytes(ROBOTS[1].size_bytes, 7 * 1_000_000_000 + 9)
    sec, nanosec = int.from_bytes(little[4:8], "little"), int.from_bytes(little[8:12], "little")
    big = b"\x00\x00\x00\x00" + sec.to_bytes(4, "big") + nanosec.to_bytes(4, "big")
    assert image_stamp_ns(big) == image_stamp_ns(little) == 7 * 1_000_000_000 + 9
    assert image_stamp_ns(b"\x00\x03\x00\x00" + little[4:]) is None, "parameter list: not plain"
    assert image_stamp_ns(little[:11]) is None


def test_an_image_smaller_than_its_overhead_is_refused() -> None:
    with pytest.raises(DbmlError, match=r"size_bytes=51: an Image takes 52 at least"):
        image_message(51)


def test_a_missing_rclpy_names_the_extra(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "rclpy", None)  # as if not installed
    spec = RoleSpec(step_s=1.0, transport=TRANSPORTS["rclpy"])
    assert entry.main(["rclpy-peer", "r1", spec.to_json()]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == f"r1: {RCLPY_MISSING}\n"
    assert RCLPY_MISSING.endswith("cannot import: pip install 'dbml[rclpy]'")


# -- the peers as processes, in a domain of the test's own --------------------------------------


@pytest.fixture
def domain_id() -> Iterator[int]:
    with claim_domain() as claimed:
        yield claimed


class Probe:
    """A plain rclpy node of the test's own, in a private context, spun on a thread."""

    def __init__(self, domain_id: int) -> None:
        self._ros = PrivateRos(domain_id=domain_id, name="probe")
        try:
            self.node = self._ros.node("probe")
        except BaseException:
            self._ros.close()
            raise
        self._ros.start()

    def subscribe(
        self, topic: str, msg_type: Any, callback: Callable[[Any], None], *, reliable: bool
    ) -> None:
        reliability = ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT
        self.node.create_subscription(
            msg_type,
            topic,
            callback,
            QoSProfile(depth=10, reliability=reliability),
            raw=msg_type is Image,
        )

    def close(self) -> None:
        self._ros.close()


@pytest.fixture
def probe(domain_id: int) -> Iterator[Probe]:
    made = Probe(domain_id)
    try:
        yield made
    finally:
        made.close()


def peer_env(domain_id: int, tmp_path: Path) -> dict[str, str]:
    return ros2_child_env(domain_id=domain_id, log_dir=tmp_path / "ros-log", base=os.environ)


def window_rates_hz(arrivals: list[float], window_s: float) -> list[float]:
    """The rate over every ``window_s`` that starts at a frame and fits in ``arrivals``."""
    rates = []
    for i, start in enumerate(arrivals):
        if start + window_s > arrivals[-1]:
            break
        inside = [t for t in arrivals[i:] if t <= start + window_s]
        rates.append((len(inside) - 1) / (inside[-1] - start))
    return rates


@pytest.mark.integration
def test_a_camera_publishes_images_at_its_maximum_and_table2s_priorities(
    domain_id: int, probe: Probe, tmp_path: Path
) -> None:
    camera = ROBOTS[0]
    lock = threading.Lock()
    frames: list[tuple[float, bytes]] = []
    priorities: list[tuple[float, float]] = []

    def on_frame(payload: bytes) -> None:
        with lock:
            frames.append((time.time(), payload))

    def on_priority(message: Float64) -> None:
        with lock:
            priorities.append((time.time(), float(message.data)))

    # Reliable: it matches a reliable publisher only. Best effort, as dbml's own listener.
    probe.subscribe(camera.topic, Image, on_frame, reliable=True)
    probe.subscribe(camera.topic + PRIORITY_SUFFIX, Float64, on_priority, reliable=False)
    env = peer_env(domain_id, tmp_path)
    spec = RoleSpec(step_s=STEP_S, transport=TRANSPORTS["rclpy"], domain_id=domain_id)
    peer = Peer(Kind.RCLPY_PEER, "r1", spec, env=env)
    try:
        assert peer.next(READY_TIMEOUT_S) == {"type": "ready", "role": "r1"}
        owned = fastdds_shm_files([peer.child.pid])

        def frames_in() -> int:
            with lock:
                return len(frames)

        wait_for(lambda: frames_in() > 0, timeout_s=MATCH_TIMEOUT_S, what="a first frame")
        # The priority's endpoints were announced with the frames': start once both are matched.
        wait_for(
            lambda: probe.node.count_publishers(camera.topic + PRIORITY_SUFFIX) == 1,
            timeout_s=MATCH_TIMEOUT_S,
            what="the priority's publisher",
        )
        t0 = time.time() + 0.5
        peer.send(f"start {t0!r}")
        first = frames_in()
        wait_for(
            lambda: frames_in() >= first + MEASURE_S * MAX_RATE_HZ,
            timeout_s=MEASURE_S + REPORT_TIMEOUT_S,
            what=f"{MEASURE_S} s of frames",
        )

        def second_step_heard() -> bool:
            with lock:
                return any(t >= t0 + STEP_S for t, _ in priorities)

        wait_for(
            second_step_heard,
            timeout_s=2 * STEP_S + REPORT_TIMEOUT_S,
            what="a priority published in the second step",
        )
        publishers = probe.node.get_publishers_info_by_topic(camera.topic)
        assert [p.qos_profile.reliability for p in publishers] == [ReliabilityPolicy.RELIABLE]
        assert [p.node_name for p in publishers] == ["r1_camera"]
        assert peer.stop(REPORT_TIMEOUT_S) == 0
    finally:
        peer.close()
    assert owned, "the peer's Fast DDS shared memory, while it ran"
    # A port's segment stays while another participant (of any process that ever used the
    # port) maps it; its lock, the peer's own segment and every lock of the peer are gone.
    ports = ("fastdds_port", "sem.fastdds_port")
    left = [
        p for p in owned if p.exists() and (p.name.endswith("_el") or not p.name.startswith(ports))
    ]
    assert not left, "nothing of the peer's own left in /dev/shm"
    assert any(not p.name.startswith(ports) for p in owned), "a segment of its own, once"
    with lock:
        got = list(frames)
    arrivals = [t for t, _ in got[first:]]
    rates = window_rates_hz(arrivals, RATE_WINDOW_S)
    assert rates, "at least one full window"
    assert all(abs(r - MAX_RATE_HZ) <= RATE_TOLERANCE * MAX_RATE_HZ for r in rates), (
        min(rates),
        max(rates),
    )
    assert {len(payload) for _, payload in got} == {camera.size_bytes}
    for arrival_s, payload in got:
        message = deserialize_message(payload, Image)
        assert (message.header.frame_id, message.encoding) == ("camera", "mono8")
        stamp_ns = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
        assert image_stamp_ns(payload) == stamp_ns
        assert 0 <= arrival_s - stamp_ns / 1e9 < 0.5, "stamped when sent"
    first_step = [v for t, v in priorities if t0 <= t < t0 + STEP_S - 0.1]
    second_step = [v for t, v in priorities if t >= t0 + STEP_S]
    assert not [t for t, _ in priorities if t < t0 - 0.1], "no priority before step 1"
    assert len(first_step) >= 2, "republished within the step"
    assert set(first_step) == {step_priority(STEPS[0], 0)}
    assert second_step[0] == step_priority(STEPS[1], 0)
    assert list((tmp_path / "ros-log").glob("python*.log")), "ROS logs under tmp_path"


@pytest.mark.integration
def test_the_operator_reports_each_frame_and_the_parameters_in_force(
    domain_id: int, probe: Probe, tmp_path: Path
) -> None:
    """The robots' frames, republished raw on ``[topic]/optimized`` as a bridge would."""
    env = peer_env(domain_id, tmp_path)
    forwarded: list[list[int]] = [[] for _ in ROBOTS]
    lock = threading.Lock()
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    copies = [
        probe.node.create_publisher(Image, camera.topic + OPTIMIZED_SUFFIX, qos)
        for camera in ROBOTS
    ]

    def forward(index: int) -> Callable[[bytes], None]:
        def on_frame(payload: bytes) -> None:
            copies[index].publish(payload)
            stamp_ns = image_stamp_ns(payload)
            with lock:
                forwarded[index].append(-1 if stamp_ns is None else stamp_ns)

        return on_frame

    for i, camera in enumerate(ROBOTS):
        probe.subscribe(camera.topic, Image, forward(i), reliable=True)
    transport = open_transport("rclpy", host="base-station", domain_id=domain_id)
    spec = RoleSpec(
        step_s=1.0,
        transport=TRANSPORTS["rclpy"],
        host="operator",
        domain_id=domain_id,
        peer_wait_s=5.0,
    )
    peers: list[Peer] = []
    try:
        transport.params.set(names.BANDWIDTH, BUDGET_MBIT)  # anyone may write it
        peers += [Peer(Kind.RCLPY_PEER, c.robot.lower(), spec, env=env) for c in ROBOTS]
        operator = Peer(Kind.RCLPY_PEER, "operator", spec, env=env)
        peers.append(operator)
        for peer in peers:
            assert peer.next(READY_TIMEOUT_S)["type"] == "ready", peer.role
        operator.send(f"start {time.time()!r}")
        rows: list[Arrival] = []
        budgets: list[float | None] = []
        deadline = time.monotonic() + REPORT_TIMEOUT_S
        while time.monotonic() < deadline and not all(
            len([r for r in rows if r.robot == i]) >= OPERATOR_FRAMES for i in range(len(ROBOTS))
        ):
            message = operator.next(REPORT_TIMEOUT_S)
            assert message["type"] == "tick"
            report = OperatorReport.decode(message)
            assert report.tick.variants == ("optimized", "optimized")
            rows.extend(report.frames)
            budgets.append(report.tick.budget_mbit)
        operator.send("stop")
        for _ in range(int(REPORT_TIMEOUT_S / TICK_S)):  # the ticks still queued, then done
            if operator.next(REPORT_TIMEOUT_S)["type"] == "done":
                break
        else:
            pytest.fail("the operator never reported done")
        assert [peer.stop(REPORT_TIMEOUT_S) for peer in peers] == [0, 0, 0]
    finally:
        for peer in peers:
            peer.close()
        transport.close()
    assert budgets[-1] == BUDGET_MBIT, "the parameters in force, through dbml's rclpy transport"
    with lock:
        sent = [set(stamps) for stamps in forwarded]
    for i, camera in enumerate(ROBOTS):
        mine = [r for r in rows if r.robot == i]
        assert len(mine) >= OPERATOR_FRAMES
        assert [r.seq for r in mine] == list(range(len(mine))), "a per-topic count from 0"
        assert {r.size_bytes for r in mine} == {camera.size_bytes}
        assert all(r.rate_hz is None for r in mine), "a plain ROS 2 message carries no rate"
        stamps = [r.sent_s for r in mine if r.sent_s is not None]
        assert len(stamps) == len(mine), "every frame carries its send time"
        assert all(_near(t, sent[i]) for t in stamps), "header.stamp, as the robot sent it"
        assert all(0 <= r.arrival_s - (r.sent_s or 0) < 0.5 for r in mine), "arrived after sent"


def _near(sent_s: float, stamps_ns: set[int]) -> bool:
    """``sent_s`` is one of ``stamps_ns`` (a float of ns since the epoch rounds to ~0.2 us)."""
    return min(abs(sent_s * 1e9 - s) for s in stamps_ns) < 1_000


# -- the demo without rclpy ------------------------------------------------------------------


def test_the_rclpy_demo_without_rclpy_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "rclpy", None)  # as if not installed
    assert main(["demo", "teleop", "--transport", "rclpy", "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == f"dbml: error: {RCLPY_MISSING}\n"
