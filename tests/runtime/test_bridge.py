"""The bridge over the memory transport: newest-only forwarding, pacing, closing, typing."""

import logging
import random
import threading

import pytest

from dbml.core.config import BridgeChannel
from dbml.core.errors import TransportError
from dbml.protocol import names
from dbml.runtime import bridge as bridge_module
from dbml.runtime.bridge import Bridge
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.serve import run_bridge
from dbml.transports import ManualClock, MemoryNetwork, MemoryTransport, Sample, Variant
from dbml.transports.worker import death_count
from tests.conftest import wait_for

CAMERA = "/r1/camera"
CHANNEL = BridgeChannel(CAMERA, 1.0, 16.0)


@pytest.fixture
def network() -> MemoryNetwork:
    return MemoryNetwork()


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(100.0)


def optimized_reader(network: MemoryNetwork) -> list[Sample]:
    """What a remote operator receives of ``[topic]/optimized``."""
    received: list[Sample] = []
    MemoryTransport(network, host="op").subscribe(CAMERA, received.append, Variant.OPTIMIZED)
    return received


def started(network: MemoryNetwork, clock: ManualClock, first: bytes = b"first") -> Bridge:
    """A bridge on the robot, its topic's original publisher having sent ``first``."""
    robot = MemoryTransport(network, host="r1", clock=clock)
    bridge = Bridge(robot, CHANNEL)
    original = robot.declare_publisher(CAMERA)
    original.put(first)
    bridge.start(timeout_s=0, pace=False)
    MemoryTransport(network, host="base").params.set(names.current_value(CAMERA), 2.0)
    return bridge


def test_forwards_the_newest_message_at_most_once(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    received = optimized_reader(network)
    bridge = started(network, clock)
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    for payload in (b"one", b"two", b"three"):
        original.put(payload)
    assert bridge.forward()
    assert [s.payload for s in received] == [b"three"]  # newest wins, no queue
    clock.advance(10.0)
    assert not bridge.forward()  # nothing new: nothing is sent again
    assert len(received) == 1
    original.put(b"four")
    assert bridge.forward()
    assert [s.payload for s in received] == [b"three", b"four"]
    assert bridge.forwarded == 2


def test_a_refused_message_is_kept_unless_a_newer_one_came(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    received = optimized_reader(network)
    bridge = started(network, clock)
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    original.put(b"a")
    assert bridge.forward()
    original.put(b"b")
    assert not bridge.forward()  # 2 Hz: too early
    clock.advance(0.5)
    assert bridge.forward()
    assert [s.payload for s in received] == [b"a", b"b"]


def test_rate_follows_the_allocation(network: MemoryNetwork, clock: ManualClock) -> None:
    received = optimized_reader(network)
    bridge = started(network, clock)
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    optimizer = MemoryTransport(network, host="base").params

    def sent_in(seconds: float) -> int:
        """A 100 Hz source under the pacing thread's schedule.

        A refused message is offered again after ``retry_s``, a new one at once.
        """
        before = len(received)
        end = clock() + seconds
        next_frame = next_heartbeat = clock()
        while clock() < end - 1e-9:
            if clock() >= next_heartbeat - 1e-9:  # it keeps the allocation in force
                optimizer.set(names.ROUND, round(next_heartbeat))
                next_heartbeat += 1.0
            if clock() >= next_frame - 1e-9:
                original.put(b"x")
                next_frame += 0.01
            until_frame = next_frame - clock()
            step = until_frame if bridge.forward() else min(bridge.retry_s(), until_frame)
            clock.advance(max(step, 1e-6))
        return len(received) - before

    optimizer.set(names.current_value(CAMERA), 4.0)
    assert sent_in(10.0) == pytest.approx(40, abs=2)
    optimizer.set(names.current_value(CAMERA), 12.5)
    assert sent_in(10.0) == pytest.approx(125, abs=2)
    optimizer.set(names.current_value(CAMERA), 50.0)  # above max: clamped to 16 Hz
    assert sent_in(10.0) == pytest.approx(160, abs=2)


def test_size_follows_the_forwarded_payloads(network: MemoryNetwork, clock: ManualClock) -> None:
    bridge = started(network, clock)
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    params = MemoryTransport(network, host="viewer").params
    original.put(bytes(84_000))
    assert bridge.forward()
    assert params.get(names.size(CAMERA)) == 84_000
    clock.advance(1.0)
    original.put(bytes(21_000))
    assert bridge.forward()
    assert params.get(names.size(CAMERA)) == 21_000


def test_does_not_republish_the_full_rate_topic(network: MemoryNetwork, clock: ManualClock) -> None:
    local: list[Sample] = []
    MemoryTransport(network, host="r1").subscribe(CAMERA, local.append)
    bridge = started(network, clock, first=b"first")
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    original.put(b"second")
    assert bridge.forward()
    # Only the original publisher's two messages: the bridge added none to [topic].
    assert [s.payload for s in local] == [b"first", b"second"]
    publishers = [
        e for e in MemoryTransport(network, host="v").graph.entries() if e.role.value == "pub"
    ]
    assert {(e.host, e.topic, e.variant) for e in publishers} == {("r1", CAMERA, Variant.FULL)}


def test_start_without_a_message_names_the_topic(network: MemoryNetwork) -> None:
    bridge = Bridge(MemoryTransport(network, host="r1"), CHANNEL)
    with pytest.raises(TransportError, match=r"^topic='/r1/camera': no message within 0.01 s"):
        bridge.start(timeout_s=0.01)
    bridge.close()


def test_pacing_thread_forwards_at_the_allocated_rate(network: MemoryNetwork) -> None:
    """Real time: a 200 Hz source, a 20 Hz allocation, about 20 messages a second."""
    received = optimized_reader(network)
    robot = MemoryTransport(network, host="r1")
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    stop = threading.Event()

    def source() -> None:
        n = 0
        while not stop.wait(0.005):
            n += 1
            original.put(n.to_bytes(4, "big"))

    feeder = threading.Thread(target=source, daemon=True)
    feeder.start()
    runner = threading.Thread(
        target=run_bridge, args=(robot, [CHANNEL]), kwargs={"stop": stop, "wait_s": 5.0}
    )
    runner.start()
    try:
        wait_for(lambda: robot.params.get(names.size(CAMERA)) == 4, what="the bridge's size")
        MemoryTransport(network, host="base").params.set(names.current_value(CAMERA), 20.0)
        wait_for(lambda: len(received) > 0, what="a first forwarded message")
        start = len(received)
        stop.wait(1.0)  # a measurement window, not a wait for a condition
        count = len(received) - start
        # Never above the allocation (20 + the 2 banked frames + rounding); a loaded machine
        # may run the pacing thread late, so the floor is loose.
        assert 10 <= count <= 23
        numbers = [int.from_bytes(s.payload, "big") for s in received]
        assert numbers == sorted(set(numbers))  # each at most once, never an older one
    finally:
        stop.set()
        runner.join(timeout=5)
        feeder.join(timeout=5)
    assert not runner.is_alive()


def test_run_bridge_fails_for_a_silent_topic(network: MemoryNetwork) -> None:
    with pytest.raises(TransportError, match=r"topic='/r1/camera': no message within"):
        run_bridge(
            MemoryTransport(network, host="r1"), [CHANNEL], stop=threading.Event(), wait_s=0.05
        )


def test_managed_publisher_without_full_republish(network: MemoryNetwork) -> None:
    from dbml.runtime import ManagedPublisher

    local: list[Sample] = []
    MemoryTransport(network, host="r1").subscribe(CAMERA, local.append)
    received = optimized_reader(network)
    publisher = ManagedPublisher(
        MemoryTransport(network, host="r1"),
        CAMERA,
        min_rate_hz=1,
        max_rate_hz=16,
        failsafe_periods=1e-9,  # no wait for a first allocation
        republish_full=False,
    )
    assert publisher.publish(b"frame")
    assert local == []
    assert [s.payload for s in received] == [b"frame"]
    publisher.close()


def test_run_bridge_over_typed_topics_refuses_an_unresolved_type(network: MemoryNetwork) -> None:
    """ROS 1 and ROS 2 topics are typed: a guessed type would reach no subscriber."""
    with pytest.raises(
        TransportError,
        match=r"^topic='/r1/camera': its type cannot be resolved .* name it with --type",
    ):
        run_bridge(
            MemoryTransport(network, host="r1"),
            [CHANNEL],
            stop=threading.Event(),
            wait_s=0.05,
            typed_topics=True,
        )


def test_close_waits_for_a_send_in_progress_and_logs_a_slow_thread(
    network: MemoryNetwork, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    events: list[str] = []
    sending, release = threading.Event(), threading.Event()
    real_publish, real_close = ManagedPublisher.publish, ManagedPublisher.close

    def stuck_publish(self: ManagedPublisher, payload: bytes) -> bool:
        events.append("send")
        sending.set()
        release.wait(10.0)
        events.append("sent")
        return real_publish(self, payload)

    def close(self: ManagedPublisher) -> None:
        events.append("close")
        real_close(self)

    monkeypatch.setattr(ManagedPublisher, "publish", stuck_publish)
    monkeypatch.setattr(ManagedPublisher, "close", close)
    monkeypatch.setattr(bridge_module, "_JOIN_TIMEOUT_S", 0.05)
    robot = MemoryTransport(network, host="r1")
    bridge = Bridge(robot, CHANNEL)
    robot.declare_publisher(CAMERA).put(b"first")
    bridge.start(timeout_s=0)
    assert sending.wait(5.0), "the pacing thread's first send"
    with caplog.at_level(logging.WARNING, logger="dbml.bridge"):
        closer = threading.Thread(target=bridge.close)
        closer.start()
        wait_for(lambda: "did not stop within 0.05 s" in caplog.text, what="the slow thread logged")
        assert "close" not in events  # not while the send runs
        release.set()
        closer.join(timeout=5.0)
    assert events == ["send", "sent", "close"]
    assert not bridge.alive
    robot.declare_publisher(CAMERA).put(b"late")
    assert not bridge.forward()  # closed: nothing more goes out


def test_a_pacing_thread_that_dies_is_said_and_ends_run_bridge_with_1(
    network: MemoryNetwork, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A bridge that forwards nothing must not look alive: ``dbml bridge`` exits 1."""

    def broken_publish(self: ManagedPublisher, payload: bytes) -> bool:
        raise RuntimeError("the optimized copy is gone")

    monkeypatch.setattr(ManagedPublisher, "publish", broken_publish)
    robot = MemoryTransport(network, host="r1")
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    stop = threading.Event()

    def source() -> None:
        while not stop.wait(0.01):
            original.put(b"frame")

    feeder = threading.Thread(target=source, daemon=True)
    feeder.start()
    deaths = death_count()
    try:
        with caplog.at_level(logging.CRITICAL, logger="dbml"):
            code = run_bridge(robot, [CHANNEL], stop=stop, duration_s=20.0, wait_s=5.0)
    finally:
        stop.set()
        feeder.join(timeout=5)
    assert code == 1
    assert death_count() == deaths + 1
    assert "dbml-bridge /r1/camera: the thread died" in caplog.text
    assert "RuntimeError: the optimized copy is gone" in caplog.text
    assert "a worker thread died (see above); exiting so a supervisor restarts it" in caplog.text


def test_a_dead_pacing_thread_makes_the_bridge_not_alive(
    network: MemoryNetwork, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken_publish(self: ManagedPublisher, payload: bytes) -> bool:
        raise RuntimeError("the optimized copy is gone")

    monkeypatch.setattr(ManagedPublisher, "publish", broken_publish)
    robot = MemoryTransport(network, host="r1")
    bridge = Bridge(robot, CHANNEL)
    robot.declare_publisher(CAMERA).put(b"first")
    deaths = death_count()
    bridge.start(timeout_s=0)
    wait_for(lambda: not bridge.alive, what="the pacing thread's death")
    wait_for(lambda: death_count() == deaths + 1, what="the death counted")
    bridge.close()


def test_a_refused_message_goes_when_the_limiter_allows_not_a_period_later(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """The pacing thread's waits, driven by hand: a message offered early goes on time."""
    received = optimized_reader(network)
    bridge = started(network, clock)  # 2 Hz
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    original.put(b"a")
    assert bridge.forward()
    sent_at = clock()
    clock.advance(0.49)  # the source's next frame, 10 ms before the limiter has earned one
    original.put(b"b")
    assert not bridge.forward()
    waits = 0
    while not bridge.forward():
        wait_s = bridge.retry_s()
        assert 0 < wait_s <= 0.05
        clock.advance(wait_s)
        waits += 1
        assert waits < 10
    assert clock() - sent_at == pytest.approx(0.5, abs=1e-6)
    assert [s.payload for s in received] == [b"a", b"b"]


def test_a_driver_gone_silent_is_said_before_the_next_heartbeat(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    bridge = started(network, clock)  # 2 Hz
    publisher = bridge.publisher
    assert publisher is not None
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    optimizer = MemoryTransport(network, host="base", clock=clock).params
    params = MemoryTransport(network, host="op").params
    for beat in range(3):  # two heartbeats a second apart: 2 Hz said
        for _ in range(2):
            clock.advance(0.5)
            original.put(b"frame")
            assert bridge.forward()
        optimizer.set(names.ROUND, float(beat))
    assert params.get(names.sent(CAMERA)) == pytest.approx(2.0)
    clock.advance(0.9)  # under two intervals of silence: still running
    publisher.say_if_stopped()
    assert params.get(names.sent(CAMERA)) == pytest.approx(2.0)
    clock.advance(0.2)
    publisher.say_if_stopped()
    assert params.get(names.sent(CAMERA)) == 0.0


def test_a_jittery_driver_at_the_allocated_rate_never_bursts_past_one_message(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """Any 1-s window by send time holds the rate and one message more, whatever the jitter.

    A 16-Hz driver allocated 16 Hz, in stretches 120 ms late then on time, each frame up to
    20 ms late more, now and then two missing (a stall), under the pacing thread's schedule.
    """
    sends: list[float] = []
    MemoryTransport(network, host="op").subscribe(
        CAMERA, lambda _sample: sends.append(clock()), Variant.OPTIMIZED
    )
    bridge = started(network, clock)
    original = MemoryTransport(network, host="r1b").declare_publisher(CAMERA)
    optimizer = MemoryTransport(network, host="base").params
    optimizer.set(names.current_value(CAMERA), 16.0)
    rng = random.Random(7)
    start = clock()
    late_s = [0.12 if (k // 20) % 2 == 0 else 0.0 for k in range(16 * 30)]  # stretches late
    frames = [start + k / 16 + late + rng.uniform(0.0, 0.02) for k, late in enumerate(late_s)]
    frames = sorted(t for k, t in enumerate(frames) if k % 37 not in (1, 2))  # stalls
    next_heartbeat = start
    for at in frames:
        while True:  # the pacing thread until this frame arrives
            if clock() >= next_heartbeat:
                optimizer.set(names.ROUND, round(next_heartbeat))
                next_heartbeat += 1.0
            until = at - clock()
            if until <= 0:
                break
            clock.advance(min(bridge.retry_s(), until) if not bridge.forward() else until)
        original.put(b"x")
        bridge.forward()
    counts = [sum(1 for t in sends[i:] if t < first + 1.0) for i, first in enumerate(sends)]
    # the rate, and after a late frame the one message the limiter may catch up
    assert max(counts) <= 16 + 1, max(counts)
    assert len(sends) >= 0.95 * len(frames)  # and the rate is kept
