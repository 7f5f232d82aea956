"""Publish overhead: a managed publisher's ``publish`` against a raw zenoh ``put``, messages/s.

Same run, same zenoh session (shared memory off), same payloads (64 B and 84,000 B), same
congestion control as dbml's publishers (drop). The reference is a raw ``zenoh.Publisher.put``
on a key of its own; the managed side is ``ManagedPublisher.publish`` with min = max = the
largest rate dbml accepts (``MAX_RATE_HZ``, 1 MHz, above what either side reaches here), so
its rate limiter never drops (every ``publish`` must return True; ``dropped`` counts those that
did not) and it pays for everything else: the rate in force, size tracking, the 24-byte metadata
attachment and the put to ``[topic]/optimized``. A subscriber in another process (this script in
its ``--sink`` mode, on loopback) receives both keys, so every put really leaves the process; it
counts what arrives, reported as the delivered fraction (zenoh drops what its queue cannot take).
Each case runs for a fixed duration, raw and managed interleaved, best of ``--repeat``. Prints
JSON with ``--json``, a table then the JSON otherwise.

    python bench/publish_overhead.py [--json] [--seconds 1.5] [--repeat 3]
"""

from __future__ import annotations

import argparse
import itertools
import json
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
from rich.console import Console
from rich.table import Table

from dbml.core.spec import MAX_RATE_HZ
from dbml.harness.child import Control
from dbml.harness.supervisor import Supervisor
from dbml.protocol import names
from dbml.runtime import ManagedPublisher
from dbml.transports.zenoh import ZenohTransport

PAYLOADS = (64, 84_000)
UNLIMITED_HZ = MAX_RATE_HZ
BATCH = 64
"""Messages between two looks at the clock."""
MAX_COUNT = 20_000_000
"""Upper bound on the messages of one case, whatever the duration."""
FLUSH_KEY = "bench/overhead/flush"
READY_S = 20.0
MATCH_S = 10.0
FLUSH_S = 10.0
STOP_S = 10.0


def raw_key(size: int) -> str:
    return f"bench/overhead/raw{size}"


def managed_topic(size: int) -> str:
    return f"/bench/overhead/managed{size}"


def optimized_key(size: int) -> str:
    return managed_topic(size)[1:] + "/optimized"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


# -- the remote subscriber ------------------------------------------------------------------------


def run_sink(port: int, keys: list[str]) -> None:
    """Count samples per key; on a flush, print the counts since the last one (JSON line).

    Runs until stdin closes. Zenoh delivers a link's samples in order, so a flush (sent with
    congestion control block) arrives after every sample put before it that was not dropped.
    """
    transport = ZenohTransport(host="sink", port=port)
    lock = threading.Lock()
    counts = dict.fromkeys(keys, 0)
    try:
        declared: list[Any] = []
        for key in keys:

            def on_sample(_sample: Any, key: str = key) -> None:
                with lock:
                    counts[key] += 1

            declared.append(transport.session.declare_subscriber(key, on_sample))

        def on_flush(sample: Any) -> None:
            with lock:
                report = {"id": sample.payload.to_bytes().decode(), "counts": dict(counts)}
                for key in counts:
                    counts[key] = 0
            print(json.dumps(report), flush=True)

        declared.append(transport.session.declare_subscriber(FLUSH_KEY, on_flush))
        print(json.dumps({"ready": True}), flush=True)
        stop = threading.Event()
        Control(stop).start()
        stop.wait()  # until the parent says stop, or closes our stdin
    finally:
        transport.close()


class Sink:
    """The sink process (a ``Supervisor``'s child), its stdout read line by line; ended by PID."""

    def __init__(self, port: int, keys: list[str]) -> None:
        self._children = Supervisor()
        self._children.start(
            "sink", [sys.executable, __file__, "--sink", str(port), "--sink-keys", ",".join(keys)]
        )
        self._ids = itertools.count()

    def next_line(self, timeout_s: float, accept: Callable[[dict[str, Any]], bool]) -> Any:
        for report in self._children.reports("sink", timeout_s=timeout_s):
            if accept(report):
                return report
        raise SystemExit(f"the sink process did not answer within {timeout_s:g} s")

    def flush(self, session: Any) -> dict[str, int]:
        """What reached the sink since the last flush, per key."""
        ident = str(next(self._ids))
        session.put(FLUSH_KEY, ident.encode(), congestion_control=zenoh.CongestionControl.BLOCK)
        line = self.next_line(FLUSH_S, lambda doc: doc.get("id") == ident)
        return {str(k): int(v) for k, v in line["counts"].items()}

    def stop(self) -> None:
        """``stop`` and EOF on its stdin (its cue to close its session), then SIGTERM, SIGKILL."""
        self._children.close()


def wait_matching(session: Any, key: str, publisher: Any | None = None) -> None:
    """Until ``key`` has a subscriber this session knows of (a probe publisher if none given)."""
    probe = publisher if publisher is not None else session.declare_publisher(key)
    matched = threading.Event()
    listener = probe.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        if not (probe.matching_status.matching or matched.wait(MATCH_S)):
            raise SystemExit(f"no subscriber to {key} within {MATCH_S:g} s")
    finally:
        listener.undeclare()
        if publisher is None:
            probe.undeclare()


# -- timing ---------------------------------------------------------------------------------------


def time_raw(put: Callable[[bytes], object], payload: bytes, seconds: float) -> tuple[int, float]:
    count = 0
    start = time.perf_counter()
    end = start + seconds
    while count < MAX_COUNT:
        for _ in range(BATCH):
            put(payload)
        count += BATCH
        if time.perf_counter() >= end:
            break
    return count, time.perf_counter() - start


def time_managed(
    publish: Callable[[bytes], bool], payload: bytes, seconds: float
) -> tuple[int, float, int]:
    count = dropped = 0
    start = time.perf_counter()
    end = start + seconds
    while count < MAX_COUNT:
        for _ in range(BATCH):
            if not publish(payload):
                dropped += 1
        count += BATCH
        if time.perf_counter() >= end:
            break
    return count, time.perf_counter() - start, dropped


def measure(seconds: float, repeat: int) -> list[dict[str, Any]]:
    port = free_port()
    # This session first, so it holds the loopback rendezvous; shared memory is off by default.
    transport = ZenohTransport(host="bench", port=port)
    keys = [k for size in PAYLOADS for k in (raw_key(size), optimized_key(size))]
    sink: Sink | None = None
    raws: dict[int, Any] = {}
    manageds: dict[int, ManagedPublisher] = {}
    try:
        sink = Sink(port, keys)
        sink.next_line(READY_S, lambda doc: doc.get("ready") is True)
        session = transport.session
        for size in PAYLOADS:
            raws[size] = session.declare_publisher(
                raw_key(size), congestion_control=zenoh.CongestionControl.DROP
            )
            # No optimizer runs here: the allocation is written as one would (min = max), and
            # the fail-safe (no allocation heard again) is kept quiet.
            manageds[size] = ManagedPublisher(
                transport,
                managed_topic(size),
                min_rate_hz=UNLIMITED_HZ,
                max_rate_hz=UNLIMITED_HZ,
                failsafe_periods=1e9,
            )
            transport.params.set(names.current_value(managed_topic(size)), UNLIMITED_HZ)
            wait_matching(session, raw_key(size), raws[size])
            wait_matching(session, optimized_key(size))

        best: dict[tuple[int, str], float] = {}
        delivered: dict[tuple[int, str], float] = {}
        dropped = dict.fromkeys(PAYLOADS, 0)
        for rep in range(repeat + 1):  # the first round warms up and is not counted
            length = seconds if rep else min(seconds, 0.2)
            for size in PAYLOADS:
                payload = bytes(size)
                cases = [("raw", raw_key(size)), ("managed", optimized_key(size))]
                for kind, key in cases if rep % 2 else cases[::-1]:  # alternate who goes first
                    sink.flush(session)  # the previous case drained: start from a quiet link
                    if kind == "raw":
                        count, elapsed = time_raw(raws[size].put, payload, length)
                        lost = 0
                    else:
                        count, elapsed, lost = time_managed(manageds[size].publish, payload, length)
                    arrived = sink.flush(session)[key]
                    if not rep:
                        continue
                    dropped[size] += lost
                    rate = count / elapsed
                    if rate > best.get((size, kind), 0.0):
                        best[size, kind] = rate
                        delivered[size, kind] = arrived / (count - lost) if count > lost else 0.0
    finally:
        for managed in manageds.values():
            managed.close()
        for raw in raws.values():
            raw.undeclare()
        if sink is not None:
            sink.stop()
        transport.close()

    return [
        {
            "payload_bytes": size,
            "raw_msgs_per_s": round(best[size, "raw"]),
            "managed_msgs_per_s": round(best[size, "managed"]),
            "ratio": round(best[size, "managed"] / best[size, "raw"], 3),
            "dropped": dropped[size],
            "raw_delivered": round(delivered[size, "raw"], 3),
            "managed_delivered": round(delivered[size, "managed"], 3),
        }
        for size in PAYLOADS
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--seconds", type=float, default=1.5, help="duration of one case")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many runs")
    parser.add_argument("--sink", type=int, metavar="PORT", help=argparse.SUPPRESS)
    parser.add_argument("--sink-keys", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.sink is not None:
        run_sink(args.sink, [k for k in args.sink_keys.split(",") if k])
        return
    if not 0 < args.seconds <= 5 or not 1 <= args.repeat <= 5:
        parser.error("--seconds must be within (0, 5] and --repeat within [1, 5]")
    results = measure(args.seconds, args.repeat)
    document = {
        "benchmark": "publish_overhead",
        "reference": "raw zenoh Publisher.put (congestion control drop), same session, same run",
        "timing": (
            f"messages/s over {args.seconds:g} s per case, best of {args.repeat}, raw and managed "
            "interleaved (alternating which goes first), to a subscriber in another process on "
            "loopback, shared memory off; a first short round warms up and is not counted"
        ),
        "results": results,
    }
    if args.json:
        print(json.dumps(document))
        return
    table = Table(title="managed publish vs raw zenoh put (messages/s, best of runs)")
    for name in ("payload B", "raw msg/s", "managed msg/s", "ratio", "dropped", "delivered"):
        table.add_column(name, justify="right")
    for r in results:
        table.add_row(
            f"{r['payload_bytes']:,}",
            f"{r['raw_msgs_per_s']:,}",
            f"{r['managed_msgs_per_s']:,}",
            f"{r['ratio']:.2f}",
            str(r["dropped"]),
            f"{r['raw_delivered']:.0%} / {r['managed_delivered']:.0%}",
        )
    table.caption = "delivered: raw / managed share that reached the sink process"
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
