"""``dbml demo teleop --foxglove PORT --record FILE``: the live view as a Foxglove client sees it.

A real demo (four OS processes over zenoh); this test is the app: a WebSocket client on
``foxglove.sdk.v1`` subscribing to every channel. It checks the allocation against Table 2, sets
the budget through the Parameters capability (bad values refused and nothing changed, a good one
moving the allocation), and reads the recording back with the ``mcap`` package: every channel
with its schema, every message the live client got, one frequency sample per round.
"""

from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from dbml.harness.processes import free_port
from dbml.view.client import FoxgloveClient
from tests.integration.procs import ROOT, Proc, fleet, publish_argv

pytestmark = pytest.mark.integration

R1, R2 = "/r1/camera", "/r2/camera"
PUBLISH_R1 = publish_argv(R1, 84_000)[1:]
BUDGET = "/dbm/max_bandwidth_in_mbit"
STEP_S = 2.0
CONNECT_S = 60.0
"""The roles open their transports and meet first; the operator's view starts with the run."""
EXPECTED = {
    "/dbm/allocation": ("dbml.Allocation", "jsonschema", "json"),
    "/dbm/budget": ("dbml.Budget", "jsonschema", "json"),
    "/dbm/log": ("foxglove.Log", "protobuf", "protobuf"),
    **{
        f"{t}/dbm/frequency/{field}": ("dbml.Frequency", "jsonschema", "json")
        for t in (R1, R2)
        for field in ("current_value", "delivered_value")
    },
    **{f"{t}/optimized": ("sensor_msgs/msg/Image", "ros2msg", "cdr") for t in (R1, R2)},
}
"""Every channel of the demo's view: its schema's name and encoding, its message encoding."""


def channel(allocation: dict[str, Any], topic: str) -> dict[str, Any]:
    found = [c for c in allocation["channels"] if c["topic"] == topic]
    assert len(found) == 1, allocation
    first: dict[str, Any] = found[0]
    return first


def rates(allocation: dict[str, Any]) -> tuple[float | None, float | None]:
    return channel(allocation, R1)["rate_hz"], channel(allocation, R2)["rate_hz"]


def is_step1(allocation: dict[str, Any]) -> bool:
    """Table 2's step 1: R2 has its priority (before it, both have 0, and the same rates)."""
    if len(allocation["channels"]) != 2 or channel(allocation, R2)["priority"] == 0:
        return False
    r1, r2 = rates(allocation)
    return r1 is not None and r2 is not None and (round(r1, 2), round(r2, 2)) == (12.37, 16.0)


def read_mcap(path: Path) -> dict[str, Any]:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        channels = {
            c.topic: (summary.schemas[c.schema_id], c.message_encoding)
            for c in summary.channels.values()
        }
        messages: dict[str, list[tuple[int, bytes]]] = {}
        for _, chan, message in reader.iter_messages():
            messages.setdefault(chan.topic, []).append((message.log_time, message.data))
    return {"channels": channels, "messages": messages}


@pytest.fixture
def demo(tmp_path: Path) -> Any:
    port = free_port()
    record = tmp_path / "demo.mcap"
    args = [
        "demo",
        "teleop",
        "--step-seconds",
        str(STEP_S),
        "--foxglove",
        f"127.0.0.1:{port}",
        "--record",
        str(record),
        "--json",
    ]
    proc = Proc(args, dict(os.environ, PYTHONPATH=str(ROOT / "src")))
    try:
        yield proc, f"ws://127.0.0.1:{port}", record
    finally:
        proc.stop()


def test_the_demo_view_live_and_recorded(demo: Any) -> None:
    proc, url, record = demo
    with FoxgloveClient(url, timeout_s=CONNECT_S) as client:
        assert client.server_info is not None or client.pump(
            lambda: client.server_info is not None, timeout_s=5
        )
        assert client.server_info is not None
        assert "parameters" in client.server_info["capabilities"]

        # Step 1 of Table 2, as the app decodes /dbm/allocation.
        def step1() -> dict[str, Any] | None:
            return next((a for a in client.json_messages("/dbm/allocation") if is_step1(a)), None)

        assert client.pump(lambda: step1() is not None, timeout_s=30), (
            client.json_messages("/dbm/allocation")[-3:],
            "".join(proc.stderr_lines[-20:]),
        )
        first = step1()
        assert first is not None
        assert first["status"] == "optimal"
        assert first["budget_mbit"] == pytest.approx(11.0)
        r1, r2 = channel(first, R1), channel(first, R2)
        assert (r1["size_bytes"], r2["size_bytes"]) == (84_000, 21_000)
        assert (r1["min_hz"], r1["max_hz"], r2["min_hz"], r2["max_hz"]) == (1, 16, 1, 16)
        assert r1["managed"]
        assert r2["managed"]
        # Table 2, step 1: R1 at tc 20 s has priority 0, R2 at tc 10 s 0.59 (eq. 7); only R2
        # weighs in eq. 2, so its floor is its maximum (eq. 3).
        assert r1["priority"] == 0.0
        assert r2["priority"] == pytest.approx(0.588, abs=0.001)
        assert (r1["normalized_priority"], r2["normalized_priority"]) == (0.0, 1.0)
        assert (r1["floor_hz"], r2["floor_hz"]) == (1.0, 16.0)
        assert r1["share"] + r2["share"] == pytest.approx(1.0, abs=0.001)

        # Refused: -3, a NaN literal (the server's JSON parser refuses the message), "NaN".
        before = len(client.json_messages("/dbm/allocation"))
        client.set_parameter("minus", BUDGET, -3)
        client.send(
            {"op": "setParameters", "parameters": [{"name": BUDGET, "value": float("nan")}]}
        )
        client.set_parameter("nan-text", BUDGET, "NaN")
        assert client.pump(
            lambda: client.answer("minus") is not None and client.answer("nan-text") is not None,
            timeout_s=5,
        )
        for request in ("minus", "nan-text"):
            answer = client.answer(request)
            assert answer is not None
            assert answer["parameters"] == [{"name": BUDGET, "type": "float64", "value": 11.0}]
        statuses = client.statuses()
        assert any(f"refused: {BUDGET}=-3 must be" in s for s in statuses), statuses
        assert any(f"refused: {BUDGET}='NaN' is not a number" in s for s in statuses), statuses
        assert any("Invalid message" in s for s in statuses), statuses
        # Two more rounds, the budget unchanged in each.
        assert client.pump(
            lambda: len(client.json_messages("/dbm/allocation")) >= before + 2, timeout_s=5
        )
        later = client.json_messages("/dbm/allocation")[before:]
        assert all(a["budget_mbit"] == pytest.approx(11.0) for a in later), later
        # Nothing reached the store: a -3 written there would be named by the optimizer's view.
        assert not any("ignored" in (a["status_message"] or "") for a in later), later

        # A good value moves the allocation, and is answered with itself.
        client.set_parameter("half", BUDGET, 5.5)

        def halved() -> list[dict[str, Any]]:
            return [a for a in client.json_messages("/dbm/allocation") if a["budget_mbit"] == 5.5]

        assert client.pump(lambda: bool(halved()), timeout_s=5)
        answer = client.answer("half")
        assert answer is not None
        assert answer["parameters"] == [{"name": BUDGET, "type": "float64", "value": 5.5}]
        assert client.pump(
            lambda: any(a["allocated_mbit"] <= 5.5 + 1e-6 for a in halved()), timeout_s=5
        )
        client.set_parameter("back", BUDGET, 11.0)
        assert client.pump(lambda: client.answer("back") is not None, timeout_s=5)

        # Until the demo ends and closes the server.
        client.pump(lambda: proc.poll() is not None, timeout_s=60)
        live = {topic: list(messages) for topic, messages in client.messages.items()}
    assert proc.wait(30) in {0, 1}  # 1: the halved budget broke Table 2's step
    assert not any("Traceback" in line for line in proc.stderr_lines), proc.stderr_lines

    recording = read_mcap(record)
    assert set(recording["channels"]) == set(EXPECTED), sorted(recording["channels"])
    for topic, (schema_name, schema_encoding, encoding) in EXPECTED.items():
        schema, message_encoding = recording["channels"][topic]
        assert (schema.name, schema.encoding, message_encoding) == (
            schema_name,
            schema_encoding,
            encoding,
        )
        if schema_encoding == "jsonschema":
            assert json.loads(schema.data)["type"] == "object"
    messages = recording["messages"]
    # Every message the live client got is in the recording, the same bytes at the same time.
    for topic, got in live.items():
        missing = Counter(got) - Counter(messages.get(topic, []))
        assert not missing, (topic, len(missing))
    allocations = [json.loads(data) for _, data in messages["/dbm/allocation"]]
    assert len(allocations) >= 10 * STEP_S  # at least one per 1-s period over the 10 steps
    assert BUDGET not in json.dumps(allocations)  # parameters are not allocation fields
    for topic in (R1, R2):
        with_rate = sum(  # after the robots end, their channels leave the allocation
            1
            for a in allocations
            if any(c["topic"] == topic and c["rate_hz"] is not None for c in a["channels"])
        )
        samples = messages[f"{topic}/dbm/frequency/current_value"]
        assert len(samples) == with_rate  # one allocated-rate sample per round that rated it
    # The frames: ROS 2 images whose pixels are the payload the operator received.
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for topic, size in ((R1, 84_000), (R2, 21_000)):
        images = messages[f"{topic}/optimized"]
        assert len(images) >= 10 * STEP_S  # at least 1 Hz (the minimum) over the 10 steps
        image: Any = store.deserialize_cdr(images[-1][1], "sensor_msgs/msg/Image")
        assert (image.height * image.width, len(image.data), image.encoding) == (
            size,
            size,
            "mono8",
        )
        assert image.header.frame_id == topic


def test_the_optimizer_and_the_monitor_serve_the_view_and_a_priority_is_set_from_it(
    tmp_path: Path,
) -> None:
    config = tmp_path / "dbm.yaml"
    config.write_text("dbm:\n  max_bandwidth_in_mbit: 4\n")
    optimizer_port, monitor_port = free_port(), free_port()
    with fleet() as procs:
        optimizer = procs.start(
            "optimizer", "--config", str(config), "--host", "base",
            "--foxglove", f"127.0.0.1:{optimizer_port}",
        )  # fmt: skip
        procs.start("publish", *PUBLISH_R1, "--host", "robot1")
        procs.start("subscribe", R1, "--host", "operator")
        monitor = procs.start(
            "monitor", "--json", "--host", "desk", "--foxglove", f"127.0.0.1:{monitor_port}",
            "--record", str(tmp_path / "monitor.mcap"),
        )  # fmt: skip
        rate = 4e6 / 8 / 84_000
        for server, port in ((optimizer, optimizer_port), (monitor, monitor_port)):
            with FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=CONNECT_S) as client:

                def allocated() -> bool:
                    return any(
                        c["rate_hz"] == pytest.approx(rate)
                        for a in client.json_messages("/dbm/allocation")
                        for c in a["channels"]
                    )

                assert client.pump(allocated, timeout_s=20), (
                    server.args[0],
                    server.poll(),
                    client.topics(),
                    client.json_messages("/dbm/allocation")[-2:],
                    server.stderr()[-2000:],
                )
                assert client.pump(lambda: "/dbm/budget" in client.messages, timeout_s=5)
                assert client.json_messages("/dbm/budget")[-1]["max_bandwidth_mbit"] == 4.0
        # A priority set from the monitor's view reaches the optimizer, as `dbml priority` does.
        with FoxgloveClient(f"ws://127.0.0.1:{monitor_port}", timeout_s=CONNECT_S) as client:
            client.set_parameter("p", f"{R1}/dbm/priority", 0.75)
            client.set_parameter("bad", f"{R1}/dbm/priority", 1.5)
            assert client.pump(lambda: client.answer("bad") is not None, timeout_s=5)
            assert client.answer("p") == {
                "op": "parameterValues",
                "id": "p",
                "parameters": [{"name": f"{R1}/dbm/priority", "type": "float64", "value": 0.75}],
            }
            assert any(f"{R1}/dbm/priority=1.5 must be" in s for s in client.statuses())
        with FoxgloveClient(f"ws://127.0.0.1:{optimizer_port}", timeout_s=CONNECT_S) as client:

            def prioritized() -> bool:
                return any(
                    c["priority"] == 0.75
                    for a in client.json_messages("/dbm/allocation")
                    for c in a["channels"]
                )

            assert client.pump(prioritized, timeout_s=10)
        assert monitor.stop() == 0
    assert set(read_mcap(tmp_path / "monitor.mcap")["channels"]) >= {
        "/dbm/allocation",
        "/dbm/budget",
        f"{R1}/dbm/frequency/current_value",
    }
