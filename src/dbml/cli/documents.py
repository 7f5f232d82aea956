"""The demo's and the testbed's ``--json`` documents, built from their typed results.

The keys are a contract (scripts and the README read them): change them only with care.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

from dbml.demo.photos import PhotoDemoResult, PhotoRun, photo_steps
from dbml.demo.runner import DemoResult
from dbml.experiment.analysis import LinkChange, SeriesPoint, StepResult, Window
from dbml.scenarios.teleop import LINK_MBIT, ROBOTS
from dbml.testbed.result import TestbedResult

__all__ = ["demo_document", "photo_demo_document", "testbed_document"]


def demo_document(result: DemoResult) -> dict[str, Any]:
    """``dbml demo teleop --json``."""
    steps = [
        {
            "step": step.step.step,
            "robots": [
                {
                    "robot": robot.measured.robot,
                    "topic": robot.topic,
                    "tc_s": None if math.isinf(robot.tc_s) else robot.tc_s,
                    "priority": robot.priority,
                    "allocated_hz": robot.measured.allocated_hz,
                    "measured_hz": robot.measured.delivered_hz or None,  # nothing arrived: null
                    "variant": robot.measured.variant,
                    "within_tolerance": robot.within_tolerance,
                    "table2_hz": robot.table2_hz,
                    "matches_table2": robot.matches_table2,
                }
                for robot in step.robots
            ],
            "total_mbit": step.total_mbit,
            "budget_mbit": LINK_MBIT,
        }
        for step in result.steps
    ]
    return {
        "scenario": "teleop",
        "transport": result.options.transport.name,
        "step_seconds": result.options.step_seconds,
        "budget_mbit": LINK_MBIT,
        "steps": steps,
        "ok": result.ok,
        "interrupted": result.interrupted,
    }


def _photo_run(run: PhotoRun) -> dict[str, Any]:
    return {
        "ladder": run.ladder,
        "utility": run.utility,
        "complete": run.complete,
        "worst_window_bytes": run.wire.worst_bytes,
        "windows_over_share": run.wire.over_share,
        "limit_bytes": run.limit_bytes,
        "within_budget": run.within_budget,
        "steps": [
            {
                "step": step.step.step,
                "utility": step.utility,
                "robots": [
                    {
                        "robot": robot.measured.robot,
                        "topic": robot.topic,
                        "priority": robot.priority,
                        "preference": robot.preference.value,
                        "weight": robot.weight,
                        "allocated_hz": robot.measured.allocated_hz,
                        "allocated_mean_hz": robot.measured.allocated_mean_hz,
                        "delivered_fps": robot.measured.delivered_hz,
                        "at_10_hz": robot.at_least_min_fps,
                        "ssim": robot.measured.ssim,
                        "encoding": robot.measured.encoding,
                        "goodput_mbit": robot.measured.goodput_mbit,
                        "utility": robot.utility,
                    }
                    for robot in step.robots
                ],
            }
            for step in run.steps
        ],
    }


def photo_demo_document(result: PhotoDemoResult) -> dict[str, Any]:
    """``dbml demo teleop --frames photos --json``: both runs, the gain and each check."""
    return {
        "scenario": "teleop",
        "frames": "photos",
        "transport": result.transport.name,
        "step_seconds": result.step_seconds,
        "budget_mbit": LINK_MBIT,
        "ladder": _photo_run(result.ladder),
        "rate_only": None if result.rate_only is None else _photo_run(result.rate_only),
        "utility_gain": result.gain,
        "utility_ceiling": result.ladder.ceiling,
        "gain_ceiling": result.gain_ceiling,
        "checks": result.checks,
        "ok": result.ok,
    }


def _window(window: Window, *, drop: tuple[str, ...]) -> dict[str, Any]:
    return {k: v for k, v in asdict(window).items() if k not in drop}


def _step(
    step: StepResult, *, urgent: str | None = None, expected_hz: tuple[float, ...] = ()
) -> dict[str, Any]:
    robots = [_window(r, drop=("variant",)) for r in step.robots]
    for robot, hz in zip(robots, expected_hz, strict=False):
        robot["expected_hz"] = hz  # a fleet's: ``allocate`` on the step's implied channels
    fleet = {"urgent_robot": urgent} if expected_hz else {}
    return {
        "step": step.step,
        **fleet,
        "robots": robots,
        "goodput_mbit": step.goodput_mbit,
        "budget_mbit": step.budget_mbit,
        "estimate_mbit": step.estimate_mbit,
        "link_mbit": step.link_mbit,
    }


def _point(point: SeriesPoint) -> dict[str, Any]:
    return {
        "t": point.t_s,
        "robots": [_window(r, drop=("variant", "latency_p50_ms")) for r in point.robots],
        "budget_mbit": point.budget_mbit,
        "estimator": point.estimator,
        "goodput_mbit": point.goodput_mbit,
        "link_mbit": point.link_mbit,
    }


def _change(change: LinkChange) -> dict[str, Any]:
    rise = ("budget_recovery_s",)
    drop = ("recovery_s", "max_latency_p95_ms", "lost_after")
    return {k: v for k, v in asdict(change).items() if k not in (rise if change.drop else drop)}


def testbed_document(result: TestbedResult) -> dict[str, Any]:
    """``dbml testbed teleop --json``."""
    options, summary = result.options, result.summary()
    summary_document: dict[str, Any] = {
        "steps": summary.steps,
        "frames": options.frames.value,
        "ladder": options.ladder if options.frames.value == "photos" else None,
        "worst_window_bytes": None if result.wire is None else result.wire.worst_bytes,
        "windows_over_share": None if result.wire is None else result.wire.over_share,
        "limit_bytes": result.limit_bytes,
        "max_rate_error": summary.max_rate_error,
        "latency_p50_ms_max": summary.latency_p50_ms_max,
        "latency_p95_ms_max": summary.latency_p95_ms_max,
        "lost": summary.lost,
        "goodput_mbit_mean": summary.goodput_mbit_mean,
        "goodput_fraction_mean": summary.goodput_fraction_mean,
        "goodput_fraction_min": summary.goodput_fraction_min,
        "changes": [_change(c) for c in result.changes],
    }
    for uplink in summary.uplinks:
        summary_document[f"uplink_{uplink.robot}"] = {
            "capacity_mbit": uplink.capacity_mbit,
            "goodput_mbit_max": uplink.goodput_mbit_max,
        }
    if result.urgent:
        summary_document["urgent_stream"] = {
            u.name: {
                "received": u.received,
                "lost": u.lost,
                "latency_p50_ms": u.latency_p50_ms,
                "latency_p95_ms": u.latency_p95_ms,
                "latency_max_ms": u.latency_max_ms,
            }
            for u in result.urgent
        }
    if result.outages:
        summary_document["outages"] = [
            {
                "start_s": o.start_s,
                "end_s": o.end_s,
                "urgent_robot": o.urgent,
                "first_urgent_s": o.first_urgent_s,
                "first_fresh_urgent_s": o.first_fresh_urgent_s,
                "stale": o.stale,
                "lost": o.lost,
                "worst_window_mbit": o.worst_window_mbit,
                "worst_sent_after_mbit": o.worst_sent_after_mbit,
                "budget_mbit": o.budget_mbit,
                "over_budget_mbit": o.over_budget_mbit,
                "release_over_budget_mbit": o.release_over_budget_mbit,
            }
            for o in result.outages
        ]
    if result.recoveries:
        summary_document["recoveries"] = [
            {
                "robot": r.robot,
                "scope": r.scope,
                "down_s": r.down_s,
                "back_s": r.back_s,
                "recovery_s": r.recovery_s,
                "stuck": r.stuck,
            }
            for r in result.recoveries
        ]
    if result.bridges:
        summary_document["bridges"] = [
            {
                "robot": b.robot,
                "published": b.published,
                "dropped": b.dropped,
                "publish_max_ms": b.max_ms,
                "publish_p99_ms": b.p99_ms,
                "frame_ms": b.frame_ms,
            }
            for b in result.bridges
        ]
    if result.link_timing is not None:
        summary_document["link_timing"] = asdict(result.link_timing)
    if options.frames.value == "photos" and options.robots == len(ROBOTS):
        # judged as the loopback demo is: dbml.core.quality's utility of what arrived
        summary_document["utility"] = sum(s.utility for s in photo_steps(result.steps))
    summary_document["targets"] = dict(summary.targets)
    trace = options.link_trace
    return {
        "policy": options.policy,
        "transport": options.transport.name,
        "strategy": options.strategy,
        "link_mbit": options.link_mbit,
        "link_schedule": [list(entry) for entry in options.link_schedule],
        "link_trace": None
        if trace is None
        else {
            "name": trace.name,
            "duration_s": trace.duration_s,
            "clamped": trace.clamped,
            "queue_bytes": options.link_queue_bytes,
        },
        "uplinks_mbit": dict(options.uplinks_mbit),
        "uplink_schedules": {
            robot: [list(entry) for entry in schedule]
            for robot, schedule in options.robot_schedules.items()
        },
        "estimate": options.estimate,
        "estimator_design": options.estimator_design.value if options.estimate else None,
        "utilization": options.utilization,
        "urgent_stream": options.urgent_stream,
        "step_seconds": options.step_seconds,
        "robots": options.robots,
        "topology": options.topology,
        "run_id": result.run_id,
        "interrupted": result.interrupted,
        "steps": [
            _step(s, urgent=urgent, expected_hz=expected)
            for s, urgent, expected in zip(
                result.steps,
                result.urgent_robots(),
                result.expected_hz or [()] * len(result.steps),
                strict=True,
            )
        ],
        "summary": summary_document,
        "series": [_point(p) for p in result.series],
    }
