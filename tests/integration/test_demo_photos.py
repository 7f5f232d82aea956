"""``dbml demo teleop --frames photos``: real frames, JPEG at the rung chosen, over zenoh.

Four OS processes, twice (the ladder, then rate only). What is asserted is what the operator
measured: the frames it decoded, their SSIM against the frames that were sent, their rates and
the bytes that arrived in every 1-s window.
"""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any

import pytest

pytest.importorskip("simplejpeg")

pytestmark = [pytest.mark.integration, pytest.mark.alone]
"""Alone: eight processes encoding, decoding and scoring JPEG at 16 Hz on 1.5-s steps; beside the
ROS 2 demo in CI's parallel phase, both missed their rates (R1 under 10 Hz in a step, Table 2's
rates beyond 5 %)."""

MIN_SSIM = 0.9
"""The quality floor the demo's cameras declare, and what each robot's SSIM averages at least
over the run (../shared/QUALITY.md: 320x240 q50 is 0.83, visibly degraded)."""
PROBE_STALENESS_SSIM = 0.09
"""How far below the floor one step's delivered SSIM may sit. The floor holds on the ladder as
last probed (every 5 s, ``dbml.runtime.camera``) while the scene moves on: over R2's pan at the
demo's speed (160x120), q50's SSIM fell from 0.957 as probed to 0.876 before the next probe
(0.081), and the JPEG's size hardly moved (no sign to probe sooner). A CI run delivered 0.883 at
a rung its ladder put above 0.9."""


def test_the_ladder_keeps_every_camera_at_10_hz_within_the_budget_on_real_frames() -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "dbml",
            "demo",
            "teleop",
            "--frames",
            "photos",
            "--step-seconds",
            "1.5",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert result.returncode in {0, 1}, result.stderr[-3000:]  # 1: a check missed, said below
    document = json.loads(result.stdout)
    checks = document["checks"]
    ladder, rate_only = document["ladder"], document["rate_only"]
    why = _steps(ladder)
    assert checks["complete"] is True, why
    assert checks["every_robot_at_10_hz"] is True, why
    assert checks["prioritised_at_maximum"] is True, why
    assert checks["within_budget"] is True, ladder["worst_window_bytes"]
    assert [s["step"] for s in ladder["steps"]] == list(range(1, 11))
    for step in ladder["steps"]:
        for robot in step["robots"]:
            assert robot["encoding"] is not None  # a rung was pushed and acknowledged
            assert robot["ssim"] is not None
            assert robot["ssim"] >= MIN_SSIM - PROBE_STALENESS_SSIM, why
    for k in range(len(ladder["steps"][0]["robots"])):
        scores = [step["robots"][k]["ssim"] for step in ladder["steps"]]
        assert sum(scores) / len(scores) >= MIN_SSIM, why
    for step in rate_only["steps"]:
        for robot in step["robots"]:
            assert robot["encoding"] is None  # no ladder: the optimizer pushed no rung
    # The same frames: rate only must give up frames where the ladder gives up detail.
    assert ladder["utility"] > rate_only["utility"]
    assert document["utility_gain"] == pytest.approx(ladder["utility"] / rate_only["utility"] - 1)
    # The ceiling: every camera at 16 Hz with SSIM 1; neither run can exceed it.
    weights = sum(r["weight"] for s in ladder["steps"] for r in s["robots"])
    assert document["utility_ceiling"] == pytest.approx(weights)
    assert max(ladder["utility"], rate_only["utility"]) <= weights
    assert document["gain_ceiling"] >= document["utility_gain"]
    assert result.returncode == (0 if document["ok"] else 1)


def _steps(run: dict[str, Any]) -> str:
    """Each step's robots as a line: priority, allocated (last, mean), delivered Hz, rung, SSIM."""
    return "\n".join(
        f"step {step['step']}: "
        + "; ".join(
            f"{r['robot']} p={r['priority']:.2f} {r['allocated_hz']:.2f}"
            f" (mean {r['allocated_mean_hz']})/{r['delivered_fps']:.2f} Hz"
            f"{'' if r['at_10_hz'] else ' NOT at 10 Hz'} {r['encoding']} ssim={r['ssim']}"
            for r in step["robots"]
        )
        for step in run["steps"]
    )
