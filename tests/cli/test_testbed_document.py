"""``dbml testbed teleop --json``: what a run on real frames and a traced run add to the summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dbml.cli import documents
from dbml.experiment.analysis import StepResult, Window
from dbml.testbed.options import TestbedOptions
from dbml.testbed.result import LinkTiming, TestbedResult


def _window(robot: str, hz: float, ssim: float | None) -> Window:
    return Window(robot, hz, hz, 40.0, 60.0, 0, 1.0, ssim=ssim)


def _steps(hz: float, ssim: float | None) -> tuple[StepResult, ...]:
    return tuple(
        StepResult(k + 1, (_window("R1", hz, ssim), _window("R2", hz, ssim)), 10.12, None, 11.0)
        for k in range(10)
    )


def test_a_run_on_real_frames_is_judged_by_its_utility() -> None:
    options = TestbedOptions.from_flags(frames="photos")
    perfect = documents.testbed_document(TestbedResult(options, "run", steps=_steps(16.0, 1.0)))
    # Every camera at 16 Hz with SSIM 1 is worth its weight: 0.1 plus eq. 2's normalised
    # priority; over Table 2's ten steps the weights add up to 11.0 (docs/quality.md).
    assert perfect["summary"]["utility"] == pytest.approx(11.0)
    blind = documents.testbed_document(TestbedResult(options, "run", steps=_steps(16.0, None)))
    assert blind["summary"]["utility"] == 0.0  # nothing decoded, nothing seen
    synthetic = documents.testbed_document(
        TestbedResult(TestbedOptions(), "run", steps=_steps(16.0, 1.0))
    )
    assert "utility" not in synthetic["summary"]


def test_a_traced_run_says_how_its_link_changes_went() -> None:
    timing = LinkTiming.of([(0.001, 0.006), (0.0, 0.005), (0.002, 0.02)])
    assert timing is not None
    document = documents.testbed_document(
        TestbedResult(TestbedOptions(), "run", link_timing=timing)
    )
    assert document["summary"]["link_timing"] == {
        "changes": 3,
        "call_ms_p50": pytest.approx(6.0),
        "call_ms_max": pytest.approx(20.0),
        "late_ms_p50": pytest.approx(1.0),
        "late_ms_max": pytest.approx(2.0),
    }
    assert document["link_trace"] is None


def test_a_traced_run_records_its_links_queue(tmp_path: Path) -> None:
    pattern = [{"capacity": 8_000, "duration": 1_000}, {"capacity": 10, "duration": 200}]
    trace = tmp_path / "radio.json"
    trace.write_text(json.dumps({"uplink": {"trace_pattern": pattern}}))
    options = TestbedOptions.from_flags(link_trace=str(trace))
    document = documents.testbed_document(TestbedResult(options, "run"))
    # 200 ms of its usual 8 Mbit/s and tbf's 4,000-byte burst
    assert document["link_trace"] == {
        "name": "radio",
        "duration_s": pytest.approx(1.2),
        "clamped": 0,
        "queue_bytes": 204_000,
    }
