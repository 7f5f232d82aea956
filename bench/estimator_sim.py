"""Every estimator design on recorded capacity traces, in simulation: a design tool, seconds a run.

The testbed's matrix (``bench/estimator_traces.py``) takes 41 minutes; this runs the same
designs closed loop in ``dbml.estimator.simulation`` (the paper's two cameras sharing the
estimate 80/20, one FIFO whose rate follows the trace, each frame's transmission the trace's
capacity integrated over its time on the wire, so a fade holds what is in flight), against an
oracle in the same model whose estimate is the trace's capacity at each tick (less headers,
within the configured budget). Per design and trace: the payload delivered over what the oracle
delivered, from 2 s on, and p95 frame latency. What a simulation leaves out (TCP's
retransmission after a loss, the shaper's queue limit, the processes' own delays) is what the
testbed's runs add; a design is judged there, not here.

    .venv/bin/python bench/estimator_sim.py --gym DIR [--designs queue ...] [--traces NAME ...]
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dbml.estimator import BandwidthEstimator, Design, EstimatorSettings, settings_of
from dbml.estimator.base import Estimate, Phase
from dbml.estimator.simulation import FRAMES, WIRE_EFFICIENCY, Trace, simulate, transmission_over
from dbml.scenarios.traces import LinkTrace, load_trace

CAP_MBIT = 11.0 * 0.92
"""The configured budget of the testbed's 11-Mbit/s link: the most any estimate may set."""
SETTLE_S = 2.0
GYM_TRACES = ("4G_3mbps", "5G_12mbps", "5G_13mbps", "4G_500kbps", "4G_700kbps")
TICK_S = 0.1
REPORT_LAG_S = 0.075


class Oracle:
    """An estimate that is the trace's capacity at each tick, less headers, within the cap."""

    def __init__(self, trace: LinkTrace) -> None:
        self._trace = trace
        self.estimate_mbit = min(CAP_MBIT, (trace.first_up_mbit or 0.0) * WIRE_EFFICIENCY)

    def observe(self, _arrival: object) -> float:
        return 0.0

    def update(self, now_s: float) -> Estimate:
        self.estimate_mbit = max(min(CAP_MBIT, self._trace.mbit_at(now_s) * WIRE_EFFICIENCY), 0.01)
        return Estimate(now_s, self.estimate_mbit, Phase.HOLD, 0.0, 0.0, 0.0, 0)


def judge(run: Trace, start_s: float, end_s: float) -> dict[str, float]:
    """The payload (Mbit) that arrived in ``[start_s, end_s)`` and its frames' p95 delay."""
    size = {name: s for name, s, *_ in FRAMES}
    kept = [(d, size[name]) for t, d, name in run.delays if start_s <= t < end_s]
    delays = sorted(d for d, _ in kept)
    return {
        "payload_mbit": sum(n for _, n in kept) * 8e-6,
        "p95_ms": 1e3 * delays[int(0.95 * (len(delays) - 1))] if delays else float("nan"),
    }


def run_one(trace: LinkTrace, design: str | None) -> dict[str, float]:
    """One closed-loop run of ``design`` (None: the oracle) over ``trace``."""
    estimator: Any
    if design is None:
        estimator = Oracle(trace)
    else:
        settings = EstimatorSettings(detector=settings_of(Design(design)))
        estimator = BandwidthEstimator(max_mbit=CAP_MBIT, initial_mbit=CAP_MBIT, settings=settings)
    run = simulate(
        estimator,
        trace.mbit_at,
        duration_s=trace.duration_s,
        tick_s=TICK_S,
        report_lag_s=REPORT_LAG_S,
        transmit_until=transmission_over(trace.schedule),
    )
    return judge(run, SETTLE_S, trace.duration_s)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gym", type=Path, required=True, help="alphartc_gym/tests/data")
    parser.add_argument("--designs", nargs="+", default=[d.value for d in Design])
    parser.add_argument("--traces", nargs="+", default=list(GYM_TRACES))
    args = parser.parse_args(argv)
    rows = []
    for name in args.traces:
        trace = load_trace(args.gym / f"{name}.json")
        oracle = run_one(trace, None)
        for design in args.designs:
            got = run_one(trace, design)
            rows.append(
                {
                    "trace": name,
                    "design": design,
                    "of_oracle": round(got["payload_mbit"] / oracle["payload_mbit"], 3),
                    "p95_ms": round(got["p95_ms"]),
                    "oracle_p95_ms": round(oracle["p95_ms"]),
                }
            )
    by_design = {
        d: round(statistics.fmean(r["of_oracle"] for r in rows if r["design"] == d), 3)
        for d in args.designs
    }
    print(json.dumps({"benchmark": "estimator_sim", "rows": rows, "mean_of_oracle": by_design}))


if __name__ == "__main__":
    main()
