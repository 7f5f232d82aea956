"""Every estimator design on every link case, on the testbed (root), against an oracle.

Each case is one real ``dbml testbed teleop --estimate`` run per design (``--estimator-design``),
the paper's two cameras over a link that follows:

- ``steady``: 11 Mbit/s for 60 s (no cut is the target);
- ``drop``: 11 -> 5 -> 11 Mbit/s at 20 and 40 s;
- ``rate-drop``: ``tests/testbed/test_teleop.py -k rate_drop``'s link, 11 -> 5 Mbit/s at 8 s, for
  20 s;
- ``outage``: 11 Mbit/s, down for 1 s at 10 s, 10 s at 25 s and 30 s at 50 s, for 100 s;
- ``rfc8867-5.1``: RFC 8867's test case 5.1 (1 -> 2.5 -> 0.6 -> 1 Mbit/s at 0/40/60/80 s),
  its 2.5-Mbit/s peak as 11 Mbit/s: 4.4 -> 11 -> 2.64 -> 4.4 for 100 s;
- with ``--gym DIR`` (a checkout of OpenNetLab/gym: ``alphartc_gym/tests/data``, no licence,
  so not in this repository), its recorded 4G and 5G uplinks as they are (200-ms steps), or any
  ``NAME.txt`` there as a ``SECONDS:MBIT`` trace (``--gym bench/traces --cases lte_a lte_b``:
  two cellular-like schedules of 1-s steps written for this bench, not recordings).

Per design and case, from what the operator received: utilisation (payload delivered / what the
link could carry as payload, ``WIRE_EFFICIENCY`` of its capacity, from 2 s on), the same as a
fraction of the oracle's (``dbml.experiment.oracle``: the allocation on a perfect estimate,
through the same capacity), p50/p95/p99 frame latency, frames lost, the share of
time the budget stood above the capacity (while the link was up), and where the case has them,
the first cut after each fall, the time to 90 % after each rise, the goodput from 3 s and the
p95 from 2 s after a fall (and from which 1-s window on each is good, the rate-drop test's
``recovery_s``), the outages' recoveries and the steady link's lowest budget. Beside the
oracle, per recorded trace, the same cameras through the same FIFO on fixed budgets of 30-100 %
of its mean capacity (``fixed_budget``, ``best_fixed``): what each share of the link costs in
latency to a design that cannot foresee a fade. One
JSON object on stdout; ``--trace DIR`` also writes each run's arrivals and the operator's ticks
(with the estimator's phase and reason) as JSON lines (``bench/arrivals.py``).

    sudo .venv/bin/python bench/estimator_traces.py [--gym DIR] [--designs queue ...]
                                                   [--cases steady drop ...] [--runs N]
                                                   [--trace DIR]

A run takes its case's length and about 15 s of set-up: the whole matrix (nine cases, three
designs, one run each) took 41 minutes, before ``rate-drop`` (20 s a run) was added.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from arrivals import write_arrivals
from dbml.core.spec import BYTES_PER_S_PER_MBIT
from dbml.estimator.designs import DEFAULT_DESIGN, Design
from dbml.estimator.simulation import WIRE_EFFICIENCY
from dbml.experiment.oracle import OracleRun, simulate_fixed_budget, simulate_oracle
from dbml.experiment.runner import Snapshot
from dbml.scenarios.traces import LinkTrace, load_trace, parse_plain_trace
from dbml.testbed.options import DEFAULT_UTILIZATION
from dbml.testbed.runner import TestbedOptions, TestbedResult, run_teleop_testbed

LINK_MBIT = 11.0
MAX_BUDGET_MBIT = LINK_MBIT * DEFAULT_UTILIZATION
"""The configured budget: the most any estimate may set."""
SETTLE_S = 2.0
"""Figures from this long after the start (the first allocation and the first frames)."""
GYM_TRACES = ("4G_3mbps", "5G_12mbps", "5G_13mbps", "4G_500kbps", "4G_700kbps")
TARGET_OF_ORACLE = 0.8
TARGET_TRACE_P95_MS = 300.0
TARGET_FIRST_CUT_S = 0.3
TARGET_RISE_90_S = 5.0
TARGET_DROP_P95_MS = 250.0
TARGET_GOODPUT = 0.85
TARGET_OUTAGE_BACK_S = 3.0
TARGET_OUTAGE_BUDGET_S = 10.0
TARGET_STEADY_LOW_SHARE = 0.9
FIXED_SHARES = tuple(round(0.3 + 0.05 * k, 2) for k in range(15))
"""Fixed budgets, as shares of a trace's mean payload capacity: the latency each share of the
link costs on it, for a design that cannot foresee it (``fixed_budget``)."""


@dataclass(frozen=True, slots=True)
class Case:
    """A link to run on: a schedule (judged change by change) or a recorded trace."""

    name: str
    trace: LinkTrace
    schedule: str | None
    """``--link-schedule``'s text; None: ``--link-trace`` (a file)."""
    path: Path | None = None


def _schedule_case(name: str, schedule: str, duration_s: float) -> Case:
    trace = replace(parse_plain_trace(schedule, name=name), duration_s=duration_s)
    return Case(name, trace, schedule)


BUILT_IN = {
    "steady": _schedule_case("steady", "0:11", 60.0),
    "drop": _schedule_case("drop", "0:11,20:5,40:11", 60.0),
    "rate-drop": _schedule_case("rate-drop", "0:11,8:5", 20.0),
    "outage": _schedule_case("outage", "0:11,10:0,11:11,25:0,35:11,50:0,80:11", 100.0),
    "rfc8867-5.1": _schedule_case("rfc8867-5.1", "0:4.4,40:11,60:2.64,80:4.4", 100.0),
}


class _Recorder:
    """Keeps the operator's newest snapshot (the runner's ``observe``)."""

    def __init__(self) -> None:
        self.snapshot: Snapshot | None = None

    def __call__(self, snapshot: Snapshot) -> None:
        self.snapshot = snapshot


def case_options(case: Case, design: Design = DEFAULT_DESIGN) -> TestbedOptions:
    """The testbed's options for ``case`` with ``design``."""
    return TestbedOptions.from_flags(
        policy="dbml",
        estimate=True,
        estimator_design=design.value,
        link_mbit=LINK_MBIT,
        link_schedule=case.schedule,
        link_trace=None if case.path is None else str(case.path),
        step_seconds=case.trace.duration_s / 10,
    )


def run_case(
    case: Case, design: Design, *, trace: Path | None = None
) -> tuple[TestbedResult, Snapshot | None]:
    """One testbed run of ``case`` with ``design``; its result and the operator's records."""
    options = case_options(case, design)
    recorder = _Recorder()
    result = run_teleop_testbed(options, observe=recorder)
    if trace is not None and recorder.snapshot is not None:
        head = {"case": case.name, "design": design.value, "schedule": case.trace.schedule}
        write_arrivals(trace, f"{case.name}-{design.value}", head, recorder.snapshot)
    return result, recorder.snapshot


def figures(case: Case, result: TestbedResult, snapshot: Snapshot | None) -> dict[str, Any]:
    """The run's figures (module docstring); None where it has none."""
    if snapshot is None:
        return {"interrupted": True}
    t0, end_s = snapshot.t0, case.trace.duration_s
    frames = [
        a
        for a in snapshot.arrivals
        if a.sent_s is not None and SETTLE_S <= a.arrival_s - t0 <= end_s
    ]
    delivered = sum(a.size_bytes for a in frames)
    capacity = case.trace.megabits(SETTLE_S, end_s) * WIRE_EFFICIENCY * BYTES_PER_S_PER_MBIT
    latency = np.array([(a.arrival_s - a.sent_s) * 1e3 for a in frames if a.sent_s is not None])
    ticks = [t for t in snapshot.ticks if SETTLE_S <= t.t_s - t0 <= end_s and t.budget_mbit]
    above = [  # while the link is up: down, the estimator keeps its budget on purpose
        t.budget_mbit > case.trace.mbit_at(t.t_s - t0) * WIRE_EFFICIENCY
        for t in ticks
        if t.budget_mbit is not None and case.trace.mbit_at(t.t_s - t0) > 0
    ]
    out: dict[str, Any] = {
        "utilisation": delivered / capacity if capacity > 0 else None,
        "latency_p50_ms": _pct(latency, 50),
        "latency_p95_ms": _pct(latency, 95),
        "latency_p99_ms": _pct(latency, 99),
        "frames": len(frames),
        "lost": _lost(snapshot),
        "budget_above_capacity_share": sum(above) / len(above) if above else None,
        "link_timing": None
        if result.link_timing is None
        else {
            "changes": result.link_timing.changes,
            "call_ms_p50": result.link_timing.call_ms_p50,
            "late_ms_max": result.link_timing.late_ms_max,
        },
    }
    falls, rises = [], []
    changes = [c.t_s for c in result.changes]
    for k, change in enumerate(result.changes):
        if change.drop and change.to_mbit > 0:  # to 0: an outage, judged by its recovery
            until = changes[k + 1] if k + 1 < len(changes) else end_s
            later = np.array(
                [
                    (a.arrival_s - a.sent_s) * 1e3
                    for a in frames
                    if a.sent_s is not None and change.t_s + 2.0 <= a.sent_s - t0 < until
                ]
            )
            falls.append(
                {
                    "t_s": change.t_s,
                    "to_mbit": change.to_mbit,
                    "first_cut_s": change.first_cut_s,
                    "goodput_share_after": change.goodput_share_after,
                    "peak_p95_ms": change.max_latency_p95_ms,
                    # the rate-drop test's: from which 1-s window on each is good (p95, loss)
                    "recovery_s": change.recovery_s,
                    "p95_from_2s_ms": _pct(later, 95),
                }
            )
        elif not change.drop:
            rises.append(
                {
                    "t_s": change.t_s,
                    "to_mbit": change.to_mbit,
                    "rise_90_s": change.budget_recovery_s,
                }
            )
    if falls or rises:
        out |= {"falls": falls, "rises": rises}
    if result.recoveries:
        out["outages"] = [
            {"robot": r.robot, "back_s": r.back_s, "recovery_s": r.recovery_s}
            for r in result.recoveries
        ]
    if case.name == "steady":
        budgets = [t.budget_mbit for t in ticks if t.budget_mbit is not None]
        if budgets:
            steady = statistics.median(budgets)
            out["steady_budget_mbit"] = steady
            out["lowest_share_of_steady"] = min(budgets) / steady
    return out


def oracle(case: Case) -> dict[str, Any]:
    """What a perfect estimate reaches on ``case``'s capacity (``dbml.experiment.oracle``).

    Beside it, for a recorded trace, the same through fixed budgets (``FIXED_SHARES`` of its
    mean payload capacity): a design without foresight sends into a fade what the oracle does
    not, so the share of the link it reaches within a latency is bounded by these (``best_fixed``:
    the most of the oracle's utilisation with p95 within the trace's target; None if no
    budget's p95 is).
    """
    started = time.perf_counter()
    step_s = case.trace.duration_s / 10
    run = simulate_oracle(case.trace, step_s=step_s, max_budget_mbit=MAX_BUDGET_MBIT)
    best = _utilisation(run)
    out: dict[str, Any] = {
        "utilisation": best,
        "latency_p50_ms": run.latency_p50_ms,
        "latency_p95_ms": run.latency_p95_ms,
        "latency_p99_ms": run.latency_p99_ms,
        "frames_lost": run.frames_lost,
    }
    if case.schedule is None and best:
        mean = case.trace.megabits(0, case.trace.duration_s) / case.trace.duration_s
        fixed = []
        for share in FIXED_SHARES:
            budget = min(share * mean * WIRE_EFFICIENCY, MAX_BUDGET_MBIT)
            at = simulate_fixed_budget(case.trace, budget_mbit=budget, step_s=step_s)
            used = _utilisation(at)
            fixed.append(
                {
                    "share_of_capacity": share,
                    "budget_mbit": round(budget, 3),
                    "of_oracle": None if used is None else round(used / best, 3),
                    "latency_p95_ms": at.latency_p95_ms,
                    "frames_lost": at.frames_lost,
                }
            )
        out["fixed_budget"] = fixed
        within = [
            f["of_oracle"]
            for f in fixed
            if f["of_oracle"] is not None
            and f["latency_p95_ms"] is not None
            and f["latency_p95_ms"] <= TARGET_TRACE_P95_MS
        ]
        out["best_fixed"] = max(within, default=None)
    out["simulated_s"] = round(time.perf_counter() - started, 3)
    return out


def _utilisation(run: OracleRun) -> float | None:
    """Goodput over payload capacity from ``SETTLE_S`` on, as the designs are judged."""
    later = [w for w in run.windows if w.t_s >= SETTLE_S]
    capacity = sum(w.capacity_mbit for w in later)
    return sum(w.goodput_mbit for w in later) / capacity if capacity > 0 else None


def _pct(values: np.ndarray, q: float) -> float | None:
    return None if values.size == 0 else float(np.percentile(values, q))


def _lost(snapshot: Snapshot) -> int:
    """Sequence gaps per stream, from 2 s on."""
    last: dict[int, int] = {}
    lost = 0
    for a in sorted(snapshot.arrivals, key=lambda a: a.arrival_s):
        if a.seq is None:
            continue
        before = last.get(a.robot)
        if before is not None and a.seq > before + 1 and a.arrival_s - snapshot.t0 >= SETTLE_S:
            lost += a.seq - before - 1
        last[a.robot] = max(a.seq, before or a.seq)
    return lost


def verdict(case: Case, run: dict[str, Any], reference: dict[str, Any]) -> dict[str, bool]:
    """The issue's targets that apply to ``case``."""
    checks: dict[str, bool] = {}
    if case.schedule is None:
        share = run.get("utilisation")
        best = reference.get("utilisation")
        checks["utilisation_80pct_of_oracle"] = bool(
            share and best and share >= TARGET_OF_ORACLE * best
        )
        p95 = run.get("latency_p95_ms")
        checks["p95_at_most_300ms"] = p95 is not None and p95 <= TARGET_TRACE_P95_MS
        checks["nothing_lost"] = run.get("lost") == 0
    for fall in run.get("falls", ()):
        at = f"{fall['t_s']:g}s"
        cut, share, p95 = fall["first_cut_s"], fall["goodput_share_after"], fall["p95_from_2s_ms"]
        checks[f"first_cut_300ms_at_{at}"] = cut is not None and cut <= TARGET_FIRST_CUT_S
        checks[f"goodput_85pct_from_3s_at_{at}"] = share is not None and share >= TARGET_GOODPUT
        checks[f"p95_250ms_from_2s_at_{at}"] = p95 is not None and p95 <= TARGET_DROP_P95_MS
    back_s = TARGET_OUTAGE_BUDGET_S if case.name == "outage" else TARGET_RISE_90_S
    for rise in run.get("rises", ()):
        reached = rise["rise_90_s"]
        checks[f"budget_90_within_{back_s:g}s_at_{rise['t_s']:g}s"] = (
            reached is not None and reached <= back_s
        )
    for outage in run.get("outages", ()):
        took = outage["recovery_s"]
        checks[f"{outage['robot']}_back_within_3s_at_{outage['back_s']:g}s"] = (
            took is not None and took <= TARGET_OUTAGE_BACK_S
        )
    if case.name == "steady":
        low = run.get("lowest_share_of_steady")
        checks["no_false_cut"] = low is not None and low >= TARGET_STEADY_LOW_SHARE
    return checks


def cases(names: Sequence[str], gym: Path | None) -> list[Case]:
    """The cases asked for: built-in schedules by name, the gym's traces if ``gym`` is given."""
    found = [BUILT_IN[n] for n in names if n in BUILT_IN]
    for name in names:
        if name in BUILT_IN:
            continue
        if gym is None:
            print(f"skipped {name}: no --gym", file=sys.stderr)
            continue
        path = gym / f"{name}.json"
        if not path.exists():
            path = gym / f"{name}.txt"  # a plain SECONDS:MBIT trace (bench/traces/lte_a.txt)
        trace = load_trace(path)
        found.append(Case(name, trace, None, path))
    return found


def main(argv: list[str] | None = None) -> int:
    """Run the matrix and print the JSON report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gym", type=Path, help="OpenNetLab/gym's alphartc_gym/tests/data")
    parser.add_argument(
        "--designs", nargs="+", choices=[d.value for d in Design], default=[d.value for d in Design]
    )
    parser.add_argument("--cases", nargs="+", default=[*BUILT_IN, *GYM_TRACES])
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--trace", type=Path, help="write each run's arrivals here (JSON lines)")
    parser.add_argument("--oracle-only", action="store_true", help="no testbed: the oracle alone")
    args = parser.parse_args(argv)
    report: dict[str, Any] = {
        "benchmark": "estimator_traces",
        "reference": "the oracle: the allocation on a perfect estimate through the same capacity",
        "default_design": DEFAULT_DESIGN.value,
        "link_mbit": LINK_MBIT,
        "max_budget_mbit": MAX_BUDGET_MBIT,
        "wire_efficiency": WIRE_EFFICIENCY,
        "cases": {},
    }
    for case in cases(args.cases, args.gym):
        reference = oracle(case)
        entry: dict[str, Any] = {
            "duration_s": case.trace.duration_s,
            "capacity_mean_mbit": case.trace.megabits(0, case.trace.duration_s)
            / case.trace.duration_s,
            "clamped": case.trace.clamped,
            # a recorded radio's queue keeps its bytes through a fade; None: the shaper's 200 ms
            "link_queue_bytes": case_options(case).link_queue_bytes,
            "oracle": reference,
            "designs": {},
        }
        report["cases"][case.name] = entry
        if args.oracle_only:
            continue
        for design in (Design(d) for d in args.designs):
            runs = []
            for _ in range(args.runs):
                result, snapshot = run_case(case, design, trace=args.trace)
                run = figures(case, result, snapshot)
                best = reference["utilisation"]
                if run.get("utilisation") is not None and best:
                    run["of_oracle"] = run["utilisation"] / best
                run["checks"] = verdict(case, run, reference)
                runs.append(run)
                print(json.dumps({case.name: {design.value: run}}), file=sys.stderr)
            entry["designs"][design.value] = runs
    json.dump(report, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
