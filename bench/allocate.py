"""Allocation speed: dbml's ``paper`` strategy against scipy's HiGHS on the same fleets.

Seeded random fleets of 10 to 100,000 channels; each solver's best of several repetitions; both
must reach the same objective (eq. 5: the bytes/s allocated). HiGHS is skipped above a time limit
and the output says so. Prints JSON with ``--json``, a table otherwise.

    python bench/allocate.py [--json] [--sizes 10,1000] [--highs-limit-s 30]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table
from scipy.optimize import linprog

from dbml import ChannelSpec, Problem, allocate

SIZES = (10, 1_000, 10_000, 100_000)


def fleet(channels: int, seed: int) -> Problem:
    """A feasible fleet: budget halfway between what the floors need and what the maxima need."""
    rng = np.random.default_rng(seed)
    sizes = rng.choice([64, 1_500, 21_000, 84_000, 250_000], channels) * rng.uniform(
        0.5, 1.5, channels
    )
    fmin = rng.uniform(0.5, 5, channels)
    fmax = fmin + rng.uniform(1, 25, channels)
    # a few urgent channels, most idle, as in a fleet where only some robots see something
    priority = np.where(rng.random(channels) < 0.1, rng.random(channels), 0.0)
    weighted = priority * sizes
    floors = fmin + (fmax - fmin) * (weighted / weighted.sum() if weighted.sum() else 0)
    budget = 0.5 * (sizes @ floors + sizes @ fmax)
    specs = tuple(
        ChannelSpec(f"/robot{i}/sensor", float(a), float(b), float(w), float(p))
        for i, (a, b, w, p) in enumerate(zip(fmin, fmax, sizes, priority, strict=True))
    )
    return Problem(specs, bandwidth_mbit=float(budget) / 125_000)


def best_of(run: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    best, result = math.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - start)
    return best * 1e3, result


def measure(channels: int, *, seed: int, highs_limit_s: float) -> dict[str, Any]:
    problem = fleet(channels, seed)
    repeat = 20 if channels <= 10_000 else 7
    dbml_ms, allocation = best_of(lambda: allocate(problem, strategy="paper"), repeat)
    ours = allocation.total_bytes_per_s

    # The same LP for HiGHS, built before the clock: max w.f, w.f <= B, floors <= f <= max.
    arrays = problem.arrays
    w = arrays.size_bytes
    floors = np.asarray(allocation.floor_hz)
    c, a_ub, b_ub = -w, w[None, :], [problem.budget_bytes_per_s]  # noqa: RUF100
    bounds = [(float(lo), float(hi)) for lo, hi in zip(floors, arrays.max_rate_hz, strict=True)]

    def highs() -> Any:
        return linprog(
            c,
            A_ub=a_ub,
            b_ub=b_ub,
            bounds=bounds,
            method="highs",
            options={"time_limit": highs_limit_s},
        )

    entry: dict[str, Any] = {"channels": channels, "dbml_ms": round(dbml_ms, 4)}
    start = time.perf_counter()
    first = highs()
    once_s = time.perf_counter() - start
    if first.status != 0:
        entry.update(
            highs_ms=None,
            speedup=None,
            objective_match=None,
            highs_skipped=f"HiGHS stopped at the {highs_limit_s:g} s time limit ({first.message})",
        )
        return entry
    highs_repeat = max(1, min(repeat, int(highs_limit_s / max(once_s, 1e-6) / 4)))
    highs_ms, result = best_of(highs, highs_repeat)
    highs_ms = min(highs_ms, once_s * 1e3)
    theirs = float(w @ result.x)
    entry.update(
        highs_ms=round(highs_ms, 4),
        speedup=round(highs_ms / dbml_ms, 1),
        objective_match=bool(math.isclose(ours, theirs, rel_tol=1e-7)),
        dbml_objective_bytes_per_s=ours,
        highs_objective_bytes_per_s=theirs,
    )
    return entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument(
        "--sizes", default=",".join(map(str, SIZES)), help="comma-separated fleet sizes"
    )
    parser.add_argument("--highs-limit-s", type=float, default=30.0, help="skip HiGHS beyond this")
    parser.add_argument("--seed", type=int, default=2015)
    args = parser.parse_args()
    results = [
        measure(int(n), seed=args.seed + i, highs_limit_s=args.highs_limit_s)
        for i, n in enumerate(args.sizes.split(","))
    ]
    document = {
        "benchmark": "allocate",
        "reference": "scipy.optimize.linprog(method='highs')",
        "timing": (
            "best of several runs; dbml_ms times allocate(problem, strategy='paper') on a built "
            "Problem (its columns and stable size order are made once with the problem), "
            "highs_ms times linprog on prebuilt c, A_ub, b_ub and bounds"
        ),
        "results": results,
    }
    if args.json:
        print(json.dumps(document))
        return
    table = Table(title="dbml paper strategy vs scipy HiGHS (best of repetitions)")
    for name in ("channels", "dbml ms", "HiGHS ms", "speedup", "same objective"):
        table.add_column(name, justify="right")
    for r in results:
        table.add_row(
            f"{r['channels']:,}",
            f"{r['dbml_ms']:.3f}",
            "skipped" if r["highs_ms"] is None else f"{r['highs_ms']:.1f}",
            "-" if r["speedup"] is None else f"{r['speedup']:,.0f}x",
            "-" if r["objective_match"] is None else str(r["objective_match"]),
        )
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
