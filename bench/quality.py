"""The quality allocation's solver: its time and its gap to scipy's exact MILP, at 2-320 channels.

Random fleets of cameras, each with the JPEG ladder of a real 640x480 photograph (sizes scaled
0.5-1.5 per camera, ../shared/QUALITY.md's table), random priorities and preferences, a budget
between what the floors need on the cheapest rungs and three times that. For each size:

- ``solver_ms``: ``allocate_quality`` end to end, ladders to rungs and rates, on ``--fleets``
  fleets: the median over fleets of each one's median of ``--repeat`` solves, the slowest
  fleet's, and the fastest solve;
- ``warm_ms``: the optimizer's next round on each fleet (one camera's priority drawn again),
  started from the last allocation's price (``price_hint``), as ``dbml optimizer`` does;
  ``warm_utility_differs`` counts the fleets where it found another utility than a cold solve;
- ``gap_to_milp``: on the first fleet, 1 - its utility / ``scipy.optimize.milp`` (HiGHS) over
  every allowed rung at ``--grid`` rates from floor to maximum (negative: the continuous rate
  beat the grid);
- ``gap_to_bound``: the largest over the fleets of 1 - its utility / its own Lagrangian bound;
- ``links``: the same fleets with their cameras dealt to uplinks of four (``--uplinks``: each
  link's capacity 1.05-2.5 times what its floors need on the cheapest rungs), the solve's time
  and its gap to ``milp`` with a row per link (at the sizes up to ``--links-milp-channels``);

- ``encoding``: a 640x480 camera at 16 Hz through ``ManagedCamera``: the CPU of its JPEG path
  per frame and as a share of a core, against the 3 % target; the ladder's probe;
- ``teleop``: ``dbml demo teleop --frames photos`` over zenoh (the ladder, then rate only, on
  the same frames): per step fps, SSIM, rung, utility; the worst 1-s window; the gain.

    python bench/quality.py [--channels 2 20 80 320] [--repeat 20] [--fleets 10] [--grid 17]
                            [--uplinks] [--cpu-seconds 10] [--step-seconds 3] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import coo_array

from dbml.core.ladder import Ladder, Preference, Rung
from dbml.core.priority import normalize_priorities
from dbml.core.quality import PREFERENCE_TERMS, WEIGHT_BASE, QualityAllocation, allocate_quality
from dbml.core.spec import BYTES_PER_S_PER_MBIT, ChannelSpec, LinkSpec, Problem
from dbml.media.jpeg import encode_jpeg
from dbml.protocol.ladders import encoding_label

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
PROBE_NOTE = "5 s (its own thread)"


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
    constraints = [
        LinearConstraint(coo_array((np.ones(k), (owners, np.arange(k))), shape=(n, k)), 1, 1),
        LinearConstraint(np.array([costs]), -np.inf, problem.budget_bytes_per_s),
    ]
    for link in problem.links:  # the link's capacity (times the utilisation) over its channels
        crossing = {problem.topics.index(t) for t in link.topics}
        row = [c if owner in crossing else 0.0 for c, owner in zip(costs, owners, strict=True)]
        cap = link.capacity_mbit * BYTES_PER_S_PER_MBIT * problem.utilization
        constraints.append(LinearConstraint(np.array([row]), -np.inf, cap))
    result = milp(
        -np.array(values),
        integrality=np.ones(k, dtype=np.int64),
        bounds=Bounds(0, 1),
        constraints=constraints,
        options={"time_limit": MILP_TIME_LIMIT_S},
    )
    if result.fun is None:
        raise RuntimeError(f"milp found no solution: {result.message}")
    return float(-result.fun), str(result.message)


def _timed(
    solve: Callable[[], QualityAllocation], repeat: int
) -> tuple[QualityAllocation, list[float]]:
    """``solve`` ``repeat`` times: its last result and each call's milliseconds."""
    times_ms = []
    for _ in range(repeat):
        started = time.perf_counter()
        result = solve()
        times_ms.append((time.perf_counter() - started) * 1e3)
    return result, times_ms


def measure(n: int, repeat: int, grid: int, seed: int, fleets: int) -> dict[str, Any]:
    """The solver on ``fleets`` random fleets of ``n`` cameras; the MILP on the first."""
    per_fleet_ms: list[float] = []
    warm_ms: list[float] = []
    warm_differs = 0
    fastest_ms = math.inf
    worst_gap_to_bound = 0.0
    first: tuple[Problem, dict[str, Ladder], Any] | None = None
    for k in range(fleets):
        problem, ladders = fleet(np.random.default_rng(seed + k), n)
        allocation, solve_ms = _timed(partial(allocate_quality, problem, ladders), repeat)
        per_fleet_ms.append(statistics.median(solve_ms))
        fastest_ms = min(fastest_ms, *solve_ms)
        # The optimizer's next round: one camera's priority moved, the last price the start.
        changed = _one_priority_moved(problem, np.random.default_rng(seed + k + 1))
        cold = allocate_quality(changed, ladders)
        hint = allocation.price_per_byte
        warm, solve_ms = _timed(
            partial(allocate_quality, changed, ladders, price_hint=hint), repeat
        )
        warm_ms.append(statistics.median(solve_ms))
        warm_differs += abs(warm.utility - cold.utility) > 1e-9 * abs(cold.utility)
        assert allocation.upper_bound is not None
        gap_to_bound = 1 - allocation.utility / allocation.upper_bound
        worst_gap_to_bound = max(worst_gap_to_bound, gap_to_bound)
        if first is None:
            first = (problem, ladders, allocation)
    assert first is not None
    problem, ladders, allocation = first
    started = time.perf_counter()
    reference, status = milp_optimum(problem, ladders, grid)
    milp_s = time.perf_counter() - started
    return {
        "channels": n,
        "fleets": fleets,
        "status": allocation.status.value,
        "solver_ms_median": round(statistics.median(per_fleet_ms), 3),
        "solver_ms_worst_fleet": round(max(per_fleet_ms), 3),
        "solver_ms_min": round(fastest_ms, 3),
        "warm_ms_median": round(statistics.median(warm_ms), 3),
        "warm_ms_worst_fleet": round(max(warm_ms), 3),
        "warm_utility_differs": warm_differs,
        "utility": round(allocation.utility, 6),
        "milp_utility": round(reference, 6),
        "milp_s": round(milp_s, 2),
        "milp_status": status,
        "gap_to_milp": round(1 - allocation.utility / reference, 6),
        "gap_to_bound": round(worst_gap_to_bound, 6),
        "budget_used": round(allocation.total_bytes_per_s / problem.budget_bytes_per_s, 6),
    }


CAMERAS_PER_UPLINK = 4
"""A robot's cameras behind its uplink (``--uplink``), as the fleet bench's robots carry four."""
LINKS_MILP_CHANNELS = 20
"""The MILP with a row per link is solved up to this many cameras (it takes seconds past)."""


def with_uplinks(problem: Problem, ladders: dict[str, Ladder], rng: np.random.Generator) -> Problem:
    """``problem`` with its cameras behind uplinks of ``CAMERAS_PER_UPLINK``.

    Each uplink's capacity is 1.05-2.5 times what its floors need on the cheapest rungs.
    """
    floors = _floors(problem)
    links = []
    for start in range(0, len(problem.topics), CAMERAS_PER_UPLINK):
        topics = problem.topics[start : start + CAMERAS_PER_UPLINK]
        need = sum(floors[problem.topics.index(t)] * min(ladders[t].choice_sizes) for t in topics)
        mbit = need * float(rng.uniform(1.05, 2.5)) / BYTES_PER_S_PER_MBIT
        links.append(LinkSpec(f"uplink{start // CAMERAS_PER_UPLINK}", mbit, tuple(topics)))
    return Problem(problem.channels, problem.bandwidth_mbit, links=tuple(links))


def measure_links(n: int, repeat: int, grid: int, seed: int, fleets: int) -> dict[str, Any]:
    """The solver with an uplink per ``CAMERAS_PER_UPLINK`` cameras; the MILP on the first."""
    per_fleet_ms: list[float] = []
    worst_gap_to_bound = 0.0
    binding: list[float] = []
    first: tuple[Problem, dict[str, Ladder], Any] | None = None
    for k in range(fleets):
        rng = np.random.default_rng(seed + k)
        problem, ladders = fleet(rng, n)
        problem = with_uplinks(problem, ladders, rng)
        allocation, solve_ms = _timed(partial(allocate_quality, problem, ladders), repeat)
        per_fleet_ms.append(statistics.median(solve_ms))
        spent = allocation.bytes_per_s
        binding.append(
            statistics.fmean(
                float(sum(spent[problem.topics.index(t)] for t in link.topics))
                >= link.capacity_mbit * BYTES_PER_S_PER_MBIT * (1 - 1e-6)
                for link in problem.links
            )
        )
        if allocation.upper_bound is not None:
            gap = 1 - allocation.utility / allocation.upper_bound
            worst_gap_to_bound = max(worst_gap_to_bound, gap)
        if first is None:
            first = (problem, ladders, allocation)
    assert first is not None
    problem, ladders, allocation = first
    row: dict[str, Any] = {
        "channels": n,
        "uplinks": len(problem.links),
        "fleets": fleets,
        "status": allocation.status.value,
        "solver_ms_median": round(statistics.median(per_fleet_ms), 3),
        "solver_ms_worst_fleet": round(max(per_fleet_ms), 3),
        "uplinks_at_capacity": round(statistics.fmean(binding), 3),
        "gap_to_bound": round(worst_gap_to_bound, 6),
    }
    if n <= LINKS_MILP_CHANNELS:
        reference, status = milp_optimum(problem, ladders, grid)
        row |= {
            "milp_utility": round(reference, 6),
            "milp_status": status,
            "gap_to_milp": round(1 - allocation.utility / reference, 6),
        }
    return row


def _one_priority_moved(problem: Problem, rng: np.random.Generator) -> Problem:
    """``problem`` with one random channel's priority drawn again (an event)."""
    channels = list(problem.channels)
    i = int(rng.integers(len(channels)))
    c = channels[i]
    channels[i] = ChannelSpec(
        c.topic, c.min_rate_hz, c.max_rate_hz, c.size_bytes, float(rng.uniform(0, 1))
    )
    return Problem(tuple(channels), problem.bandwidth_mbit)


def encoding_cpu(seconds: float) -> dict[str, Any]:
    """A 640x480 camera at 16 Hz through ``ManagedCamera``: the CPU its JPEG path takes.

    - ``path``: the publishing thread's CPU time (``time.thread_time``) over ``seconds`` of
      frames paced at 16 Hz, each encoded at the rung the optimizer chose (11 Mbit/s for one
      camera) into a ``CompressedImage`` and published, in a process with the optimizer's and
      the probe's threads beside it;
    - ``encode``: libjpeg-turbo alone on the same frames at the same rung, the same thread;
    - ``probe``: the ladder's probe (its own thread): one probe's time over its interval.

    Each as a share of a core at 16 Hz, against the 3 % target and the frame period.
    """
    from dbml.media.images import Frame
    from dbml.media.photos import PanCamera
    from dbml.runtime.camera import PROBE_INTERVAL_S, ManagedCamera
    from dbml.testing import Fleet
    from dbml.transports.base import Variant

    rate_hz = 16.0
    with Fleet(clock=time.monotonic) as fleet:
        camera = ManagedCamera(fleet.host("r1"), "/r1/camera", min_rate_hz=1.0, max_rate_hz=rate_hz)
        fleet.watch("/r1/camera", remote=Variant.COMPRESSED)
        fleet.budget(11.0)
        eye = PanCamera(640, 480)
        camera.publish_frame(Frame(eye.frame(), "rgb8"))  # the first probe, in this thread
        fleet.optimizer.start()  # rounds and heartbeats: the allocation stays in force
        frames = [Frame(eye.frame(), "rgb8") for _ in range(int(seconds * rate_hz))]
        deadline = time.monotonic() + 10.0
        while camera.publisher.encoding is None or camera.current_rate_hz() < rate_hz:
            if time.monotonic() > deadline:
                raise RuntimeError("no allocation of 16 Hz within 10 s")
            time.sleep(0.01)
        sent = 0
        camera.rate.reset()
        cpu_start, wall_start = time.thread_time(), time.perf_counter()
        for frame in frames:  # paced as a driver is: one frame a period
            camera.rate.sleep()
            sent += camera.publish_frame(frame)
        cpu_s = time.thread_time() - cpu_start
        wall_s = time.perf_counter() - wall_start
        probe_s = camera.probe_seconds
        encoding = camera.publisher.encoding
        camera.close()
    assert encoding is not None
    scale, quality = encoding
    assert quality is not None
    encode_start = time.thread_time()
    for frame in frames:
        encode_jpeg(frame.pixels, encoding="rgb8", quality=quality, scale=scale)
    encode_ms = (time.thread_time() - encode_start) / len(frames) * 1e3
    per_frame_ms = cpu_s / max(sent, 1) * 1e3
    return {
        "camera": "640x480 rgb8 at 16 Hz",
        "rung": encoding_label(scale, quality),
        "frames": len(frames),
        "sent": sent,
        "path_ms_per_frame": round(per_frame_ms, 3),
        "path_share_at_16_hz": round(per_frame_ms * rate_hz / 1e3, 4),
        "encode_ms_per_frame": round(encode_ms, 3),
        "encode_share_at_16_hz": round(encode_ms * rate_hz / 1e3, 4),
        "target_share": 0.03,
        "reference_frame_period_ms": round(1e3 / rate_hz, 2),
        "probe_ms": round(probe_s * 1e3, 1),
        "probe_share": round(probe_s / PROBE_INTERVAL_S, 4),
        "wall_s": round(wall_s, 2),
    }


def teleop(step_s: float) -> dict[str, Any]:
    """The paper's experiment on real frames over zenoh: the ladder, then rate only."""
    from dbml.cli.documents import photo_demo_document
    from dbml.demo.photos import run_photo_demo
    from dbml.transports.registry import TRANSPORTS

    result = run_photo_demo(TRANSPORTS["zenoh"], step_seconds=step_s)
    return photo_demo_document(result)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channels", type=int, nargs="+", default=[2, 20, 80, 320])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--grid", type=int, default=17, help="MILP rates per rung")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--fleets", type=int, default=10, help="fleets timed per size")
    parser.add_argument(
        "--uplinks", action="store_true", help="also each size with an uplink per 4 cameras"
    )
    parser.add_argument("--cpu-seconds", type=float, default=10.0, help="0: skip")
    parser.add_argument("--step-seconds", type=float, default=3.0, help="teleop; 0: skip")
    parser.add_argument("--json", action="store_true", help="JSON only")
    args = parser.parse_args()
    results = [measure(n, args.repeat, args.grid, args.seed, args.fleets) for n in args.channels]
    document: dict[str, Any] = {
        "benchmark": "quality_solver",
        "reference": "scipy.optimize.milp (HiGHS) over every allowed rung at a grid of rates",
        "results": results,
    }
    if args.uplinks:
        document["links"] = [
            measure_links(n, args.repeat, args.grid, args.seed, args.fleets)
            for n in args.channels
            if n >= CAMERAS_PER_UPLINK
        ]
    if args.cpu_seconds > 0:
        document["encoding"] = encoding_cpu(args.cpu_seconds)
    if args.step_seconds > 0:
        document["teleop"] = teleop(args.step_seconds)
    if not args.json:
        for row in results:
            print(
                f"{row['channels']:>4} channels: {row['solver_ms_median']:.3f} ms (median of "
                f"{row['fleets']} fleets; slowest fleet {row['solver_ms_worst_fleet']:.3f}); "
                f"the next round from the last price {row['warm_ms_median']:.3f} ms (slowest "
                f"{row['warm_ms_worst_fleet']:.3f}); gap to milp {row['gap_to_milp']:+.2e}, to "
                f"bound {row['gap_to_bound']:.2e}"
            )
        for row in document.get("links", []):
            print(
                f"{row['channels']:>4} channels behind {row['uplinks']} uplinks: "
                f"{row['solver_ms_median']:.3f} ms (slowest fleet "
                f"{row['solver_ms_worst_fleet']:.3f}); {row['uplinks_at_capacity']:.0%} of "
                f"uplinks at capacity; gap to milp {row.get('gap_to_milp', float('nan')):+.2e}"
            )
        if "encoding" in document:
            enc = document["encoding"]
            print(
                f"camera at {enc['rung']}: encoding {enc['encode_ms_per_frame']:.2f} ms a frame "
                f"({enc['encode_share_at_16_hz']:.1%} of a core at 16 Hz), the whole path "
                f"{enc['path_ms_per_frame']:.2f} ms ({enc['path_share_at_16_hz']:.1%}); target 3 "
                f"%; probe {enc['probe_ms']:.0f} ms every {PROBE_NOTE}"
            )
        if "teleop" in document:
            tel = document["teleop"]
            print(
                f"teleop: utility {tel['ladder']['utility']:.3f} with the ladder, "
                f"{tel['rate_only']['utility'] if tel['rate_only'] else float('nan'):.3f} rate "
                f"only ({tel['utility_gain']:+.1%}); checks {tel['checks']}"
            )
    print(json.dumps(document))


if __name__ == "__main__":
    main()
