"""``dbml bridge`` and ``dbml router`` as real processes over zenoh on loopback."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from dbml.harness.processes import free_port
from dbml.protocol import names
from dbml.runtime.rate import RateLimiter
from tests.conftest import wait_for
from tests.integration.procs import fleet

pytestmark = pytest.mark.integration

CAMERA = "/r1/camera"
SIZE_BYTES = 10_000
SOURCE_HZ = 50.0
BUDGET_MBIT = 0.8
"""100,000 B/s: 10 Hz of 10 kB frames, well under the source's 50 Hz and the 40 Hz maximum."""
EXPECTED_HZ = BUDGET_MBIT * 125_000 / SIZE_BYTES
WINDOW_S = 1.0
TOLERANCE = 0.25
MEASURED_WINDOWS = 4
"""The span measured, in windows: sliding 1-s windows every half second over it."""


def _session(*, connect: list[str] | None = None, mode: str = "peer") -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", f'"{mode}"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    if connect:
        config.insert_json5("connect/endpoints", "[" + ", ".join(f'"{e}"' for e in connect) + "]")
    return zenoh.open(config)


@contextmanager
def plain_source(port: int) -> Iterator[None]:
    """A plain zenoh publisher of ``r1/camera`` (no dbml), 10 kB at 50 Hz, until the block ends."""
    session = _session(connect=[f"tcp/127.0.0.1:{port}"])
    stop = threading.Event()

    def run() -> None:
        for n in range(1, 10_001):  # bounded: 200 s at 50 Hz
            if stop.wait(1.0 / SOURCE_HZ):
                return
            session.put(CAMERA[1:], n.to_bytes(4, "big") + bytes(SIZE_BYTES - 4))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=5)
        session.close()  # type: ignore[no-untyped-call]


def test_bridge_forwards_at_the_allocated_rate(tmp_path: Path) -> None:
    config = tmp_path / "dbm.yaml"
    config.write_text(f"dbm:\n  max_bandwidth_in_mbit: {BUDGET_MBIT}\n")
    arrivals: list[tuple[float, int, int]] = []
    lock = threading.Lock()

    def passive(sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        with lock:
            arrivals.append((time.monotonic(), len(payload), int.from_bytes(payload[:4], "big")))

    with fleet() as f, plain_source(f.port):
        listener = _session(connect=[f"tcp/127.0.0.1:{f.port}"])
        try:
            listener.declare_subscriber(CAMERA[1:] + "/optimized", passive)
            f.start("optimizer", "--config", str(config), "--host", "base")
            bridge = f.start(
                "bridge", CAMERA, "--min-hz", "1", "--max-hz", "40", "--host", "robot1"
            )
            f.start("subscribe", CAMERA, "--host", "operator")  # remote: makes it managed
            wait_for(
                lambda: f.param(names.current_value(CAMERA)) == pytest.approx(EXPECTED_HZ),
                timeout_s=20,
                what=f"the allocation of {EXPECTED_HZ} Hz",
            )
            assert f.param(names.size(CAMERA)) == SIZE_BYTES
            assert f.param(names.managed(CAMERA)) is True
            wait_for(
                lambda: f.param(names.applied(CAMERA)) == pytest.approx(EXPECTED_HZ),
                timeout_s=10,
                what="the bridge applying the allocation",
            )
            applied_at = time.monotonic()

            def after(t0: float, count: int) -> list[float]:
                with lock:
                    return [t for t, _, _ in arrivals if t >= t0][:count]

            # The frames banked at the old rate go out first; the measurement starts after.
            banked = int(RateLimiter.BANKED_FRAMES) + 1
            wait_for(
                lambda: len(after(applied_at, banked)) == banked,
                timeout_s=10,
                what="the banked frames forwarded",
            )
            start = after(applied_at, banked)[-1]
            end = start + MEASURED_WINDOWS * WINDOW_S
            wait_for(
                lambda: bool(after(end, 1)),
                timeout_s=3 * MEASURED_WINDOWS * WINDOW_S,
                what="frames over the whole measured span",
            )
            assert bridge.poll() is None, bridge.stderr()
        finally:
            listener.close()  # type: ignore[no-untyped-call]
    with lock:
        measured = [a for a in arrivals if a[0] >= start]
        numbers = [n for _, _, n in arrivals]
    assert numbers == sorted(set(numbers))  # each message at most once, never an older one
    budget = BUDGET_MBIT * 125_000
    for k in range(2 * MEASURED_WINDOWS - 1):  # sliding 1-s windows over the span
        t0 = start + k * 0.5
        in_window = sum(size for t, size, _ in measured if t0 <= t < t0 + WINDOW_S)
        assert in_window == pytest.approx(budget * WINDOW_S, rel=TOLERANCE), (k, in_window)


def test_bridge_of_a_silent_topic_exits_2_with_one_line() -> None:
    with fleet() as f:
        proc = f.start("bridge", "/nobody", "--min-hz", "1", "--max-hz", "5", "--wait", "0.5")
        assert proc.wait(30) == 2
        proc.stop()
        assert proc.stderr_lines == [
            "dbml: error: topic='/nobody': no message within 0.5 s "
            "(is its publisher running on this host?)\n"
        ]


def test_bridge_over_ros2_of_an_untyped_topic_exits_2_with_one_line() -> None:
    """Over ROS 2 every topic has a type: none found and no --type is an error, not a guess."""
    listen = f"tcp/127.0.0.1:{free_port()}"
    with fleet() as f:
        proc = f.start(
            "bridge", "/nobody", "--min-hz", "1", "--max-hz", "5", "--wait", "0.5",
            "--transport", "ros2", "--listen", listen,
        )  # fmt: skip
        assert proc.wait(30) == 2
        proc.stop()
        assert proc.stderr_lines == [
            "dbml: error: topic='/nobody': its type cannot be resolved (no publisher seen "
            "within 0.5 s); name it with --type pkg/msg/Name\n"
        ]


def test_bridge_bad_bounds_exit_2_with_one_line() -> None:
    with fleet() as f:
        proc = f.start("bridge", CAMERA, "--min-hz", "9", "--max-hz", "3")
        assert proc.wait(30) == 2
        proc.stop()
        assert proc.stderr().count("\n") == 1
        assert "frequency.min=9.0 exceeds frequency.max=3.0" in proc.stderr()


def test_router_routes_between_two_clients() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with fleet() as f:
        router = f.start("router", "--listen", endpoint)
        line = router.next_line(timeout_s=20)
        assert line == f"zenoh router listening on {endpoint}"
        received: list[bytes] = []
        first = _session(connect=[endpoint], mode="client")
        second = _session(connect=[endpoint], mode="client")
        try:
            second.declare_subscriber("dbml/test", lambda s: received.append(s.payload.to_bytes()))

            def delivered() -> bool:
                first.put("dbml/test", b"hello")
                return b"hello" in received

            wait_for(delivered, timeout_s=10, what="a put routed from one client to the other")
        finally:
            first.close()  # type: ignore[no-untyped-call]
            second.close()  # type: ignore[no-untyped-call]
        assert router.stop() == 0


def test_router_bad_endpoint_exits_2_with_one_line() -> None:
    with fleet() as f:
        proc = f.start("router", "--listen", "tcp/127.0.0.1:99999")
        assert proc.wait(30) == 2
        proc.stop()
        assert proc.stderr().count("\n") == 1
        assert "endpoint='tcp/127.0.0.1:99999'" in proc.stderr()
