"""The no-flags mesh: how many dbml sessions on one machine still all reach each other.

With no flags, every dbml session is a zenoh peer that listens on loopback and meets the others
through one rendezvous port; gossip then links every pair, and zenoh peers send only over
direct links. For each size N this starts N ``ZenohTransport`` sessions with no flags
(``--per-process`` to a worker process, a private ``DBML_ZENOH_PORT``), and every
``POLL_S`` reads each session's direct links (``session.info.peers_zid()``); every session stays
open until ``--seconds`` after the last one opened. Per size:

- ``meshed_sessions``: the sessions that held all N - 1 links ``--seconds`` after the last
  opened (the reference: the full mesh, every session linked to every other);
- ``links_min`` / ``links_median``: the links the sessions held at the end;
- ``meshed_s``: from the last session's open until every session had held N - 1 links at a
  poll (null: not within ``--seconds``);
- ``warned``: the sessions that logged ``PEER_MESH_SESSIONS``'s warning.

    python bench/mesh.py [--sessions 20 40 60 70 80] [--seconds 30] [--per-process 10] [--json]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from typing import Any

POLL_S = 0.5
"""How often each worker reads its sessions' links."""
START_TIMEOUT_S = 120.0
"""Bound on the workers' sessions opening."""
STOP_TIMEOUT_S = 30.0
"""Bound on a worker closing its sessions."""
MAX_RUN_S = 900.0
"""A worker whose parent never says stop ends by itself."""
MESH_WARNING = "dbml sessions in zenoh's peer mesh"
"""Part of the warning ``dbml.transports.zenoh`` logs past ``PEER_MESH_SESSIONS``."""


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def worker(first: int, count: int) -> None:
    """Open ``count`` sessions; report their links every ``POLL_S`` until ``stop`` on stdin."""
    from dbml.transports.zenoh import ZenohTransport

    warned: list[str] = []

    class _Catch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if MESH_WARNING in record.getMessage():
                warned.append(record.getMessage())

    logging.getLogger("dbml").addHandler(_Catch())
    stop = threading.Event()

    def wait_for_stop() -> None:
        sys.stdin.readline()
        stop.set()

    threading.Thread(target=wait_for_stop, daemon=True).start()
    sessions = [ZenohTransport(host=f"m{first + i}") for i in range(count)]
    try:
        print(json.dumps({"opened": time.time()}), flush=True)
        deadline = time.monotonic() + MAX_RUN_S
        while not stop.wait(POLL_S) and time.monotonic() < deadline:
            links = [len(list(s.session.info.peers_zid())) for s in sessions]
            print(json.dumps({"t": time.time(), "links": links}), flush=True)
        print(json.dumps({"warned": len(warned)}), flush=True)
    finally:
        for session in sessions:
            session.close()


class _Worker:
    """One worker process and the JSON lines it printed (read on a thread of its own)."""

    def __init__(self, first: int, count: int, env: dict[str, str]) -> None:
        argv = [sys.executable, __file__, "--worker", str(first), str(count)]
        self.proc = subprocess.Popen(
            argv,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        self.rows: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.rows.append(json.loads(line))

    def opened(self) -> float | None:
        return next((r["opened"] for r in list(self.rows) if "opened" in r), None)

    def polls(self) -> list[tuple[float, list[int]]]:
        return [(r["t"], r["links"]) for r in list(self.rows) if "links" in r]

    def stop(self) -> int:
        """Ask it to close its sessions; its warnings counted (killed, by PID, if it hangs)."""
        try:
            assert self.proc.stdin is not None
            self.proc.stdin.write("stop\n")
            self.proc.stdin.flush()
            self.proc.wait(timeout=STOP_TIMEOUT_S)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        self._reader.join(timeout=STOP_TIMEOUT_S)
        return sum(r["warned"] for r in list(self.rows) if "warned" in r)


def measure(n: int, *, seconds: float, per_process: int) -> dict[str, Any]:
    """N sessions in ``ceil(n / per_process)`` workers; their links ``seconds`` after opening."""
    env = {**os.environ, "DBML_ZENOH_PORT": str(_free_port())}
    workers = [
        _Worker(first, min(per_process, n - first), env) for first in range(0, n, per_process)
    ]
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while any(w.opened() is None for w in workers) and time.monotonic() < deadline:
            time.sleep(POLL_S)
        opened = max((w.opened() or math.nan for w in workers), default=math.nan)
        time.sleep(seconds)  # the run: every session open, the workers polling
        # Each worker's first poll from now (a poll over busy sessions can take seconds).
        end = time.time()
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline and any(
            not any(t >= end for t, _ in w.polls()) for w in workers
        ):
            time.sleep(POLL_S)
        final = [
            links
            for w in workers
            for links in next((links for t, links in w.polls() if t >= end), [])
        ]
        done_at = [
            next((t for t, links in w.polls() if all(k == n - 1 for k in links)), math.inf)
            for w in workers
        ]
    finally:
        warned = sum(w.stop() for w in workers)
    meshed = all(math.isfinite(t) for t in done_at) and math.isfinite(opened)
    return {
        "sessions": n,
        "reported": len(final),
        "meshed_sessions": sum(k == n - 1 for k in final),
        "links_min": min(final, default=None),
        "links_median": statistics.median(final) if final else None,
        "links_full": n - 1,
        "meshed_s": round(max(max(done_at) - opened, 0.0), 2) if meshed else None,
        "warned": warned,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, nargs="+", default=[20, 40, 60, 70, 80])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--per-process", type=int, default=10)
    parser.add_argument("--json", action="store_true", help="JSON only")
    parser.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        first, count = args.worker
        worker(int(first), int(count))
        return
    results = [
        measure(n, seconds=args.seconds, per_process=args.per_process) for n in args.sessions
    ]
    document = {
        "benchmark": "peer_mesh",
        "reference": "the full mesh: every session directly linked to the other N - 1",
        "results": results,
    }
    if not args.json:
        for row in results:
            print(
                f"{row['sessions']:>4} sessions: {row['meshed_sessions']} of {row['reported']} "
                f"hold all {row['links_full']} links (min {row['links_min']}), meshed in "
                f"{row['meshed_s']} s; warned {row['warned']}"
            )
    print(json.dumps(document))


if __name__ == "__main__":
    main()
