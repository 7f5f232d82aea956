"""ROS 2 publish overhead: a managed publish over rclpy against raw rclpy publishes, messages/s.

Same run, same ROS 2 participant (dbml's ``RclpyTransport``, Fast DDS), same QoS (reliable,
keep last 5, volatile: dbml's publishers'), 64-B and 84,000-B ``sensor_msgs/msg/Image``
messages published back to back. Three ways, each on a topic of its own:

- ``raw_bytes``: rclpy's ``publisher.publish(bytes)`` of the already-serialised CDR, exactly the
  bytes the managed side sends (the reference: nothing is serialised);
- ``raw_msg``: an ``Image`` built per message (header, encoding, the pixels) and
  ``publisher.publish(msg)``, what a typical driver does; one call is build + publish;
- ``managed``: ``ManagedPublisher.publish`` of those bytes, the hot path of ``dbml publish
  --transport rclpy`` (its payload is ``dbml.transports.registry.camera_frame``'s), with min = max =
  ``MAX_RATE_HZ`` and that rate allocated, so its limiter never drops (``dropped`` counts the
  calls that returned False) and it pays for everything else: the rate in force, size tracking,
  the check for local subscribers of ``[topic]``, the metadata it packs and the put to
  ``[topic]/optimized``.

A subscriber in another process (this script in ``--sink`` mode: one raw, best-effort
subscription per topic, an ``EventsExecutor`` where rclpy has one) receives every topic, so each
publish really goes out; what arrives is reported as the delivered share (a best-effort reader
that falls behind loses messages, the publisher never waits). Each case runs for ``--seconds``,
the three interleaved (rotating who goes first), best of ``--repeat`` for messages/s; p50/p99 of
one call come from every timed call of the counted rounds. Where managed / raw_bytes is below
``TARGET_RATIO``, the managed publish is profiled (``cProfile``, then each part timed alone) and
the JSON says where its time goes. Every process runs in a ROS 2 domain claimed for the run, with
its logs in a temporary directory. Prints JSON with ``--json``, a table then the JSON otherwise.

    python bench/ros2_publish.py [--json] [--seconds 1.5] [--repeat 3] [--profile]
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import itertools
import json
import os
import pstats
import queue
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from dbml.core.spec import MAX_RATE_HZ
from dbml.harness.child import Control
from dbml.harness.ros2env import (
    claim_domain,
    fastdds_shm_files,
    remove_fastdds_shm,
    ros2_child_env,
)
from dbml.harness.supervisor import Supervisor
from dbml.protocol import names
from dbml.protocol.metadata import pack_meta
from dbml.runtime import ManagedPublisher

PAYLOADS = (64, 84_000)
KINDS = ("raw_bytes", "raw_msg", "managed")
UNLIMITED_HZ = MAX_RATE_HZ
TARGET_RATIO = 0.8
MAX_COUNT = 2_000_000
"""Upper bound on the calls of one case, whatever the duration."""
PUBLISH_DEPTH = 5
SINK_DEPTH = 100
READY_S = 30.0
MATCH_S = 15.0
QUIET_S = 0.2
"""The sink reports a case once nothing arrived for this long."""
FLUSH_S = 15.0
STOP_S = 10.0
PROFILE_CALLS = 20_000
"""Managed publishes profiled (cProfile) where the ratio misses the target."""
PART_CALLS = 20_000
"""Calls per part when the managed publish's parts are timed alone."""
PROFILE_TOP = 12
REFERENCE = "raw rclpy publisher.publish(bytes) of the same CDR, same participant, same run"


def topic_of(kind: str, size: int) -> str:
    return f"/bench/ros2pub/{kind}{size}"


def wire_topic(kind: str, size: int) -> str:
    """Where a case's messages travel: the managed one's on ``[topic]/optimized``."""
    topic = topic_of(kind, size)
    return f"{topic}/optimized" if kind == "managed" else topic


def percentile_us(samples_ns: list[int], q: float) -> float | None:
    if not samples_ns:
        return None
    return round(float(np.percentile(samples_ns, q)) / 1e3, 1)


# -- the subscriber process -----------------------------------------------------------------------


def run_sink(topics: list[str]) -> None:
    """Count raw messages per topic; on ``flush <id>`` (stdin), once quiet, print the counts."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from dbml.harness.ros2node import PrivateRos

    ros = PrivateRos(domain_id=None, name="sink", events=True)  # ROS_DOMAIN_ID
    node = ros.node("bench_sink")
    lock = threading.Lock()
    counts = dict.fromkeys(topics, 0)
    last = [time.monotonic()]
    qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=SINK_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT
    )
    for topic in topics:

        def on_message(_data: bytes, topic: str = topic) -> None:
            with lock:
                counts[topic] += 1
                last[0] = time.monotonic()

        node.create_subscription(Image, topic, on_message, qos, raw=True)
    ros.start()
    try:
        print(json.dumps({"ready": True}), flush=True)
        stop = threading.Event()
        control = Control(stop).start()  # ``flush <id>`` commands until ``stop`` or EOF
        while not stop.is_set():
            try:
                command, _, ident = control.commands.get(timeout=0.1).partition(" ")
            except queue.Empty:
                continue
            if command != "flush":
                continue
            while True:
                with lock:
                    quiet = time.monotonic() - last[0]
                if quiet >= QUIET_S:
                    break
                time.sleep(QUIET_S - quiet)
            with lock:
                report = {"id": ident, "counts": dict(counts)}
                for topic in counts:
                    counts[topic] = 0
            print(json.dumps(report), flush=True)
    finally:
        ros.close()


class Sink:
    """The sink process (a ``Supervisor``'s child), its stdout read line by line; ended by PID."""

    def __init__(self, topics: list[str], env: dict[str, str]) -> None:
        self._children = Supervisor()
        self._sink = self._children.start(
            "sink", [sys.executable, __file__, "--sink", ",".join(topics)], env=env
        )
        self._ids = itertools.count()

    @property
    def pid(self) -> int:
        return self._sink.pid

    def next_line(self, timeout_s: float, accept: Callable[[dict[str, Any]], bool]) -> Any:
        for report in self._children.reports("sink", timeout_s=timeout_s):
            if accept(report):
                return report
        raise SystemExit(f"the sink process did not answer within {timeout_s:g} s")

    def flush(self) -> dict[str, int]:
        """What reached the sink since the last flush, per topic (once the sink went quiet)."""
        ident = str(next(self._ids))
        self._sink.send(f"flush {ident}")
        line = self.next_line(FLUSH_S, lambda doc: doc.get("id") == ident)
        return {str(k): int(v) for k, v in line["counts"].items()}

    def stop(self) -> None:
        """``stop`` and EOF (its cue to close its context), then SIGTERM and SIGKILL."""
        self._children.close()


# -- the publishers -------------------------------------------------------------------------------


class Cases:
    """The three publishers per size, on the transport's own node (one participant)."""

    def __init__(self, transport: Any) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        from dbml.transports.registry import camera_frame

        self._image = Image
        self.transport = transport
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=PUBLISH_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        self.raw: dict[tuple[str, int], Any] = {}
        self.managed: dict[int, ManagedPublisher] = {}
        self.payloads: dict[int, bytes] = {}
        for size in PAYLOADS:
            for kind in ("raw_bytes", "raw_msg"):
                self.raw[kind, size] = transport.node.create_publisher(
                    Image, topic_of(kind, size), qos
                )
            topic = topic_of("managed", size)
            self.payloads[size] = camera_frame(transport, "rclpy", topic, size)  # as `dbml publish`
            # No optimizer runs here: the allocation is written as the optimizer's would be
            # (min = max, so the limiter never drops), and the fail-safe is kept quiet.
            self.managed[size] = ManagedPublisher(
                transport,
                topic,
                min_rate_hz=UNLIMITED_HZ,
                max_rate_hz=UNLIMITED_HZ,
                failsafe_periods=1e9,
            )
            transport.params.set(names.current_value(topic), UNLIMITED_HZ)

    def wait_matched(self) -> None:
        """Until every publisher has the sink's subscription (the graph as the RMW sees it)."""
        deadline = time.monotonic() + MATCH_S
        matched: list[tuple[str, Callable[[], object]]] = []
        for (kind, size), publisher in self.raw.items():
            matched.append((topic_of(kind, size), partial(publisher.get_subscription_count)))
        for size, managed in self.managed.items():
            optimized = managed._switch.publisher  # dbml's publisher of [topic]/optimized
            matched.append(
                (wire_topic("managed", size), partial(getattr, optimized, "has_subscribers"))
            )
        for topic, has_subscribers in matched:
            while not has_subscribers():
                if time.monotonic() >= deadline:
                    raise SystemExit(f"no subscriber to {topic} within {MATCH_S:g} s")
                time.sleep(0.02)

    def call(self, kind: str, size: int) -> Callable[[], object]:
        """One publish of ``kind`` (the callable the loop times)."""
        payload = self.payloads[size]
        if kind == "raw_bytes":
            return partial(self.raw[kind, size].publish, payload)
        if kind == "managed":
            return partial(self.managed[size].publish, payload)
        publish = self.raw[kind, size].publish
        image = self._image
        pixels = bytes(size - 52)

        def build_and_publish() -> None:
            message = image(height=1, width=len(pixels), encoding="mono8", step=len(pixels))
            message.header.frame_id = "camera"
            message.data = pixels
            publish(message)

        return build_and_publish

    def close(self) -> None:
        for managed in self.managed.values():
            managed.close()
        for publisher in self.raw.values():
            self.transport.node.destroy_publisher(publisher)


def time_case(call: Callable[[], object], seconds: float) -> tuple[int, float, int, list[int]]:
    """Calls, elapsed s, calls that returned False (a managed drop), and each call's ns."""
    clock = time.perf_counter_ns
    durations: list[int] = []
    record = durations.append
    dropped = count = 0
    start = clock()
    end = start + int(seconds * 1e9)
    now = start
    while now < end and count < MAX_COUNT:
        before = clock()
        result = call()
        now = clock()
        record(now - before)
        if result is False:
            dropped += 1
        count += 1
    return count, (now - start) / 1e9, dropped, durations


# -- profiling ------------------------------------------------------------------------------------


def profile_managed(cases: Cases, size: int) -> dict[str, Any]:
    """Where a managed publish's time goes: cProfile of it, then its parts timed alone."""
    call = cases.call("managed", size)
    for _ in range(1_000):
        call()
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(PROFILE_CALLS):
        call()
    profiler.disable()
    stats = pstats.Stats(profiler)
    raw_stats: dict[Any, Any] = stats.stats  # type: ignore[attr-defined]  # untyped in typeshed
    total_s = sum(entry[2] for entry in raw_stats.values())
    rows = sorted(raw_stats.items(), key=lambda item: item[1][2], reverse=True)[:PROFILE_TOP]
    top = [
        {
            "function": f"{Path(file).name}:{line}({func})" if line else func,
            "calls_per_publish": round(entry[1] / PROFILE_CALLS, 2),
            "own_us_per_publish": round(entry[2] / PROFILE_CALLS * 1e6, 2),
            "own_share": round(entry[2] / total_s, 3) if total_s else None,
        }
        for (file, line, func), entry in rows
    ]
    return {
        "cprofile_calls": PROFILE_CALLS,
        "cprofile_us_per_publish": round(total_s / PROFILE_CALLS * 1e6, 2),
        "cprofile_top_by_own_time": top,
        "parts_alone_mean_us": time_parts(cases, size),
    }


def time_parts(cases: Cases, size: int) -> dict[str, float]:
    """Mean us of each part of a managed publish, timed alone; beside the whole and raw bytes.

    Each part runs ``PART_CALLS`` times between two looks at the clock, best of three.
    """
    managed = cases.managed[size]
    payload = cases.payloads[size]
    optimized: Any = managed._switch.publisher  # dbml's put to [topic]/optimized
    full = managed._full  # [topic]'s publisher, asked for local subscribers
    limiter = managed._limiter  # the rate limiter of [topic]/optimized
    parts: dict[str, Callable[[], object]] = {
        "managed publish (whole)": cases.call("managed", size),
        "raw publisher.publish(bytes)": cases.call("raw_bytes", size),
        "dbml put to [topic]/optimized (_RclpyPublisher.put)": partial(optimized.put, payload),
        "rclpy publish(bytes) on [topic]/optimized": partial(
            optimized._publisher.publish,
            payload,
        ),
        "[topic].has_subscribers (rclpy get_subscription_count)": (
            (lambda: full.has_subscribers) if full is not None else (lambda: None)
        ),
        "RateLimiter.allow(now)": lambda: limiter.allow(cases.transport.now()),
        "pack_meta(seq, time.time_ns(), rate)": lambda: pack_meta(1, time.time_ns(), 1.0),
        "transport.now()": cases.transport.now,
        "an empty Python call (the timing loop's own cost)": lambda: None,
    }
    result: dict[str, float] = {}
    for name, call in parts.items():
        best = float("inf")
        for _ in range(3):
            start = time.perf_counter_ns()
            for _ in range(PART_CALLS):
                call()
            best = min(best, (time.perf_counter_ns() - start) / PART_CALLS)
        result[name] = round(best / 1e3, 3)
    return result


# -- the run --------------------------------------------------------------------------------------


@contextlib.contextmanager
def ros2_domain(workdir: Path) -> Iterator[tuple[int, dict[str, str]]]:
    """A claimed domain and its child environment; this process joins it the same way."""
    with claim_domain() as domain_id:
        env = ros2_child_env(domain_id=domain_id, log_dir=workdir / "ros-log")
        saved = dict(os.environ)
        os.environ.update(env)  # this process's rclpy: the same domain, logs and profile
        try:
            yield domain_id, env
        finally:
            os.environ.clear()
            os.environ.update(saved)


def measure(seconds: float, repeat: int, *, profile: bool) -> dict[str, Any]:
    from dbml.transports.rclpy import RclpyTransport

    topics = [wire_topic(kind, size) for size in PAYLOADS for kind in KINDS]
    with (
        tempfile.TemporaryDirectory(prefix="dbml-ros2pub-") as tmp,
        ros2_domain(Path(tmp)) as (domain_id, env),
    ):
        transport = RclpyTransport(host="bench", domain_id=domain_id)
        sink: Sink | None = None
        cases: Cases | None = None
        shm: list[Path] = []
        try:
            sink = Sink(topics, env)
            sink.next_line(READY_S, lambda doc: doc.get("ready") is True)
            shm = fastdds_shm_files([sink.pid])
            cases = Cases(transport)
            cases.wait_matched()
            best: dict[tuple[int, str], float] = {}
            delivered: dict[tuple[int, str], float] = {}
            durations: dict[tuple[int, str], list[int]] = {}
            dropped = dict.fromkeys(PAYLOADS, 0)
            order = list(KINDS)
            for rep in range(repeat + 1):  # the first round warms up and is not counted
                length = seconds if rep else min(seconds, 0.3)
                for size in PAYLOADS:
                    for kind in order:
                        sink.flush()  # the previous case drained: start from a quiet sink
                        count, elapsed, lost, calls = time_case(cases.call(kind, size), length)
                        arrived = sink.flush()[wire_topic(kind, size)]
                        if not rep:
                            continue
                        durations.setdefault((size, kind), []).extend(calls)
                        if kind == "managed":
                            dropped[size] += lost
                        rate = count / elapsed
                        if rate > best.get((size, kind), 0.0):
                            best[size, kind] = rate
                            delivered[size, kind] = arrived / (count - lost) if count > lost else 0
                order = order[1:] + order[:1]  # rotate who goes first
            results = []
            for size in PAYLOADS:
                ratio = best[size, "managed"] / best[size, "raw_bytes"]
                row: dict[str, Any] = {"payload_bytes": size}
                for kind in KINDS:
                    row[f"{kind}_msgs_per_s"] = round(best[size, kind])
                row["ratio_managed_raw_bytes"] = round(ratio, 3)
                row["ratio_raw_msg_raw_bytes"] = round(
                    best[size, "raw_msg"] / best[size, "raw_bytes"], 3
                )
                row["meets_target"] = ratio >= TARGET_RATIO
                row["managed_overhead_us_per_msg"] = round(
                    1e6 / best[size, "managed"] - 1e6 / best[size, "raw_bytes"], 2
                )
                for kind in KINDS:
                    row[f"{kind}_p50_us"] = percentile_us(durations[size, kind], 50)
                    row[f"{kind}_p99_us"] = percentile_us(durations[size, kind], 99)
                for kind in KINDS:
                    row[f"{kind}_delivered"] = round(delivered[size, kind], 3)
                row["managed_dropped"] = dropped[size]
                if profile or ratio < TARGET_RATIO:
                    row["profile"] = profile_managed(cases, size)
                results.append(row)
        finally:
            if cases is not None:
                cases.close()
            if sink is not None:
                sink.stop()
            transport.close()
            remove_fastdds_shm(shm)  # only what the sink left, should it have been killed
    return {
        "benchmark": "ros2_publish",
        "transport": "rclpy",
        "reference": REFERENCE,
        "target": f"managed / raw_bytes >= {TARGET_RATIO}",
        "timing": (
            f"messages/s over {seconds:g} s per case, best of {repeat}, back to back, the three "
            "interleaved (rotating who goes first), to one raw best-effort subscriber in another "
            "process; p50/p99 of every call of the counted rounds, each timed alone (two "
            "perf_counter_ns reads in every case; raw_msg: build + publish); a first short round "
            "warms up and is not counted"
        ),
        "domain_id": domain_id,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "results": results,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--seconds", type=float, default=1.5, help="duration of one case")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many runs")
    parser.add_argument(
        "--profile",
        action="store_true",
        help="profile the managed publish even where it meets the target",
    )
    parser.add_argument("--sink", metavar="TOPICS", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.sink is not None:
        run_sink([t for t in args.sink.split(",") if t])
        return
    if not 0 < args.seconds <= 5 or not 1 <= args.repeat <= 5:
        parser.error("--seconds must be within (0, 5] and --repeat within [1, 5]")
    document = measure(args.seconds, args.repeat, profile=args.profile)
    if args.json:
        print(json.dumps(document))
        return
    table = Table(title="managed publish vs raw rclpy publish (messages/s, best of runs)")
    columns = ("payload B", "raw bytes", "raw msg", "managed", "ratio", "p50/p99 us (b/m/mgd)")
    for name in columns:
        table.add_column(name, justify="right")
    for r in document["results"]:
        table.add_row(
            f"{r['payload_bytes']:,}",
            f"{r['raw_bytes_msgs_per_s']:,}",
            f"{r['raw_msg_msgs_per_s']:,}",
            f"{r['managed_msgs_per_s']:,}",
            f"{r['ratio_managed_raw_bytes']:.2f}",
            " / ".join(f"{r[f'{k}_p50_us']}/{r[f'{k}_p99_us']}" for k in KINDS),
        )
    table.caption = f"target: {document['target']}; reference: {REFERENCE}"
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
