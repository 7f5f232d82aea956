"""``dbml testbed teleop --foxglove PORT --record FILE``: the operator's view, from this machine.

The operator runs in its own namespace, which has no link to this one: its view is reached
through the forward (``dbml.testbed.forward``), and its recording is written where asked.
"""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from dbml.harness.processes import free_port
from dbml.testbed import leftover_namespaces
from dbml.testbed.options import TestbedOptions
from dbml.testbed.result import TestbedResult
from dbml.testbed.runner import run_teleop_testbed
from dbml.view.client import FoxgloveClient
from dbml.view.target import ViewTarget
from tests.integration.test_foxglove import EXPECTED, read_mcap

pytestmark = pytest.mark.integration

STEP_S = 2.0
R1 = "/r1/camera"


def test_the_operator_s_view_is_reached_from_here_and_recorded(
    netns_privilege: None, tmp_path: Path
) -> None:
    port = free_port()
    record = tmp_path / "run.mcap"
    view = ViewTarget.from_flags(f"127.0.0.1:{port}", str(record))
    options = TestbedOptions.from_flags(step_seconds=STEP_S, view=view)
    results: list[TestbedResult] = []
    run = threading.Thread(target=lambda: results.append(run_teleop_testbed(options)))
    run.start()
    try:
        with FoxgloveClient(f"ws://127.0.0.1:{port}", timeout_s=60) as client:
            frames = f"{R1}/optimized"
            assert client.pump(
                lambda: (
                    len(client.messages.get(frames, [])) >= 10
                    and len(client.json_messages("/dbm/allocation")) >= 3
                ),
                timeout_s=40,
            ), {topic: len(m) for topic, m in client.messages.items()}
            client.set_parameter("bad", "/dbm/max_bandwidth_in_mbit", -3)
            assert client.pump(lambda: client.answer("bad") is not None, timeout_s=5)
            answer = client.answer("bad")
            assert answer is not None
            assert answer["parameters"][0]["value"] == 11.0
    finally:
        run.join(timeout=120)
    assert not run.is_alive()
    (result,) = results
    assert not result.interrupted
    assert len(result.steps) == 10
    assert leftover_namespaces(f"dbml-{result.run_id}-") == []
    recording = read_mcap(record)
    assert set(recording["channels"]) == set(EXPECTED)
    assert len(recording["messages"][f"{R1}/optimized"]) >= 10 * STEP_S
