"""The estimator's designs judged on the testbed's recorded traces (issue 20, item 4).

``bench/estimator_rmcat.py --trace bench/traces`` records what a testbed estimate run received
(per frame: stream, seq, sent and arrival time, size, the rate the publisher applied) and the
operator's ticks. This derives a link model from each trace: the payload rate the link gave per
shaped Mbit/s (from frames that waited behind another), the delay noise on top of the FIFO
(from frames that did not wait), how the allocation split the budget between the robots over
time, and how late a budget change reached the senders. It then runs every design closed loop
in that model (``dbml.estimator.simulation``) on the trace's own link schedule, for a few seeds
of the noise, and prints JSON: per design and schedule the item-4 figures by name
(min/median/max over traces and seeds). A steady trace is also replayed open loop: its
recorded arrivals fed to each design as they came (item 3: the lowest estimate against the
steady value). ``--tick-s`` and ``--report-lag-s`` change the loop (the node judges every 0.1 s,
75 ms in the past; at once on a report of a queued frame, which 0.025 and 0.025 stand for).
Pure arithmetic: ``.venv/bin/python bench/estimator_replay.py [TRACE...]``.
"""

from __future__ import annotations

import argparse
import bisect
import json
import random
import statistics
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dbml.estimator import Arrival, BandwidthEstimator, Design, EstimatorSettings, settings_of

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import itertools

from dbml.estimator.simulation import FRAMES, Trace, simulate

TRACES = Path(__file__).resolve().parent / "traces"
UTILIZATION = 0.92
"""The testbed's budget share of the shaped rate: the estimate's cap."""
TICK_S = 0.1
REPORT_LAG_S = 0.075
"""The node judges the window its reports completed (``dbml.runtime.estimator``)."""
SEEDS = 3
REACTION_S = 0.1
"""A cut's decision to the senders' first frame at the new rate when a trace does not say: the
first drop trace shows the new rate 20-100 ms after the cut reached the operator."""
GOODPUT_AFTER_S = 3.0
WINDOW_S = 1.0
WINDOW_STEP_S = 0.25
CUT_TOLERANCE = 0.01
STEADY_SETTLED_S = 5.0


@dataclass(frozen=True)
class Loop:
    """The node's loop: how often it judges and how late it sees a frame."""

    tick_s: float = TICK_S
    report_lag_s: float = REPORT_LAG_S


NODE = Loop()


@dataclass(frozen=True)
class Recorded:
    """One trace: the run's schedule, its frames and ticks (t0-relative seconds)."""

    name: str
    schedule: tuple[tuple[float, float], ...]
    step_s: float
    frames: list[dict[str, Any]]
    ticks: list[dict[str, Any]]

    @property
    def duration_s(self) -> float:
        return 10 * self.step_s

    def link_mbit(self, t_s: float) -> float:
        rate = self.schedule[0][1]
        for at, mbit in self.schedule:
            if at <= t_s:
                rate = mbit
        return rate


@dataclass(frozen=True)
class LinkFit:
    """What a trace says about the link and the loop around it."""

    efficiency: float
    """Payload Mbit/s the link carried per shaped Mbit/s while busy."""
    noise_s: list[float]
    """Delay beyond the FIFO's, of frames that did not wait (sorted)."""
    reaction_s: float
    """From a budget change at the operator to the senders' first frame at the new rate."""
    shares: list[tuple[float, dict[str, float]]]
    """(from, per stream share of the bytes): the allocation's split over time."""


def load(path: Path) -> Recorded:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    head = rows[0]
    schedule = tuple(
        (float(at), float(mbit))
        for at, mbit in (part.split(":") for part in head["schedule"].split(","))
    )
    frames = sorted((r for r in rows if r["kind"] == "frame"), key=lambda r: r["arrival_s"])
    ticks = [r for r in rows if r["kind"] == "tick"]
    return Recorded(path.stem, schedule, float(head["step_s"]), frames, ticks)


def fit(trace: Recorded) -> LinkFit:
    frames = [f for f in trace.frames if f["arrival_s"] >= 0 and f["sent_s"] >= 0]
    rates, idle = [], []
    for prev, frame in itertools.pairwise(frames):
        gap = frame["arrival_s"] - prev["arrival_s"]
        link = trace.link_mbit(frame["arrival_s"])
        if link > 0 and gap > 0 and frame["sent_s"] < prev["arrival_s"] - 0.005:
            rates.append(frame["size_bytes"] * 8e-6 / gap / link)  # it waited behind ``prev``
    efficiency = statistics.median(rates) if rates else 0.957
    # frames alone on the link from their send to their arrival: their delay is the
    # serialisation plus the noise the FIFO does not model
    by_sent = sorted(frames, key=lambda f: f["sent_s"])
    for k, frame in enumerate(by_sent):
        before = by_sent[k - 1] if k else None
        after = by_sent[k + 1] if k + 1 < len(by_sent) else None
        if (before is None or before["arrival_s"] < frame["sent_s"]) and (
            after is None or after["sent_s"] > frame["arrival_s"]
        ):
            idle.append(frame)
    # (a frame alone goes out at the shaped rate: the token bucket's burst covers its headers)
    noise = sorted(
        max(0.0, f["arrival_s"] - f["sent_s"] - f["size_bytes"] * 8e-6 / link)
        for f in idle
        if (link := trace.link_mbit(f["sent_s"])) > 0
    )
    return LinkFit(efficiency, noise, _reaction(trace), _shares(trace))


def _reaction(trace: Recorded) -> float:
    """Shortest lag from a cut's decision (the estimator's clock) to a frame sent at a lower rate.

    Traces without decision times (the first ones): ``REACTION_S``.
    """
    lags = []
    sends: dict[str, list[dict[str, Any]]] = {}
    for f in sorted(trace.frames, key=lambda f: f["sent_s"]):
        sends.setdefault(f["stream"], []).append(f)
    decided = sorted({t["decided_s"] for t in trace.ticks if t.get("decided_s") is not None})
    for at in decided:
        firsts = []
        for stream in sends.values():
            times = [f["sent_s"] for f in stream]
            k = bisect.bisect_left(times, at)
            if k == 0 or k >= len(stream):
                continue
            before = stream[k - 1]["rate_hz"]
            changed = next((f for f in stream[k : k + 40] if f["rate_hz"] < before), None)
            if changed is not None:
                firsts.append(changed["sent_s"] - at)
        if firsts:
            lags.append(min(firsts))
    return min(lags) if lags else REACTION_S  # a later lower rate may be another change


def _shares(trace: Recorded) -> list[tuple[float, dict[str, float]]]:
    """Per step of the run, each stream's share of the bytes the allocation asked for."""
    sizes = {name: size for name, size, *_ in FRAMES}
    out = []
    for k in range(10):
        start, end = k * trace.step_s, (k + 1) * trace.step_s
        wanted: dict[str, list[float]] = {}
        for f in trace.frames:
            if start <= f["sent_s"] < end and f["rate_hz"] and f["stream"] in sizes:
                wanted.setdefault(f["stream"], []).append(f["rate_hz"] * f["size_bytes"])
        means = {s: statistics.mean(v) for s, v in wanted.items()}
        total = sum(means.values())
        if total > 0:
            out.append((start, {s: v / total for s, v in means.items()}))
    return out


def _share_at(shares: list[tuple[float, dict[str, float]]]) -> Callable[[float], dict[str, float]]:
    starts = [at for at, _ in shares]

    def at(t_s: float) -> dict[str, float]:
        if not shares:
            return {}
        return shares[max(0, bisect.bisect_right(starts, t_s) - 1)][1]

    return at


def run_model(
    trace: Recorded, link: LinkFit, settings: EstimatorSettings, seed: int, loop: Loop = NODE
) -> tuple[Trace, float]:
    """One closed-loop run of ``settings`` in the trace's model; (trace, the estimate's cap)."""
    rng = random.Random(seed)
    noise = link.noise_s

    def jitter(_stream: str, _seq: int) -> float:
        return noise[rng.randrange(len(noise))] if noise else 0.0

    cap = max(mbit for _, mbit in trace.schedule) * UTILIZATION
    estimator = BandwidthEstimator(max_mbit=cap, settings=settings)
    result = simulate(
        estimator,
        trace.link_mbit,
        duration_s=trace.duration_s,
        tick_s=loop.tick_s,
        reaction_s=link.reaction_s,
        wire_efficiency=link.efficiency,
        jitter_s=jitter,
        report_lag_s=loop.report_lag_s,
        shares=_share_at(link.shares),
    )
    return result, cap


def figures(
    trace: Recorded, model: Trace, cap: float, loop: Loop = NODE
) -> dict[str, float | None]:
    """The item-4 figures by name (and item 3's on a steady schedule)."""
    out: dict[str, float | None] = {}
    schedule = trace.schedule
    end = trace.duration_s
    ests = [(e.t_s + loop.report_lag_s, e.estimate_mbit) for e in model.estimates]
    for k in range(1, len(schedule)):
        at, mbit = schedule[k]
        before = schedule[k - 1][1]
        until = schedule[k + 1][0] if k + 1 < len(schedule) else end
        tag = f"{before:g}->{mbit:g}@{at:g}s"
        if mbit < before:
            prior = [v for t, v in ests if t <= at]
            cut = next(
                (
                    t - at
                    for t, v in ests
                    if at < t <= until and v < prior[-1] * (1 - CUT_TOLERANCE)
                ),
                None,
            )
            out[f"{tag} first_cut_s"] = cut
            out[f"{tag} peak_p95_ms"] = _peak_p95_ms(model, at, until)
            out[f"{tag} goodput_share_after"] = _goodput(model, at + GOODPUT_AFTER_S, until) / mbit
        else:
            out[f"{tag} rise_90_s"] = next(
                (t - at for t, v in ests if at <= t <= until and v >= 0.9 * mbit), None
            )
    if len(schedule) > 2:
        bounds = [*schedule, (end, 0.0)]
        for (start, mbit), (stop, _) in itertools.pairwise(bounds):
            tag = f"phase {start:g}-{stop:g}s@{mbit:g}"
            out[f"{tag} utilisation"] = _goodput(model, start, stop) / mbit
            out[f"{tag} latency_p95_ms"] = 1000 * _p95(model, start, stop)
    if len(schedule) == 1:
        out |= _steady([(t, v) for t, v in ests], trace.schedule[0][1] * 0.957)
        out["latency_p95_ms"] = 1000 * _p95(model, STEADY_SETTLED_S, end)
    return out


def _steady(ests: Sequence[tuple[float, float]], payload_mbit: float) -> dict[str, float | None]:
    values = [v for t, v in ests if t >= STEADY_SETTLED_S]
    steady = statistics.median(values)
    return {
        "steady_share_of_payload": steady / payload_mbit,
        "lowest_share_of_steady": min(values) / steady,
    }


def _p95(model: Trace, start: float, end: float) -> float:
    delays = sorted(d for t, d, _ in model.delays if start <= t < end)
    return delays[int(0.95 * (len(delays) - 1))] if delays else 0.0


def _peak_p95_ms(model: Trace, start: float, end: float) -> float:
    peak, t = 0.0, start + WINDOW_S
    while t <= end:
        peak = max(peak, _p95(model, t - WINDOW_S, t))
        t += WINDOW_STEP_S
    return 1000 * peak


def _goodput(model: Trace, start: float, end: float) -> float:
    """Mbit/s that arrived in [start, end)."""
    sizes = {name: size for name, size, *_ in FRAMES}
    bits = sum(sizes[s] * 8e-6 for t, _, s in model.delays if start <= t < end)
    return bits / (end - start) if end > start else 0.0


def open_loop(
    trace: Recorded, settings: EstimatorSettings, loop: Loop = NODE
) -> dict[str, float | None]:
    """A steady trace's arrivals fed as they came: the lowest estimate against its steady value."""
    cap = trace.schedule[0][1] * UTILIZATION
    estimator = BandwidthEstimator(max_mbit=cap, settings=settings)
    frames = trace.frames
    k, t, ests = 0, loop.tick_s, []
    while t <= trace.duration_s:
        judged = t - loop.report_lag_s
        while k < len(frames) and frames[k]["arrival_s"] <= judged:
            f = frames[k]
            estimator.observe(
                Arrival(f["stream"], f["seq"], f["sent_s"], f["arrival_s"], f["size_bytes"])
            )
            k += 1
        ests.append((t, estimator.update(judged).estimate_mbit))
        t += loop.tick_s
    return _steady(ests, trace.schedule[0][1] * 0.957)


DESIGNS: Mapping[str, EstimatorSettings] = {
    design.value: EstimatorSettings(detector=settings_of(design)) for design in Design
}
"""Each design with its own defaults, by name (``--design``)."""


def kind_of(trace: Recorded) -> str:
    return trace.name.split("-")[0]


def spread(runs: Sequence[Mapping[str, float | None]]) -> dict[str, dict[str, Any]]:
    names = list(dict.fromkeys(n for run in runs for n in run))
    out = {}
    for name in names:
        values = [v for run in runs if (v := run.get(name)) is not None]
        out[name] = {
            "min": round(min(values), 3) if values else None,
            "median": round(statistics.median(values), 3) if values else None,
            "max": round(max(values), 3) if values else None,
            "missing": len(runs) - len(values),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("traces", nargs="*", type=Path)
    parser.add_argument("--seeds", type=int, default=SEEDS)
    parser.add_argument("--design", action="append", choices=tuple(DESIGNS))
    parser.add_argument("--tick-s", type=float, default=TICK_S, help="how often it judges")
    parser.add_argument(
        "--report-lag-s", type=float, default=REPORT_LAG_S, help="how late it sees a frame"
    )
    args = parser.parse_args(argv)
    loop = Loop(args.tick_s, args.report_lag_s)
    paths = args.traces or sorted(TRACES.glob("*.jsonl"))
    traces = [load(p) for p in paths]
    fits = {t.name: fit(t) for t in traces}
    report: dict[str, Any] = {
        "traces": {
            t.name: {
                "efficiency": round(fits[t.name].efficiency, 4),
                "noise_p50_ms": round(1000 * _quantile(fits[t.name].noise_s, 0.5), 2),
                "noise_p95_ms": round(1000 * _quantile(fits[t.name].noise_s, 0.95), 2),
                "reaction_s": round(fits[t.name].reaction_s, 3),
            }
            for t in traces
        }
    }
    designs = {d: DESIGNS[d] for d in (args.design or DESIGNS)}
    for design, settings in designs.items():
        per_kind: dict[str, list[dict[str, float | None]]] = {}
        for trace in traces:
            for seed in range(args.seeds):
                model, cap = run_model(trace, fits[trace.name], settings, seed, loop)
                per_kind.setdefault(kind_of(trace), []).append(figures(trace, model, cap, loop))
            if len(trace.schedule) == 1:
                per_kind.setdefault("steady-open-loop", []).append(open_loop(trace, settings, loop))
        report[design] = {kind: spread(runs) for kind, runs in per_kind.items()}
    json.dump(report, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


def _quantile(values: Sequence[float], q: float) -> float:
    return values[int(q * (len(values) - 1))] if values else 0.0


if __name__ == "__main__":
    sys.exit(main())
