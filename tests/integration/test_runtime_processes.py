"""The runtime's rules with real processes over zenoh on loopback, driven by the CLI."""

from __future__ import annotations

import itertools
import math
import signal
import threading
import time
from pathlib import Path

import pytest

from dbml.protocol import names
from dbml.protocol.keys import LINK_TOPIC, encode_param, param_key
from dbml.protocol.messages import Heard, LinkBeacon
from dbml.protocol.metadata import MessageMeta
from dbml.transports.base import ParamValue, Sample, Variant
from tests.conftest import MONITOR_JSON_KEYS, wait_for
from tests.integration.procs import fleet, publish_argv

pytestmark = pytest.mark.integration

CAMERA = "/r1/camera"
FRAME_BYTES = 84_000
FLOOD_MAX_BEACONS = 5_000
"""A forged-beacon flood's bound in rounds (three beacons a round, every 5 ms: about 25 s)."""


def config(tmp_path: Path, *, mbit: float, period_s: float = 1.0) -> str:
    path = tmp_path / "dbm.yaml"
    path.write_text(
        f"dbm:\n  max_bandwidth_in_mbit: {mbit}\n  optimization_rate_in_seconds: {period_s}\n"
    )
    return str(path)


def publisher(size: int = 84_000, *extra: str) -> list[str]:
    args = ["publish", CAMERA, "--size-bytes", str(size), "--min-hz", "1", "--max-hz", "16"]
    return [*args, "--host", "robot1", *extra]


def allocated(f: object) -> float | None:
    value = f.param(names.current_value(CAMERA))  # type: ignore[attr-defined]
    return float(value) if isinstance(value, int | float) else None


def test_local_subscriber_gets_full_rate_remote_gets_optimized() -> None:
    with fleet() as f:
        f.start(*publisher(1000))
        local = f.start("subscribe", CAMERA, "--json", "--host", "robot1")
        remote = f.start("subscribe", CAMERA, "--json", "--host", "operator")

        def variant_of(proc: object) -> str | None:
            for line in proc.json_lines(timeout_s=15):  # type: ignore[attr-defined]
                if line["rate_hz"] > 0:
                    return str(line["variant"])
            return None

        assert variant_of(local) == "full"
        assert variant_of(remote) == "optimized"


def test_unmanaged_runs_at_max_and_returns_to_max_when_the_remote_subscriber_leaves(
    tmp_path: Path,
) -> None:
    with fleet() as f:
        f.start("optimizer", "--config", config(tmp_path, mbit=2), "--host", "base")
        f.start(*publisher())
        f.start("subscribe", CAMERA, "--host", "robot1")  # a local reader does not manage it
        wait_for(lambda: allocated(f) == 16.0, timeout_s=15, what="unmanaged at max (16 Hz)")
        assert f.param(names.managed(CAMERA)) is False
        remote = f.start("subscribe", CAMERA, "--host", "operator")
        # 2 Mbit/s = 250,000 B/s over 84,000 B frames
        wait_for(
            lambda: allocated(f) == pytest.approx(250_000 / 84_000),
            timeout_s=15,
            what="managed at 2.98 Hz",
        )
        assert f.param(names.managed(CAMERA)) is True
        remote.stop(signal.SIGTERM)
        wait_for(lambda: allocated(f) == 16.0, timeout_s=10, what="back to max after it leaves")


def test_priority_change_reacts_at_once_not_at_the_period(tmp_path: Path) -> None:
    with fleet() as f:
        f.start("optimizer", "--config", config(tmp_path, mbit=11, period_s=60), "--host", "base")
        for robot, topic, size in (
            ("robot1", "/r1/camera", 84_000),
            ("robot2", "/r2/camera", 21_000),
        ):
            f.start(*publish_argv(topic, size, "--host", robot))
            f.start("subscribe", topic, "--host", "operator")
        # priorities 0/0: Table 2 step 2, R1 12.37 Hz
        wait_for(lambda: round(allocated(f) or 0, 2) == 12.37, timeout_s=20, what="12.37 Hz")
        setter = f.start("priority", "/r1/camera", "0.8", "--host", "cli")
        assert setter.wait(30) == 0, setter.stderr()
        # R1 at priority 0.8 (R2 0): floor 16 Hz. The period is 60 s: only an event explains it.
        wait_for(lambda: allocated(f) == 16.0, timeout_s=5, what="the immediate reaction")


def test_failsafe_without_optimizer_and_takeover_by_a_new_one(tmp_path: Path) -> None:
    cfg = config(tmp_path, mbit=2, period_s=0.5)
    with fleet() as f:
        optimizer = f.start("optimizer", "--config", cfg, "--host", "base")
        robot = f.start(*publisher())
        f.start("subscribe", CAMERA, "--host", "operator")
        wait_for(
            lambda: allocated(f) == pytest.approx(250_000 / 84_000),
            timeout_s=15,
            what="the first allocation",
        )
        optimizer.stop(signal.SIGKILL)  # no clean goodbye
        wait_for(
            lambda: "fail-safe: minimum 1.000 Hz" in robot.stderr(),
            timeout_s=10,
            what="the publisher's fail-safe log line",
        )
        f.start("optimizer", "--config", cfg, "--host", "base2")
        wait_for(
            lambda: "allocation heard again" in robot.stderr(),
            timeout_s=10,
            what="the new optimizer taking over",
        )


def test_monitor_json_lists_every_channel(tmp_path: Path) -> None:
    with fleet() as f:
        f.start("optimizer", "--config", config(tmp_path, mbit=11), "--host", "base")
        f.start(*publisher(21_000, "--priority", "0.5"))
        f.start("subscribe", CAMERA, "--host", "operator")
        wait_for(lambda: allocated(f) == 16.0, timeout_s=15, what="an allocation")
        monitor = f.start("monitor", "--json", "--duration", "3", "--host", "viewer")
        rows = [row for row in monitor.json_lines(timeout_s=20) if row["topic"] == CAMERA]
        assert rows, monitor.stderr()
        row = rows[-1]
        assert set(row) == MONITOR_JSON_KEYS
        assert row["estimate_mbit"] is None  # this optimizer does not estimate
        assert row["host"] == "robot1"
        assert row["managed"] is True
        assert row["priority"] == 0.5
        assert row["size_bytes"] == 21_000
        assert row["allocated_hz"] == 16.0
        assert row["share"] == pytest.approx(16 * 21_000 / 1_375_000)
        assert row["status"] == "optimal"
        assert monitor.wait(15) == 0


def test_an_estimating_optimizer_shows_its_estimate_in_the_monitor(tmp_path: Path) -> None:
    """On loopback the link carries everything: the estimate sits at the configured budget."""
    with fleet() as f:
        f.start("optimizer", "--config", config(tmp_path, mbit=11), "--estimate", "--host", "base")
        f.start(*publisher(21_000, "--priority", "0.5"))
        f.start("subscribe", CAMERA, "--host", "operator")  # reports what it receives
        monitor = f.start("monitor", "--json", "--duration", "6", "--host", "viewer")
        rows = (row for row in monitor.json_lines(timeout_s=20) if row["topic"] == CAMERA)
        # The estimate and the estimator's state are two parameters: a row may hold one first.
        row = next(
            (r for r in rows if r["estimate_mbit"] is not None and r["estimator"] is not None),
            None,
        )
        assert row is not None, monitor.stderr()
        assert row["estimate_mbit"] == pytest.approx(11.0)  # never above the configured
        assert row["estimator"].split(":")[0] in {"increase", "hold", "decrease"}
        assert "received" in row["estimator"]


def test_bad_values_from_a_peer_are_ignored_and_the_wire_keeps_the_budget(
    tmp_path: Path,
) -> None:
    """Garbage written by any peer is refused where it enters each process.

    Nothing crashes, no channel drops out, the rate on the wire stays the allocated one.
    """
    budget = 4 * 125_000  # 4 Mbit/s: 5.95 Hz of 84,000-byte frames
    with fleet() as f:
        optimizer = f.start("optimizer", "--config", config(tmp_path, mbit=4), "--host", "base")
        camera = f.start(*publisher())
        viewer = f.start("subscribe", CAMERA, "--json", "--host", "operator")
        wait_for(
            lambda: allocated(f) == pytest.approx(budget / 84_000),
            timeout_s=15,
            what="the allocation",
        )
        # The stream flows before the writes: every 1-s window read below then starts after
        # its first frame (one that did not once counted 4 of the allocated 5.95 frames).
        flowing = (line for line in viewer.json_lines(timeout_s=10) if line["bytes_per_s"] > 0)
        assert next(flowing, None) is not None, viewer.stderr()
        writes: list[tuple[str, ParamValue]] = [  # on the wire: set() refuses them here
            (names.max_rate(CAMERA), -1),  # once dropped the live channel from the allocation
            (names.max_rate(CAMERA), "x"),
            (names.current_value(CAMERA), math.nan),  # once killed the publisher
            (names.current_value(CAMERA), 1e12),  # once gave thousands of frames at once
            (names.PERIOD, math.inf),  # once killed the optimizer's thread
            (names.priority(CAMERA), 10**400),
            (names.BANDWIDTH, 1e300),
        ]
        for name, value in writes:
            f.probe.session.put(param_key(name), encode_param(value, time.time_ns(), "hostile"))
        # A budget stamped an hour ahead: newest-stamp-wins once pinned such a write for good.
        future_ns = time.time_ns() + 3600 * 10**9
        f.probe.session.put(
            param_key(names.BANDWIDTH), encode_param(100.0, future_ns, "not-a-clock")
        )
        wait_for(
            lambda: "ignored: " in str(f.param(names.STATUS_MESSAGE)),
            timeout_s=10,
            what="the bad values reported in /dbm/status_message",
        )
        viewer.drain()  # lines printed before the allocation settled are not the claim
        rates = [
            line["bytes_per_s"]
            for line, _ in zip(viewer.json_lines(timeout_s=8), range(5), strict=False)
        ]
        assert len(rates) == 5
        assert max(rates) <= 1.1 * budget  # whole frames per 1-s window: at most one extra
        assert min(rates) >= 0.75 * budget  # still sending: nothing dropped out
        assert f.param(names.current_value(CAMERA)) == pytest.approx(budget / 84_000)
        for proc in (optimizer, camera, viewer):
            assert proc.poll() is None, proc.stderr()
        assert "Traceback" not in optimizer.stderr() + camera.stderr()
        # Good values again: the reports go, and a change is followed as ever.
        for name, good in [
            (names.max_rate(CAMERA), 16.0),
            (names.priority(CAMERA), 0.5),
            (names.PERIOD, 1.0),
            (names.BANDWIDTH, 2.0),
        ]:
            f.probe.params.set(name, good)
        wait_for(
            lambda: "ignored: " not in str(f.param(names.STATUS_MESSAGE)),
            timeout_s=10,
            what="no bad value reported any more",
        )
        wait_for(
            lambda: allocated(f) == pytest.approx(2 * 125_000 / 84_000),
            timeout_s=10,
            what="the allocation following the good budget",
        )


def test_a_forged_graph_token_neither_pulls_the_full_stream_nor_unmanages(
    tmp_path: Path,
) -> None:
    """A plain session claims "/r1/camera is published on host operator".

    The operator's subscriber once took the full-rate stream from r1 over the network for it,
    and the optimizer stopped managing the channel: 1.59 x B.
    """
    budget = 4 * 125_000
    with fleet() as f:
        f.start("optimizer", "--config", config(tmp_path, mbit=4), "--host", "base")
        f.start(*publisher())
        viewer = f.start("subscribe", CAMERA, "--json", "--host", "operator")
        wait_for(
            lambda: allocated(f) == pytest.approx(budget / 84_000),
            timeout_s=15,
            what="the allocation",
        )
        forged = f.probe.session.liveliness().declare_token(
            f"dbml/graph/pub/operator/forged.1/full{CAMERA}"
        )
        try:
            wait_for(
                lambda: any(
                    e.host == "operator" and e.uid == "forged.1" for e in f.probe.graph.entries()
                ),
                timeout_s=10,
                what="the forged token in the graph",
            )
            viewer.drain()  # only what was received with the forged token standing
            lines = [
                line for line, _ in zip(viewer.json_lines(timeout_s=8), range(5), strict=False)
            ]
        finally:
            forged.undeclare()  # type: ignore[no-untyped-call]
        assert len(lines) == 5
        assert {line["variant"] for line in lines} == {"optimized"}
        assert max(line["bytes_per_s"] for line in lines) <= 1.1 * budget
        assert f.param(names.managed(CAMERA)) is True
        assert f.param(names.current_value(CAMERA)) == pytest.approx(budget / 84_000)


def test_forged_link_beacons_never_widen_the_wire(tmp_path: Path) -> None:
    """Forged ``/dbm/link`` beacons from a plain session never raise what is sent.

    The flood: garbage, outages, releases naming every channel as heard (without counts, with
    a count from another run, and with the count that owes least: the newest number read off
    the wire, nothing recent), beacons stamped an hour ahead, up and down alternating every few
    milliseconds. A beacon can make a publisher hold (send less), but nothing in one may raise
    a rate: each release spends the same credit as any message, and a count can at most owe
    nothing. Measured on the wire by the passive subscriber's 1-s windows while the flood
    lasts.
    """
    budget = 4 * 125_000
    with fleet() as f:
        f.start("optimizer", "--config", config(tmp_path, mbit=4), "--host", "base")
        camera = f.start(*publisher())
        viewer = f.start("subscribe", CAMERA, "--json", "--host", "operator")
        wait_for(
            lambda: allocated(f) == pytest.approx(budget / 84_000),
            timeout_s=15,
            what="the allocation",
        )
        beacon = f.probe.declare_publisher(LINK_TOPIC)
        newest = [0]  # the camera's newest sequence number, as anyone on the network sees it

        def on_frame(sample: Sample) -> None:
            if sample.attachment is not None:
                newest[0] = max(newest[0], MessageMeta.decode(sample.attachment).seq)

        watch = f.probe.subscribe(CAMERA, on_frame, Variant.OPTIMIZED)

        def heard(k: int) -> dict[str, Heard] | None:
            counts = [None, Heard(10**9, 0), Heard(newest[0], 0)][k % 3]
            return None if counts is None else {CAMERA: counts, "/r2/camera": counts}

        garbage = [b"{not json", b'{"up": true, "heard": [1]}', b'{"up": "false"}']
        stop = threading.Event()

        def flood() -> None:
            for k in itertools.count():
                if stop.is_set() or k >= FLOOD_MAX_BEACONS:
                    return
                now = f.probe.now()
                forged = [
                    LinkBeacon(up=k % 2 == 0, release_s={CAMERA: 0.0}, sent_s=now, heard=heard(k)),
                    LinkBeacon(up=True, release_s={CAMERA: 0.0}, sent_s=now - 3600.0),
                ]
                for data in [*(b.encode() for b in forged), garbage[k % len(garbage)]]:
                    beacon.put(data)
                stop.wait(0.005)

        flooder = threading.Thread(target=flood, name="forged-beacons")
        flooder.start()
        try:
            viewer.drain()  # only what was received while the flood lasts
            rates = [
                line["bytes_per_s"]
                for line, _ in zip(viewer.json_lines(timeout_s=8), range(5), strict=False)
            ]
        finally:
            stop.set()
            flooder.join(timeout=5)
            beacon.close()
            watch.close()
        assert len(rates) == 5
        assert max(rates) <= 1.1 * budget  # whole frames per 1-s window: at most one extra
        assert min(rates) >= FRAME_BYTES  # held and owed, never silenced: the minimum, 1 Hz
        assert camera.poll() is None, camera.stderr()
        assert "Traceback" not in camera.stderr()
