"""The bandwidth estimator against the congestion-control anchors, on the testbed (root).

Three schedules, each a real ``dbml testbed teleop --estimate`` run: the drop 11 -> 5 -> 11
Mbit/s, RFC 8867's test case 5.1 (variable available capacity, one flow) scaled to the paper's
11 Mbit/s: 4.4 -> 11 -> 2.6 -> 4.4 Mbit/s at 0/40/60/80 s, and (issue 20, item 3) a steady
11 Mbit/s link for 60 s. Prints one JSON object: per link change the time to the first budget
cut, peak p95, goodput share from 3 s on and the time to 90 % after a rise; per phase
utilisation, p95 and losses; on the steady link the estimate's steady value against the link's
payload capacity and its lowest point after it settled; each judged against the targets by
name. ``--runs N`` repeats each schedule and adds a min/median/max summary of every target;
``--trace DIR`` writes each run's arrivals (per frame: stream, seq, sent_s, arrival_s,
size_bytes) and the operator's ticks, with the link schedule, as JSON lines for
``bench/estimator_replay.py``. Not a timed test: ``sudo .venv/bin/python
bench/estimator_rmcat.py [--only drop|rmcat|steady] [--runs N] [--trace bench/traces]``
takes about 3 minutes a run of each (set-up included).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from arrivals import write_arrivals
from dbml.experiment.runner import Snapshot
from dbml.testbed.runner import TestbedOptions, TestbedResult, run_teleop_testbed

DROP_SCHEDULE = "0:11,20:5,40:11"
DROP_STEP_S = 6.0
RMCAT_SCHEDULE = "0:4.4,40:11,60:2.6,80:4.4"
"""RFC 8867 section 5.1: 1.0 -> 2.5 -> 0.6 -> 1.0 Mbit/s at 0/40/60/80 s, times 4.4."""
RMCAT_STEP_S = 10.0
"""Ten steps of 10 s: RFC 8867's 100 s."""
STEADY_SCHEDULE = "0:11"
STEADY_STEP_S = 6.0
"""Ten steps of 6 s: issue 20's 60 s of a steady link."""
STEADY_SETTLED_S = 5.0
"""On the steady link the estimate is judged from this long after the start."""
WIRE_EFFICIENCY = 0.957
"""Payload Mbit/s per shaped Mbit/s measured with raw TCP (FACTS.md)."""

GCC_FIRST_CUT_S = 0.1
"""GCC cuts within about one round trip plus 100 ms (round trip here under 1 ms)."""
GCC_BACKOFF = 0.85
"""GCC's decrease: 0.85 times the receive rate."""
RFC8867_MIN_UTILISATION = 0.8
"""A common reading of RFC 8868's criteria: a flow uses at least 80 % of the capacity."""
TARGET_FIRST_CUT_S = 0.3
TARGET_PEAK_P95_MS = 250.0
TARGET_GOODPUT_SHARE = 0.85
TARGET_RISE_90_S = 5.0
TARGET_STEADY_LOW_SHARE = 0.9
"""Item 3: on a steady link no cut below this share of the estimate's steady value."""

SCHEDULES = {
    "drop": (DROP_SCHEDULE, DROP_STEP_S),
    "rmcat": (RMCAT_SCHEDULE, RMCAT_STEP_S),
    "steady": (STEADY_SCHEDULE, STEADY_STEP_S),
}


class _Recorder:
    """Keeps the operator's lists (the runner's ``observe`` sees them grow)."""

    def __init__(self) -> None:
        self.snapshot: Snapshot | None = None

    def __call__(self, snapshot: Snapshot) -> None:
        self.snapshot = snapshot


def _run(schedule: str, step_s: float, trace: Path | None, name: str) -> TestbedResult:
    options = TestbedOptions.from_flags(
        policy="dbml", estimate=True, link_schedule=schedule, step_seconds=step_s
    )
    recorder = _Recorder()
    result = run_teleop_testbed(options, observe=recorder)
    if trace is not None and recorder.snapshot is not None:
        head = {"schedule": schedule, "step_s": step_s, "wire": WIRE_EFFICIENCY}
        write_arrivals(trace, name, head, recorder.snapshot)
    return result


def _report(result: TestbedResult) -> dict[str, Any]:
    changes = []
    for change in result.changes:
        row: dict[str, Any] = {
            "t_s": change.t_s,
            "from_mbit": change.from_mbit,
            "to_mbit": change.to_mbit,
            "goodput_share_after": change.goodput_share_after,
        }
        if change.drop:
            cut, p95 = change.first_cut_s, change.max_latency_p95_ms
            row |= {
                "first_cut_s": cut,
                "first_cut_ok": cut is not None and cut <= TARGET_FIRST_CUT_S,
                "gcc_first_cut_s": GCC_FIRST_CUT_S,
                "peak_p95_ms": p95,
                "peak_p95_ok": p95 is not None and p95 <= TARGET_PEAK_P95_MS,
                "recovery_s": change.recovery_s,
                "lost_after": change.lost_after,
            }
            share = change.goodput_share_after
            row["goodput_share_ok"] = share is not None and share >= TARGET_GOODPUT_SHARE
        else:
            rise = change.budget_recovery_s
            row |= {"rise_90_s": rise, "rise_90_ok": rise is not None and rise <= TARGET_RISE_90_S}
        changes.append(row)
    phases = [
        {
            "start_s": p.start_s,
            "end_s": p.end_s,
            "link_mbit": p.link_mbit,
            "goodput_mbit": p.goodput_mbit,
            "utilisation": p.utilisation,
            "utilisation_ok": p.utilisation >= RFC8867_MIN_UTILISATION,
            "latency_p95_ms": p.latency_p95_ms,
            "latency_p95_ok": p.latency_p95_ms is not None
            and p.latency_p95_ms <= TARGET_PEAK_P95_MS,
            "lost": p.lost,
        }
        for p in result.phases
    ]
    return {"run_id": result.run_id, "changes": changes, "phases": phases}


def _steady(result: TestbedResult) -> dict[str, Any]:
    """Item 3: the estimate's steady value, its lowest point after it settled, the cuts."""
    link = result.options.link_mbit
    values = [
        p.budget_mbit
        for p in result.series
        if p.t_s >= STEADY_SETTLED_S and p.budget_mbit is not None
    ]
    steady = statistics.median(values) if values else None
    low = min(values, default=None)
    share = None if steady is None or low is None else low / steady
    return {
        "steady_estimate_mbit": steady,
        "payload_capacity_mbit": link * WIRE_EFFICIENCY,
        "steady_share_of_payload": None if steady is None else steady / (link * WIRE_EFFICIENCY),
        "lowest_estimate_mbit": low,
        "lowest_share_of_steady": share,
        "no_false_cut_ok": share is not None and share >= TARGET_STEADY_LOW_SHARE,
        "latency_p95_ms": max(
            (p.latency_p95_ms for p in result.phases if p.latency_p95_ms is not None),
            default=None,
        ),
    }


def _figures(kind: str, report: dict[str, Any]) -> dict[str, float | None]:
    """The run's targets by name: the figures the ``--runs`` summary spreads."""
    figures: dict[str, float | None] = {}
    if kind == "steady":
        for key in ("steady_share_of_payload", "lowest_share_of_steady", "latency_p95_ms"):
            figures[key] = report[key]
        return figures
    for change in report["changes"]:
        tag = f"{change['from_mbit']:g}->{change['to_mbit']:g}@{change['t_s']:g}s"
        if "first_cut_s" in change:
            figures[f"{tag} first_cut_s"] = change["first_cut_s"]
            figures[f"{tag} peak_p95_ms"] = change["peak_p95_ms"]
            figures[f"{tag} goodput_share_after"] = change["goodput_share_after"]
        else:
            figures[f"{tag} rise_90_s"] = change["rise_90_s"]
    if kind == "rmcat":
        for phase in report["phases"]:
            tag = f"phase {phase['start_s']:g}-{phase['end_s']:g}s@{phase['link_mbit']:g}"
            figures[f"{tag} utilisation"] = phase["utilisation"]
            figures[f"{tag} latency_p95_ms"] = phase["latency_p95_ms"]
    return figures


def summarise(runs: Sequence[dict[str, float | None]]) -> dict[str, dict[str, Any]]:
    """Per figure: min, median and max over the runs (a run without the figure: missing)."""
    names = list(dict.fromkeys(name for run in runs for name in run))
    summary: dict[str, dict[str, Any]] = {}
    for name in names:
        values = [v for run in runs if (v := run.get(name)) is not None]
        missing = len(runs) - len(values)
        summary[name] = {
            "min": min(values, default=None),
            "median": statistics.median(values) if values else None,
            "max": max(values, default=None),
            "missing": missing,
        }
    return summary


def main(argv: list[str] | None = None) -> int:
    """Run the schedules and print the JSON report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=tuple(SCHEDULES), action="append")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--trace", type=Path, help="write each run's arrivals here (JSON lines)")
    args = parser.parse_args(argv)
    kinds = args.only or ["drop", "rmcat"]
    report: dict[str, Any] = {
        "anchors": {"gcc_first_cut_s": GCC_FIRST_CUT_S, "gcc_backoff": GCC_BACKOFF},
        "targets": {
            "first_cut_s": TARGET_FIRST_CUT_S,
            "peak_p95_ms": TARGET_PEAK_P95_MS,
            "goodput_share_after": TARGET_GOODPUT_SHARE,
            "rise_90_s": TARGET_RISE_90_S,
            "rmcat_utilisation": RFC8867_MIN_UTILISATION,
            "steady_lowest_share": TARGET_STEADY_LOW_SHARE,
        },
    }
    for kind in kinds:
        schedule, step_s = SCHEDULES[kind]
        runs, figures = [], []
        for _ in range(args.runs):
            result = _run(schedule, step_s, args.trace, kind)
            run = _report(result)
            if kind == "steady":
                run |= _steady(result)
            runs.append(run)
            figures.append(_figures(kind, run))
            print(json.dumps({kind: _figures(kind, run)}), file=sys.stderr)
        report[kind] = {"schedule": schedule, "runs": runs, "summary": summarise(figures)}
    json.dump(report, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
