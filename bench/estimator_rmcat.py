"""The bandwidth estimator against the congestion-control anchors, on the testbed (root).

Two schedules, each a real ``dbml testbed teleop --estimate`` run: the drop 11 -> 5 -> 11 Mbit/s
and RFC 8867's test case 5.1 (variable available capacity, one flow) scaled to the paper's
11 Mbit/s: 4.4 -> 11 -> 2.6 -> 4.4 Mbit/s at 0/40/60/80 s. Prints one JSON object: per link
change the time to the first budget cut, peak p95, goodput share from 3 s on and the time to
90 % after a rise; per phase utilisation, p95 and losses; each judged against the targets and
beside the GCC anchor. Not a timed test: ``sudo .venv/bin/python bench/estimator_rmcat.py
[--only drop|rmcat]`` takes about 3 minutes (100 s of RMCAT, 60 s of drop, set-up).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from dbml.testbed.runner import TestbedOptions, TestbedResult, run_teleop_testbed

DROP_SCHEDULE = "0:11,20:5,40:11"
DROP_STEP_S = 6.0
RMCAT_SCHEDULE = "0:4.4,40:11,60:2.6,80:4.4"
"""RFC 8867 section 5.1: 1.0 -> 2.5 -> 0.6 -> 1.0 Mbit/s at 0/40/60/80 s, times 4.4."""
RMCAT_STEP_S = 10.0
"""Ten steps of 10 s: RFC 8867's 100 s."""

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


def _run(schedule: str, step_s: float) -> TestbedResult:
    options = TestbedOptions.from_flags(
        policy="dbml", estimate=True, link_schedule=schedule, step_seconds=step_s
    )
    return run_teleop_testbed(options)


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
                "peak_p95_ok": p95 is not None and p95 < TARGET_PEAK_P95_MS,
                "recovery_s": change.recovery_s,
                "lost_after": change.lost_after,
            }
        else:
            rise = change.budget_recovery_s
            row |= {"rise_90_s": rise, "rise_90_ok": rise is not None and rise < TARGET_RISE_90_S}
        share = change.goodput_share_after
        row["goodput_share_ok"] = share is not None and share >= TARGET_GOODPUT_SHARE
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
            "lost": p.lost,
        }
        for p in result.phases
    ]
    return {"run_id": result.run_id, "changes": changes, "phases": phases}


def main(argv: list[str] | None = None) -> int:
    """Run the schedules and print the JSON report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("drop", "rmcat"))
    args = parser.parse_args(argv)
    report: dict[str, Any] = {
        "anchors": {"gcc_first_cut_s": GCC_FIRST_CUT_S, "gcc_backoff": GCC_BACKOFF},
        "targets": {
            "first_cut_s": TARGET_FIRST_CUT_S,
            "peak_p95_ms": TARGET_PEAK_P95_MS,
            "goodput_share_after": TARGET_GOODPUT_SHARE,
            "rise_90_s": TARGET_RISE_90_S,
            "rmcat_utilisation": RFC8867_MIN_UTILISATION,
        },
    }
    if args.only in (None, "drop"):
        report["drop"] = {"schedule": DROP_SCHEDULE} | _report(_run(DROP_SCHEDULE, DROP_STEP_S))
    if args.only in (None, "rmcat"):
        report["rmcat"] = {"schedule": RMCAT_SCHEDULE} | _report(_run(RMCAT_SCHEDULE, RMCAT_STEP_S))
    json.dump(report, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
