import io
import json
import logging
import subprocess
import sys
import threading

import pytest

from dbml.cli.commands import (
    run_monitor,
    run_optimizer,
    run_subscriber,
    set_budget,
    set_priority,
)
from dbml.core import DbmSettings, SpecError
from dbml.protocol import names
from dbml.runtime import ManagedPublisher, ManagedSubscriber, OptimizerNode
from dbml.runtime.monitor import MonitorView, channel_rows
from dbml.runtime.rounds import RoundFollower
from dbml.transports import MemoryNetwork, MemoryTransport
from tests.conftest import MONITOR_JSON_KEYS


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (-0.1, r"^priority=-0.1 must be within \[0, 1\]$"),
        (1.5, r"^priority=1.5 must be within \[0, 1\]$"),
        (float("nan"), r"^priority=nan is not finite$"),
    ],
)
def test_priority_outside_0_1_is_rejected(value: float, message: str) -> None:
    with pytest.raises(SpecError, match=message):
        set_priority(MemoryTransport(), "/r1/camera", value)


def test_priority_is_set() -> None:
    network = MemoryNetwork()
    set_priority(MemoryTransport(network, host="cli"), "/r1/camera", 0.7)
    assert MemoryTransport(network, host="x").params.get(names.priority("/r1/camera")) == 0.7


def test_monitor_rows_and_json() -> None:
    network = MemoryNetwork()
    camera = ManagedPublisher(
        MemoryTransport(network, host="robot1"),
        "/r1/camera",
        min_rate_hz=1,
        max_rate_hz=16,
        priority=0.5,
    )
    idle = ManagedPublisher(
        MemoryTransport(network, host="robot2"), "/r2/scan", min_rate_hz=1, max_rate_hz=10
    )
    camera.publish(bytes(84_000))
    idle.publish(bytes(1000))
    ManagedSubscriber(MemoryTransport(network, host="operator"), "/r1/camera", lambda s: None)
    viewer = MemoryTransport(network, host="viewer")
    rounds = RoundFollower(viewer)
    optimizer = OptimizerNode(MemoryTransport(network, host="base"), settings=DbmSettings(11.0))
    # Before the optimizer's first report: the rate pushed, no share of the budget.
    assert channel_rows(viewer, rounds.latest())[0].share is None
    optimizer.optimize()
    rows = {row.topic: row for row in channel_rows(viewer, rounds.latest())}
    assert rows["/r1/camera"].managed
    assert rows["/r1/camera"].host == "robot1"
    # the only managed channel: p' = 1, floor = max = 16 Hz
    assert rows["/r1/camera"].allocated_hz == 16.0
    assert rows["/r1/camera"].share == pytest.approx(16 * 84_000 / 1_375_000)
    assert rows["/r1/camera"].status == "optimal"
    assert not rows["/r2/scan"].managed
    assert rows["/r2/scan"].allocated_hz == 10.0
    assert rows["/r2/scan"].status == "unmanaged"
    views: list[MonitorView] = []
    stop = threading.Event()
    stop.set()  # one update, then stop
    run_monitor(MemoryTransport(network, host="viewer"), show=views.append, stop=stop)
    assert views == []  # stopped before the first update
    run_monitor(
        MemoryTransport(network, host="viewer"),
        show=views.append,
        stop=threading.Event(),
        duration_s=0.01,
        interval_s=0.01,
    )
    lines = [json.loads(json.dumps(row.as_json())) for view in views for row in view.rows]
    assert {line["topic"] for line in lines} == {"/r1/camera", "/r2/scan"}
    assert set(lines[0]) == MONITOR_JSON_KEYS


def test_subscriber_reports_variant_rate_and_bytes() -> None:
    network = MemoryNetwork()
    camera = ManagedPublisher(
        MemoryTransport(network, host="robot1"), "/cam", min_rate_hz=100, max_rate_hz=100
    )
    MemoryTransport(network, host="base").params.set(names.current_value("/cam"), 100.0)
    out = io.StringIO()
    stop = threading.Event()

    def publish() -> None:
        while not stop.is_set():
            camera.publish(bytes(1000))
            stop.wait(0.01)

    thread = threading.Thread(target=publish)
    thread.start()
    try:
        run_subscriber(
            MemoryTransport(network, host="operator"),
            "/cam",
            as_json=True,
            stop=threading.Event(),
            duration_s=1.5,
            out=out,
        )
    finally:
        stop.set()
        thread.join()
    line = json.loads(out.getvalue().splitlines()[0])
    assert set(line) == {"topic", "variant", "rate_hz", "bytes_per_s"}
    assert line["variant"] == "optimized"
    assert line["rate_hz"] > 10
    assert line["bytes_per_s"] == pytest.approx(line["rate_hz"] * 1000)


def test_cli_bad_priority_is_one_line_exit_2() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "dbml", "priority", "/r1/camera", "3"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 2
    assert result.stderr.strip().endswith("priority=3.0 must be within [0, 1]")
    assert result.stderr.count("\n") == 1


def test_the_optimizer_command_exits_non_zero_when_its_worker_dies(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A process that looks alive while its optimizer thread is gone helps nobody."""

    def die(_self: OptimizerNode) -> None:
        raise SystemExit("gone")  # ends a thread silently, unlike an Exception

    monkeypatch.setattr(OptimizerNode, "optimize", die)
    transport = MemoryTransport(MemoryNetwork(), host="base")
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        code = run_optimizer(
            transport, settings=None, links=(), stop=threading.Event(), duration_s=10.0
        )
    assert code == 1
    assert "the thread died" in caplog.text
    assert "exiting so a supervisor restarts" in caplog.text


def test_the_subscriber_command_exits_non_zero_when_a_part_of_it_ends(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its run watches the subscriber: one no longer following the graph ends it, exit 1."""
    monkeypatch.setattr(ManagedSubscriber, "alive", property(lambda _self: False))
    out = io.StringIO()
    with caplog.at_level(logging.CRITICAL, logger="dbml"):
        code = run_subscriber(
            MemoryTransport(MemoryNetwork(), host="operator"),
            "/cam",
            as_json=True,
            stop=threading.Event(),
            duration_s=10.0,
            out=out,
        )
    assert code == 1
    assert out.getvalue() == ""  # over before its first line
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.CRITICAL] == [
        "a worker thread died (see above); exiting so a supervisor restarts it"
    ]


def test_budget_writes_bandwidth_and_utilization_for_everyone() -> None:
    network = MemoryNetwork()
    reader = MemoryTransport(network, host="base")
    assert set_budget(MemoryTransport(network, host="op"), 8, utilization=0.9) == 0
    assert reader.params.get(names.BANDWIDTH) == 8.0
    assert reader.params.get(names.UTILIZATION) == 0.9
