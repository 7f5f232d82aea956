"""Budget integrity: the bytes on the wire in every 1-s window against the budget, under churn.

An optimizer (11 Mbit/s, period 1 s), five managed publishers (84,000 / 21,000 / 8,000 / 40,000 /
1,000 B, 1-16 Hz, hosts robot1-5) and a remote subscriber per topic (host operator) run as
``python -m dbml`` processes on a private loopback zenoh mesh. A plain zenoh session (shared
memory off) counts every sample on ``**/optimized`` with ``WireSniffer`` and checks sequence
numbers, so a sniffer that missed or doubled samples shows as ``sniffer_lost``/``_duplicates``.
After a warm-up (every channel allocated, acknowledged and seen; excluded), each run measures
the reference, steady state (10 s: nothing changes, so its worst window is whole-frame
quantisation alone), then churn (``--seconds``, 30): 10 seeded random priority writes per
second, the budget stepped 11 -> 8 Mbit/s at 1/3, a sixth publisher (30,000 B) joining at 1/2
and the 40,000 B one ended by PID at 22/30.

Each byte is charged against the budget in force when it arrived (from the instant before this
process writes the step): a window's ratio is sum(bytes / B(t)), exactly bytes / B when it does
not cross the step. Judging a whole window by one budget (the smaller, or the one at its end)
would charge up to a second of traffic correctly sent under 11 Mbit/s against 8, putting
windows near the step at ~1.37 even with an instant optimizer; this way the optimizer's
reaction time still counts in full, with no grace. The target, ``worst window <= B + one
largest message``, is ratio <= (B + L) / B with B = 11 Mbit/s: after the step that allowance
(6.1 %) is stricter than L / 8 Mbit/s (8.4 %), never more lenient. The allocated sum
(``current_value * size`` over live managed channels, polled every 50 ms) is reported too; a
poll within 0.25 s after the step is judged against the old budget, which is all it can know.

The optimizer runs with ``frame_headroom: true`` (one message per channel but the largest kept
out of the budget, so whole frames cannot add up past B + one message in a window);
``--without-headroom`` allocates the whole budget instead, to see the quantisation it covers.

    python bench/budget_integrity.py [--json] [--runs 3] [--seconds 30] [--without-headroom]
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, NamedTuple

import zenoh
from rich.console import Console
from rich.table import Table

from dbml.core.errors import TransportError
from dbml.harness.processes import end_process, free_port
from dbml.harness.sniffer import WireSniffer, window_stats
from dbml.protocol import names
from dbml.runtime.graph import is_managed, published_topics
from dbml.runtime.metadata import MessageMeta
from dbml.transports.base import ParamValue
from dbml.transports.zenoh import ZenohTransport


class Channel(NamedTuple):
    topic: str
    size_bytes: int
    host: str


CHANNELS = (
    Channel("/robot1/camera", 84_000, "robot1"),
    Channel("/robot2/camera", 21_000, "robot2"),
    Channel("/robot3/lidar", 8_000, "robot3"),
    Channel("/robot4/depth", 40_000, "robot4"),
    Channel("/robot5/imu", 1_000, "robot5"),
)
JOINER = Channel("/robot6/camera", 30_000, "robot6")
LEAVER = CHANNELS[3]
MIN_HZ, MAX_HZ = 1.0, 16.0
BUDGET_MBIT, STEP_MBIT = 11.0, 8.0
PERIOD_S = 1.0
CHANGES_PER_S = 10
STEP_AT, JOIN_AT, LEAVE_AT = 10 / 30, 15 / 30, 22 / 30
"""When the budget step, the join and the leave happen, as shares of the churn pass."""
SEED = 20_240_917
"""Run k draws its priorities from ``random.Random(SEED + k)``."""
STEADY_S = 10.0
OVER_RATIO = 1.05
READY_S = 40.0
"""Bounds reaching the fleet, then every channel allocated, acknowledged and seen (warm-up)."""
POLL_S = 0.05
ALLOCATION_GRACE_S = 0.25
LATE_S = 2.0
"""The churn pass fails when the schedule falls further behind than this (an overloaded host)."""
STOP_S = 5.0
REFERENCE = "steady state: the same fleet with no priority changes, no step, no join, no leave"
TARGET = "worst window <= B + one largest message"


def bytes_per_s(mbit: float) -> float:
    return mbit * 1e6 / 8


class BenchError(Exception):
    """A run that could not be measured: a process exited, or the fleet never settled."""


class Fleet:
    """The ``python -m dbml`` processes of one run, each ended by its PID."""

    def __init__(self, port: int, workdir: Path) -> None:
        self._env = dict(os.environ, DBML_ZENOH_PORT=str(port))
        self._workdir = workdir
        self._procs: dict[str, subprocess.Popen[bytes]] = {}
        self._ended: set[str] = set()

    def start(self, name: str, *args: str) -> None:
        log = self._workdir / f"{name}.log"
        with log.open("wb") as err:
            self._procs[name] = subprocess.Popen(
                [sys.executable, "-m", "dbml", *args],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=err,
                env=self._env,
            )

    def start_publisher(self, channel: Channel) -> None:
        self.start(
            f"publish-{channel.host}",
            "publish",
            channel.topic,
            "--size-bytes",
            str(channel.size_bytes),
            "--min-hz",
            f"{MIN_HZ:g}",
            "--max-hz",
            f"{MAX_HZ:g}",
            "--host",
            channel.host,
        )

    def end(self, name: str) -> None:
        """End one process on purpose (a leave)."""
        self._ended.add(name)
        end_process(self._procs[name], timeout_s=STOP_S)

    def exited(self) -> list[str]:
        """Processes that exited without being asked to."""
        return [
            f"{name} (exit {popen.returncode})"
            for name, popen in self._procs.items()
            if name not in self._ended and popen.poll() is not None
        ]

    def check(self) -> None:
        if exited := self.exited():
            raise BenchError(f"exited: {', '.join(exited)}\n{self.logs()}")

    def logs(self, lines: int = 12) -> str:
        parts = []
        for name in self._procs:
            tail = (self._workdir / f"{name}.log").read_text(errors="replace").splitlines()
            parts.append(f"--- {name} ---\n" + "\n".join(tail[-lines:]))
        return "\n".join(parts)

    def stop(self) -> None:
        """SIGTERM every process started here (the nodes close their session), then reap."""
        for popen in self._procs.values():
            if popen.poll() is None:
                popen.terminate()
        for popen in self._procs.values():
            end_process(popen, timeout_s=STOP_S)


def sniffer_session(port: int) -> zenoh.Session:
    """A plain zenoh peer on the run's loopback mesh: no dbml, no shared memory."""
    config = zenoh.Config()
    for key, value in (
        ("mode", '"peer"'),
        ("scouting/multicast/enabled", "false"),
        ("transport/shared_memory/enabled", "false"),
        ("listen/endpoints", '["tcp/127.0.0.1:0"]'),
        ("connect/endpoints", f'["tcp/127.0.0.1:{port}"]'),
    ):
        config.insert_json5(key, value)
    return zenoh.open(config)


class SequenceGaps:
    """Which optimized keys were seen, and how many samples the sniffer's session missed."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self._lock = threading.Lock()
        self._seen: set[str] = set()
        self._last: dict[str, int] = {}
        self._lost = self._duplicates = 0
        self._subscriber = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        attachment = sample.attachment
        try:
            seq = MessageMeta.decode(None if attachment is None else attachment.to_bytes()).seq
        except TransportError:
            seq = None
        with self._lock:
            self._seen.add(key)
            if seq is None:
                return
            last = self._last.get(key)
            if last is not None and seq > last + 1:
                self._lost += seq - last - 1
            elif last is not None and seq <= last:
                self._duplicates += 1  # counted twice (or reordered): the sniffer overcounts
            self._last[key] = seq if last is None else max(last, seq)

    def seen(self) -> set[str]:
        with self._lock:
            return set(self._seen)

    def lost(self) -> int:
        with self._lock:
            return self._lost

    def duplicates(self) -> int:
        with self._lock:
            return self._duplicates

    def close(self) -> None:
        self._subscriber.undeclare()  # type: ignore[no-untyped-call]  # unannotated in stubs


@dataclass
class BudgetSchedule:
    """The budget in force over time (monotonic seconds), as this process wrote it."""

    steps: list[tuple[float, float]] = field(default_factory=list)
    """``(t_s, bytes_per_s)`` in time order; the first applies from the start."""

    def at(self, t_s: float) -> float:
        times = [t for t, _ in self.steps]
        index = max(0, bisect.bisect_right(times, t_s) - 1)
        return self.steps[index][1]


class AllocationPoller:
    """Every 50 ms: the sum of ``current_value * size`` over the live managed channels."""

    def __init__(self, transport: ZenohTransport, bound_s: float) -> None:
        self._transport = transport
        self._lock = threading.Lock()
        self._samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._deadline = time.monotonic() + bound_s
        self._thread = threading.Thread(target=self._run, name="allocated-sum", daemon=True)
        self._thread.start()

    def allocated_bytes_per_s(self) -> float:
        params = self._transport.params
        entries = self._transport.graph.entries()
        total = 0.0
        for topic in published_topics(entries):
            if not is_managed(entries, topic):
                continue
            rate = number(params.get(names.current_value(topic)))
            size = number(params.get(names.size(topic)))
            if rate is not None and size is not None:
                total += rate * size
        return total

    def _run(self) -> None:
        while not self._stop.wait(POLL_S) and time.monotonic() < self._deadline:
            sample = (time.monotonic(), self.allocated_bytes_per_s())
            with self._lock:
                self._samples.append(sample)

    def samples(self, start_s: float, end_s: float) -> list[tuple[float, float]]:
        with self._lock:
            return [s for s in self._samples if start_s <= s[0] <= end_s]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=STOP_S)


def number(value: ParamValue) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def optimized_key(topic: str) -> str:
    return f"{topic[1:]}/optimized"


@dataclass
class Rig:
    """One run's processes and observers."""

    fleet: Fleet
    transport: ZenohTransport
    sniffer: WireSniffer
    gaps: SequenceGaps
    poller: AllocationPoller
    rng: random.Random


def settled(rig: Rig, channels: tuple[Channel, ...], since_ns: int) -> bool:
    """Every channel managed, allocated by a round after ``since_ns``, acknowledged, on the wire.

    An unchanged rate is not written again: a round's heartbeat (``/dbm/round``) written after
    ``since_ns`` says the rates in the store are that round's.
    """
    params = rig.transport.params
    seen = rig.gaps.seen()
    stamp = params.stamp(names.ROUND)
    for channel in channels:
        current = number(params.get(names.current_value(channel.topic)))
        applied = number(params.get(names.applied(channel.topic)))
        if (
            params.get(names.managed(channel.topic)) is not True
            or stamp is None
            or stamp[0] <= since_ns
            or current is None
            or applied is None
            or not math.isclose(current, applied, rel_tol=1e-9)
            or number(params.get(names.size(channel.topic))) != channel.size_bytes
            or optimized_key(channel.topic) not in seen
        ):
            return False
    return True


def wait_until(rig: Rig, predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Poll ``predicate`` every 50 ms for at most ``timeout_s``; a process exit fails at once."""
    deadline = time.monotonic() + timeout_s
    for _ in range(math.ceil(timeout_s / POLL_S) + 1):
        rig.fleet.check()
        if predicate():
            return True
        left = deadline - time.monotonic()
        if left <= 0:
            break
        time.sleep(min(POLL_S, left))
    return False


def hold(rig: Rig, seconds: float) -> None:
    """Let ``seconds`` pass, checking every 0.25 s that no process exited."""
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        rig.fleet.check()
        time.sleep(min(0.25, left))


def charged(
    arrivals: list[tuple[float, int]], budget: BudgetSchedule, reference_bps: float
) -> list[tuple[float, int]]:
    """Each arrival's bytes charged against the budget in force then, in ``reference`` bytes."""
    return [(t, round(n * reference_bps / budget.at(t))) for t, n in arrivals]


def wire_stats(
    rig: Rig,
    start_s: float,
    end_s: float,
    budget: BudgetSchedule,
    phases: dict[str, float] | None = None,
) -> tuple[dict[str, Any], int]:
    """The pass's windows; with ``phases`` (name -> start), also the worst inside each phase."""
    reference = budget.steps[0][1]
    arrivals = [a for a in rig.sniffer.arrivals(since_s=start_s) if a[0] <= end_s]
    weighted = charged(arrivals, budget, reference)
    stats = window_stats(weighted, limit_bytes=OVER_RATIO * reference)
    largest = max((n for _, n in arrivals), default=0)
    span_s = weighted[-1][0] - weighted[0][0] if len(weighted) > 1 else 0.0
    mean = sum(n for _, n in weighted[:-1]) / (reference * span_s) if span_s else 0.0
    document: dict[str, Any] = {
        "windows": stats.windows,
        "worst_ratio": round(stats.worst_bytes / reference, 4),
        "over_1_05_share": round(stats.over_share, 4),
        "mean_ratio": round(mean, 4),
    }
    if phases:
        bounds = sorted(phases.items(), key=lambda item: item[1])
        by_phase = {}
        for i, (name, begin_s) in enumerate(bounds):
            until_s = bounds[i + 1][1] if i + 1 < len(bounds) else math.inf
            inside = [a for a in weighted if begin_s <= a[0] < until_s]
            worst = window_stats(inside, limit_bytes=OVER_RATIO * reference).worst_bytes
            by_phase[name] = round(worst / reference, 4)
        document["worst_ratio_by_phase"] = by_phase
    return document, largest


def allocated_worst(
    rig: Rig, start_s: float, end_s: float, budget: BudgetSchedule
) -> dict[str, Any]:
    """The worst allocated sum / budget of the pass, and when it was polled (s into the pass)."""
    worst, at_s = 0.0, None
    for t, total in rig.poller.samples(start_s, end_s):
        limit = max(budget.at(t), budget.at(t - ALLOCATION_GRACE_S))
        if total / limit > worst:
            worst, at_s = total / limit, t - start_s
    return {
        "allocated_worst_ratio": round(worst, 4),
        "allocated_worst_at_s": None if at_s is None else round(at_s, 2),
    }


def steady_pass(rig: Rig, seconds: float) -> tuple[dict[str, Any], int]:
    budget = BudgetSchedule([(-math.inf, bytes_per_s(BUDGET_MBIT))])
    lost, duplicates = rig.gaps.lost(), rig.gaps.duplicates()
    start = time.monotonic()
    rig.sniffer.clear()
    hold(rig, seconds)
    end = time.monotonic()
    stats, largest = wire_stats(rig, start, end, budget)
    stats.update(allocated_worst(rig, start, end, budget))
    stats["sniffer_lost"] = rig.gaps.lost() - lost
    stats["sniffer_duplicates"] = rig.gaps.duplicates() - duplicates
    return stats, largest


def churn_plan(seconds: float) -> list[tuple[float, str]]:
    """The scheduled actions, ``(offset_s, action)`` in time order; events before a write."""
    plan = [(k / CHANGES_PER_S, "priority") for k in range(round(seconds * CHANGES_PER_S))]
    plan += [
        (STEP_AT * seconds, "step"),
        (JOIN_AT * seconds, "join"),
        (LEAVE_AT * seconds, "leave"),
    ]
    return sorted(plan, key=lambda item: (item[0], item[1] == "priority"))


def churn_pass(rig: Rig, seconds: float) -> tuple[dict[str, Any], int]:
    params = rig.transport.params
    budget = BudgetSchedule([(-math.inf, bytes_per_s(BUDGET_MBIT))])
    live = {c.topic for c in CHANNELS}
    leaving: threading.Thread | None = None
    writes = 0
    lag_s = 0.0
    join_ns: int | None = None
    lost, duplicates = rig.gaps.lost(), rig.gaps.duplicates()
    start = time.monotonic()
    phases = {"before_step": start}
    rig.sniffer.clear()
    for offset, action in churn_plan(seconds):
        wait = start + offset - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        lag_s = max(lag_s, -wait)
        if lag_s > LATE_S:
            raise BenchError(f"the churn schedule fell {lag_s:.1f} s behind: host overloaded")
        rig.fleet.check()
        if action == "priority":
            topic = rig.rng.choice(sorted(live))
            params.set(names.priority(topic), rig.rng.random())
            writes += 1
        elif action == "step":
            phases["after_step"] = time.monotonic()
            budget.steps.append((phases["after_step"], bytes_per_s(STEP_MBIT)))
            params.set(names.BANDWIDTH, STEP_MBIT)
        elif action == "join":
            phases["after_join"], join_ns = time.monotonic(), time.time_ns()
            rig.fleet.start_publisher(JOINER)
            live.add(JOINER.topic)
        else:
            phases["after_leave"] = time.monotonic()
            live.discard(LEAVER.topic)
            leaving = threading.Thread(
                target=rig.fleet.end, args=(f"publish-{LEAVER.host}",), daemon=True
            )
            leaving.start()
    hold(rig, start + seconds - time.monotonic())
    end = time.monotonic()
    if leaving is not None:
        leaving.join(timeout=STOP_S * 2)
    stats, largest = wire_stats(rig, start, end, budget, phases)
    stats.update(allocated_worst(rig, start, end, budget))
    stamp = params.stamp(names.current_value(JOINER.topic))
    stats.update(
        priority_changes=writes,
        schedule_lag_ms=round(lag_s * 1e3, 1),
        sniffer_lost=rig.gaps.lost() - lost,
        sniffer_duplicates=rig.gaps.duplicates() - duplicates,
        joiner_managed=bool(
            join_ns is not None
            and params.get(names.managed(JOINER.topic)) is True
            and stamp is not None
            and stamp[0] > join_ns
        ),
    )
    return stats, largest


@contextlib.contextmanager
def rig_for(run: int, seconds: float, workdir: Path, *, headroom: bool) -> Iterator[Rig]:
    port = free_port()
    config = workdir / "dbm.yaml"
    config.write_text(
        f"dbm:\n  max_bandwidth_in_mbit: {BUDGET_MBIT:g}\n"
        f"  optimization_rate_in_seconds: {PERIOD_S:g}\n"
        f"  frame_headroom: {'true' if headroom else 'false'}\n"
    )
    # This session first, so it holds the rendezvous for the whole run.
    with contextlib.ExitStack() as stack:
        transport = ZenohTransport(host="bench", port=port)
        stack.callback(transport.close)
        session = sniffer_session(port)
        stack.callback(session.close)
        sniffer = stack.enter_context(WireSniffer(session, "**/optimized"))
        gaps = SequenceGaps(session, "**/optimized")
        stack.callback(gaps.close)
        poller = AllocationPoller(transport, bound_s=2 * READY_S + STEADY_S + seconds)
        stack.callback(poller.close)
        fleet = Fleet(port, workdir)
        stack.callback(fleet.stop)  # runs first: the processes end before the sessions close
        fleet.start("optimizer", "optimizer", "--config", str(config), "--host", "base")
        for channel in (*CHANNELS, JOINER):
            fleet.start(
                f"subscribe-{channel.host}", "subscribe", channel.topic, "--host", "operator"
            )
        for channel in CHANNELS:
            fleet.start_publisher(channel)
        yield Rig(fleet, transport, sniffer, gaps, poller, random.Random(SEED + run))


def measure_run(run: int, seconds: float, *, headroom: bool) -> dict[str, Any]:
    with (
        tempfile.TemporaryDirectory(prefix="dbml-budget-") as tmp,
        rig_for(run, seconds, Path(tmp), headroom=headroom) as rig,
    ):
        if not rig.transport.wait_for_peers(READY_S):
            raise BenchError(f"no dbml process reached\n{rig.fleet.logs()}")
        params = rig.transport.params
        for channel in CHANNELS:
            params.set(names.priority(channel.topic), rig.rng.random())
        since_ns = time.time_ns()
        if not wait_until(rig, lambda: settled(rig, CHANNELS, since_ns), READY_S):
            raise BenchError(
                f"not every channel allocated within {READY_S:g} s\n{rig.fleet.logs()}"
            )
        steady, steady_largest = steady_pass(rig, min(STEADY_S, seconds))
        churn, churn_largest = churn_pass(rig, seconds)
    largest = max(steady_largest, churn_largest, 1)
    reference = bytes_per_s(BUDGET_MBIT)
    return {
        "windows": churn["windows"],
        "worst_ratio": churn["worst_ratio"],
        "over_1_05_share": churn["over_1_05_share"],
        "worst_ratio_by_phase": churn["worst_ratio_by_phase"],
        "mean_ratio": churn["mean_ratio"],
        "allocated_worst_ratio": churn["allocated_worst_ratio"],
        "allocated_worst_at_s": churn["allocated_worst_at_s"],
        "largest_message_bytes": largest,
        "target_ratio": round((reference + largest) / reference, 4),
        "steady_worst_ratio": steady["worst_ratio"],
        "steady_windows": steady["windows"],
        "steady_over_1_05_share": steady["over_1_05_share"],
        "steady_mean_ratio": steady["mean_ratio"],
        "steady_allocated_worst_ratio": steady["allocated_worst_ratio"],
        "priority_changes": churn["priority_changes"],
        "joiner_managed": churn["joiner_managed"],
        "schedule_lag_ms": churn["schedule_lag_ms"],
        "sniffer_lost": churn["sniffer_lost"] + steady["sniffer_lost"],
        "sniffer_duplicates": churn["sniffer_duplicates"] + steady["sniffer_duplicates"],
    }


def measure(runs: int, seconds: float, *, headroom: bool = True) -> dict[str, Any]:
    results = [measure_run(run, seconds, headroom=headroom) for run in range(runs)]
    return {
        "benchmark": "budget_integrity",
        "frame_headroom": headroom,
        "runs": results,
        "windows": sum(r["windows"] for r in results),
        "worst_ratio": max(r["worst_ratio"] for r in results),
        "over_1_05_share": max(r["over_1_05_share"] for r in results),
        "allocated_worst_ratio": max(r["allocated_worst_ratio"] for r in results),
        "steady_worst_ratio": max(r["steady_worst_ratio"] for r in results),
        "target": TARGET,
        "met": all(r["worst_ratio"] <= r["target_ratio"] for r in results),
        "reference": REFERENCE,
        "scenario": {
            "seconds": seconds,
            "steady_seconds": min(STEADY_S, seconds),
            "budget_mbit": [BUDGET_MBIT, STEP_MBIT],
            "step_at_s": round(STEP_AT * seconds, 3),
            "join_at_s": round(JOIN_AT * seconds, 3),
            "leave_at_s": round(LEAVE_AT * seconds, 3),
            "changes_per_s": CHANGES_PER_S,
            "seed": SEED,
        },
    }


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--runs", type=int, default=3, help="runs (default 3)")
    parser.add_argument("--seconds", type=float, default=30.0, help="churn pass (default 30)")
    parser.add_argument(
        "--without-headroom",
        action="store_true",
        help="allocate the whole budget (dbm.frame_headroom false): whole-frame quantisation shows",
    )
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be >= 1")
    if not 5 <= args.seconds <= 600:
        parser.error("--seconds must be 5-600")
    signal.signal(signal.SIGTERM, _interrupt)  # the same cleanup as Ctrl-C
    try:
        document = measure(args.runs, args.seconds, headroom=not args.without_headroom)
    except BenchError as err:
        raise SystemExit(f"budget_integrity: {err}") from None
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    if args.json:
        print(json.dumps(document))
        return

    table = Table(title="bytes on */optimized per 1-s window / budget, under churn (loopback)")
    columns = ("run", "windows", "worst", "steady worst", ">1.05", "allocated", "target", "lost")
    for name in columns:
        table.add_column(name, justify="right")
    for i, run in enumerate(document["runs"]):
        table.add_row(
            str(i),
            str(run["windows"]),
            f"{run['worst_ratio']:.3f}",
            f"{run['steady_worst_ratio']:.3f}",
            f"{run['over_1_05_share']:.1%}",
            f"{run['allocated_worst_ratio']:.3f}",
            f"{run['target_ratio']:.3f}",
            str(run["sniffer_lost"]),
        )
    table.caption = f"{TARGET}: {'met' if document['met'] else 'NOT met'}; reference: {REFERENCE}"
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
