"""The quality allocation's solver: its time and its gap to scipy's exact MILP, at 2-320 channels.

Random fleets of cameras, each with the JPEG ladder of a real 640x480 photograph (sizes scaled
0.5-1.5 per camera, ../shared/QUALITY.md's table), random priorities and preferences, a budget
between what the floors need on the cheapest rungs and three times that. For each size:

- ``solver_ms``: ``allocate_quality`` end to end, ladders to rungs and rates (median and
  minimum of ``--repeat``);
- ``gap_to_milp``: 1 - its utility / ``scipy.optimize.milp`` (HiGHS) over every allowed rung at
  ``--grid`` rates from floor to maximum (negative: the continuous rate beat the grid);
- ``gap_to_bound``: 1 - its utility / its own Lagrangian dual bound.

    python bench/quality.py [--channels 2 20 80 320] [--repeat 20] [--grid 17] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from typing import Any

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import coo_array

from dbml.core.ladder import Ladder, Preference, Rung
from dbml.core.priority import normalize_priorities
from dbml.core.quality import PREFERENCE_TERMS, WEIGHT_BASE, allocate_quality
from dbml.core.spec import ChannelSpec, Problem

PHOTO = (
    (1.0, 10, 15_871, 0.835), (1.0, 30, 30_488, 0.925), (1.0, 50, 41_227, 0.950),
    (1.0, 70, 55_379, 0.966), (1.0, 80, 68_925, 0.976), (1.0, 90, 100_519, 0.987),
    (1.0, 95, 142_770, 0.993), (0.5, 50, 13_557, 0.834), (0.5, 80, 22_543, 0.871),
    (0.5, 95, 45_121, 0.893), (0.25, 50, 4_495, 0.647), (0.25, 80, 7_205, 0.694),
    (0.25, 95, 13_716, 0.719),
)  # fmt: skip
"""A 640x480 photograph's JPEG ladder: (scale, JPEG quality, bytes, SSIM), measured with
libjpeg-turbo (../shared/QUALITY.md)."""
PAPER_SIZE_BYTES = 84_000
"""The paper's R1 frame: each camera's declared size is this, scaled."""
MILP_TIME_LIMIT_S = 120.0


def fleet(rng: np.random.Generator, n: int) -> tuple[Problem, dict[str, Ladder]]:
    """``n`` cameras with the photograph's ladder, random priorities and preferences."""
    channels, ladders = [], {}
    for i in range(n):
        scale = float(rng.uniform(0.5, 1.5))
        topic = f"/r{i}/camera"
        priority = float(rng.uniform(0, 1)) if rng.uniform() < 0.3 else 0.0
        channels.append(ChannelSpec(topic, 1.0, 16.0, PAPER_SIZE_BYTES * scale, priority))
        ladders[topic] = Ladder(
            tuple(Rung(b * scale, q, scale=s, jpeg_quality=j) for s, j, b, q in PHOTO),
            preference=Preference(rng.choice(list(Preference))),
        )
    probe = Problem(tuple(channels), 1.0)
    floors = _floors(probe)
    need = sum(f * min(lad.choice_sizes) for f, lad in zip(floors, ladders.values(), strict=True))
    bandwidth = need * float(rng.uniform(1.05, 3.0)) * 8 / 1e6
    return Problem(tuple(channels), bandwidth), ladders


def _floors(problem: Problem) -> np.ndarray:
    a = problem.arrays
    return (a.max_rate_hz - a.min_rate_hz) * normalize_priorities(
        a.priority, a.size_bytes
    ) + a.min_rate_hz


def _value(problem: Problem, ladder: Ladder, i: int, rung: Rung, rate: float) -> float:
    """The documented utility of one channel (dbml.core.quality's docstring)."""
    a = problem.arrays
    weight = WEIGHT_BASE + normalize_priorities(a.priority, a.size_bytes)[i]
    gamma, knee = PREFERENCE_TERMS[ladder.preference]
    fmax = float(a.max_rate_hz[i])
    k = fmax if knee is None else knee
    return float(weight * rung.quality**gamma * math.log1p(rate / k) / math.log1p(fmax / k))


def milp_optimum(problem: Problem, ladders: dict[str, Ladder], grid: int) -> tuple[float, str]:
    """HiGHS's MILP over every allowed rung at ``grid`` rates: its utility and its status."""
    floors = _floors(problem)
    costs: list[float] = []
    values: list[float] = []
    owners: list[int] = []
    for i, topic in enumerate(problem.topics):
        ladder = ladders[topic]
        for rung in (r for r in ladder.rungs if r.quality >= ladder.min_quality):
            for rate in np.linspace(floors[i], problem.arrays.max_rate_hz[i], grid):
                costs.append(float(rate) * rung.size_bytes)
                values.append(_value(problem, ladder, i, rung, float(rate)))
                owners.append(i)
    k, n = len(costs), len(problem.topics)
    result = milp(
        -np.array(values),
        integrality=np.ones(k, dtype=np.int64),
        bounds=Bounds(0, 1),
        constraints=[
            LinearConstraint(coo_array((np.ones(k), (owners, np.arange(k))), shape=(n, k)), 1, 1),
            LinearConstraint(np.array([costs]), -np.inf, problem.budget_bytes_per_s),
        ],
        options={"time_limit": MILP_TIME_LIMIT_S},
    )
    if result.fun is None:
        raise RuntimeError(f"milp found no solution: {result.message}")
    return float(-result.fun), str(result.message)


def measure(n: int, repeat: int, grid: int, seed: int) -> dict[str, Any]:
    problem, ladders = fleet(np.random.default_rng(seed), n)
    solve_ms = []
    for _ in range(repeat):
        started = time.perf_counter()
        allocation = allocate_quality(problem, ladders)
        solve_ms.append((time.perf_counter() - started) * 1e3)
    started = time.perf_counter()
    reference, status = milp_optimum(problem, ladders, grid)
    milp_s = time.perf_counter() - started
    assert allocation.upper_bound is not None
    return {
        "channels": n,
        "status": allocation.status.value,
        "solver_ms_median": round(statistics.median(solve_ms), 3),
        "solver_ms_min": round(min(solve_ms), 3),
        "utility": round(allocation.utility, 6),
        "milp_utility": round(reference, 6),
        "milp_s": round(milp_s, 2),
        "milp_status": status,
        "gap_to_milp": round(1 - allocation.utility / reference, 6),
        "gap_to_bound": round(1 - allocation.utility / allocation.upper_bound, 6),
        "budget_used": round(allocation.total_bytes_per_s / problem.budget_bytes_per_s, 6),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", type=int, nargs="+", default=[2, 20, 80, 320])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--grid", type=int, default=17, help="MILP rates per rung")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", action="store_true", help="JSON only")
    args = parser.parse_args()
    results = [measure(n, args.repeat, args.grid, args.seed) for n in args.channels]
    document = {
        "benchmark": "quality_solver",
        "reference": "scipy.optimize.milp (HiGHS) over every allowed rung at a grid of rates",
        "results": results,
    }
    if not args.json:
        for row in results:
            print(
                f"{row['channels']:>4} channels: {row['solver_ms_median']:.3f} ms, gap to milp "
                f"{row['gap_to_milp']:+.2e}, to bound {row['gap_to_bound']:.2e}"
            )
    print(json.dumps(document))


if __name__ == "__main__":
    main()
