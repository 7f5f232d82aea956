"""`rostopic hz` against the allocation, during `dbml demo teleop --transport ros1`.

This starts a ROS master, runs the demo on it (the optimizer, R1, R2 and the operator as nodes on
ROS hosts 127.0.0.1-4), and beside it `rostopic hz -w WINDOW` on `/r1/camera/optimized` and
`/r2/camera/optimized`: ROS's own tool, a subscriber of its own, counting what the robots send.
It also follows each topic's `[topic]/dbm/frequency/current_value` on the parameter server. For
every stretch of constant allocation, the last `rostopic hz` average whose whole window lies inside
the stretch (after 1 s to settle) is compared with the allocation: the reference. Needs ROS 1
(scripts/install-ros1). Prints JSON with ``--json``, a table then the JSON otherwise.

    python bench/ros1_hz.py [--json] [--step-seconds 10] [--window 10]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from typing import Any

from rich.console import Console
from rich.table import Table

from dbml.harness.processes import foreign_interpreter_env
from dbml.harness.rosmaster import RosMaster
from dbml.harness.supervisor import Supervisor
from dbml.protocol import names
from dbml.scenarios.teleop import ROBOTS
from dbml.transports.ros1.master import MasterClient

SETTLE_S = 1.0
TOLERANCE = 0.05
READ_S = 1.0
"""How long one read of ``rostopic hz``'s output waits before looking again."""


class HzReader:
    """``rostopic hz -w window topic`` (a ``Supervisor``'s child), its averages time-stamped."""

    def __init__(self, topic: str, window: int, env: dict[str, str]) -> None:
        self.topic = topic
        self.readings: list[tuple[float, float, int]] = []  # (time, Hz, messages in window)
        self._children = Supervisor()
        self._hz = self._children.start(
            "rostopic-hz",
            ["rostopic", "hz", "-w", str(window), topic],
            env=foreign_interpreter_env(env),  # Debian's /usr/bin/python3, not ours
            stdin=False,
            stop_signal=signal.SIGINT,  # as rostopic expects
        )
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        rate: float | None = None
        while (line := self._hz.next(timeout_s=READ_S)) is None or not line.ended:
            if line is None:
                continue
            if match := re.search(r"average rate: ([0-9.]+)", line.text):
                rate = float(match.group(1))
            elif (match := re.search(r"window: (\d+)", line.text)) and rate is not None:
                self.readings.append((time.time(), rate, int(match.group(1))))

    def stop(self) -> None:
        self._children.close()
        self._thread.join(timeout=5)


def follow_allocations(
    client: MasterClient, topics: list[str], stop: threading.Event
) -> dict[str, list[tuple[float, float]]]:
    """Each topic's allocation changes, (time, Hz), read from the parameter server at 20 Hz."""
    changes: dict[str, list[tuple[float, float]]] = {t: [] for t in topics}
    while not stop.wait(0.05):
        for topic in topics:
            value = client.call("getParam", names.current_value(topic), missing_ok=True)
            if isinstance(value, float) and (not changes[topic] or changes[topic][-1][1] != value):
                changes[topic].append((time.time(), value))
    return changes


def compare(
    changes: list[tuple[float, float]], readings: list[tuple[float, float, int]], window: int
) -> list[dict[str, Any]]:
    rows = []
    for k, (start, allocated) in enumerate(changes):
        end = changes[k + 1][0] if k + 1 < len(changes) else float("inf")
        span_s = window / allocated  # how far back a full window reaches
        inside = [
            (t, hz)
            for t, hz, n in readings
            if n >= window and start + SETTLE_S + span_s <= t <= end
        ]
        if not inside:
            continue  # too short a stretch for a full window at this rate
        t, hz = inside[-1]
        rows.append(
            {
                "allocated_hz": allocated,
                "rostopic_hz": hz,
                "error_pct": 100 * (hz - allocated) / allocated,
                "seconds_into_stretch": t - start,
            }
        )
    return rows


def measure(step_s: float, window: int) -> dict[str, Any]:
    topics = [camera.topic for camera in ROBOTS]
    with RosMaster() as master, MasterClient(master.uri) as client:
        env = dict(os.environ, ROS_MASTER_URI=master.uri)
        readers = [HzReader(f"{topic}/optimized", window, env) for topic in topics]
        stop = threading.Event()
        followed: dict[str, list[tuple[float, float]]] = {}
        follower = threading.Thread(
            target=lambda: followed.update(follow_allocations(client, topics, stop)), daemon=True
        )
        follower.start()
        argv = ["demo", "teleop", "--transport", "ros1", "--step-seconds", str(step_s), "--json"]
        try:
            demo = subprocess.run(
                [sys.executable, "-m", "dbml", *argv],
                env=env,
                capture_output=True,
                text=True,
                timeout=60 + 12 * step_s,
                check=False,
            )
        finally:
            stop.set()
            follower.join(timeout=5)
            for reader in readers:
                reader.stop()
    if demo.returncode not in (0, 1):
        raise SystemExit(f"demo failed ({demo.returncode}): {demo.stderr[-2000:]}")
    result = json.loads(demo.stdout)
    per_topic = {
        reader.topic: compare(followed.get(topic, []), reader.readings, window)
        for topic, reader in zip(topics, readers, strict=True)
    }
    errors = [abs(row["error_pct"]) for rows in per_topic.values() for row in rows]
    return {
        "benchmark": "ros1_rostopic_hz",
        "reference": "the allocated rate ([topic]/dbm/frequency/current_value)",
        "step_seconds": step_s,
        "window_messages": window,
        "demo_ok": result["ok"],
        "topics": per_topic,
        "compared": len(errors),
        "max_abs_error_pct": max(errors) if errors else None,
        "within_5pct": bool(errors) and max(errors) <= 100 * TOLERANCE,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--step-seconds", type=float, default=10.0, help="demo step (default 10)")
    parser.add_argument("--window", type=int, default=10, help="rostopic hz -w (default 10)")
    args = parser.parse_args()
    if args.window < 2 or args.step_seconds < 1:
        parser.error("--window must be >= 2 and --step-seconds >= 1")
    document = measure(args.step_seconds, args.window)
    if args.json:
        print(json.dumps(document))
        return
    table = Table(title=f"rostopic hz -w {args.window} vs the allocation, ros1 demo")
    for name in ("topic", "allocated Hz", "rostopic hz", "error %"):
        table.add_column(name, justify="right")
    for topic, rows in document["topics"].items():
        for row in rows:
            table.add_row(
                topic,
                f"{row['allocated_hz']:.3f}",
                f"{row['rostopic_hz']:.3f}",
                f"{row['error_pct']:+.2f}",
            )
    table.caption = (
        f"max |error| {document['max_abs_error_pct']:.2f} % over {document['compared']} stretches"
        if document["compared"]
        else "nothing compared"
    )
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
