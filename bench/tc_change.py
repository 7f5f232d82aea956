"""What one ``tc qdisc change`` of the testbed's shaped link costs, and how soon it takes effect.

The testbed (``dbml.testbed.netns.Network``, one robot) shapes the router's egress toward the
operator with tbf; ``Network.set_link_rate`` changes it with one ``tc qdisc change``, the call
the testbed's ``_change_link`` makes once per step of a link schedule. A UDP sender in r1's
namespace offers 1,200-byte datagrams at 30 Mbit/s (paced in bursts of about 1 ms), well above
the link, so the tbf queue stays full and the receiver in the operator's namespace sees exactly
the shaped rate. The receiver stamps every datagram with the kernel's receive time
(``SO_TIMESTAMPNS``, CLOCK_REALTIME, which every namespace of one machine shares); this process
stamps each ``set_link_rate`` with ``time.time()`` before and after.

The link runs at 11 Mbit/s for ``--warmup`` seconds, then changes to 5 Mbit/s, holds ``--hold``
seconds, back to 11, holds; ``--changes`` such pairs. For each change:

- ``call_ms``: the wall time of ``set_link_rate`` (fork and exec of ``tc`` included, as the
  testbed makes it);
- ``effect_ms``: from the start of the call to the end of the first 20-ms bin (sliding, 1-ms
  steps) whose received rate (on-wire bytes, 1,242 a datagram: tbf counts the Ethernet frame)
  is within 10 % of the new rate, and stays there for 200 ms. The bin itself accounts for up to
  20 ms of it. A 20-ms bin holds only ten datagrams at 5 Mbit/s, so one late dequeue of tbf's
  timer can put a bin outside the band at any time: ``first_in_band_ms`` (the first such bin,
  no stay) and ``steady_bins_outside_band`` (the share of bins outside the band from 0.5 s after
  a change on, when nothing changes) tell that noise from a slow change.

Per direction: count, call ms (p50, max), effect ms (p50, max), and ``share_of_200ms_step``: p50
call ms / 200, the step of recorded traces (OpenNetLab gym) that the testbed would replay one
``set_link_rate`` each. Also the received steady rates and the one-way delay (tbf's queue)
at the end of each hold, and ``--calls`` back-to-back ``set_link_rate`` calls (alternating
11 and 10 Mbit/s) with no traffic: p50/p99/max ms. Prints one JSON object; progress to stderr.
Needs root; about a minute with the defaults:

    sudo .venv/bin/python bench/tc_change.py [--changes 10] [--hold 2] [--warmup 2] [--calls 100]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import selectors
import socket
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dbml.testbed.netns import Network

HIGH_MBIT = 11.0
"""The paper's link."""
LOW_MBIT = 5.0
B2B_MBIT = (10.0, 11.0)
"""Back-to-back calls alternate these (starting from the link's 11)."""
DATAGRAM_BYTES = 1200
WIRE_BYTES = DATAGRAM_BYTES + 8 + 20 + 14
"""What tbf charges for one datagram: UDP, IPv4 and Ethernet headers (veth has no FCS)."""
OFFERED_MBIT = 30.0
BURST_MAX = 16
"""At most this many datagrams in one burst, however late the sender's timer."""
PORT = 47_011
BIN_S = 0.020
GRID_S = 0.001
TOLERANCE = 0.10
STAY_S = 0.200
TRACE_STEP_MS = 200.0
"""One step of a recorded trace (OpenNetLab gym): one ``set_link_rate`` each."""
READY_TIMEOUT_S = 15.0
IDLE_S = 1.0
"""The receiver stops once nothing has arrived for this long (the queue drains in < 0.5 s)."""
EXIT_TIMEOUT_S = 3.0
HEADER = struct.Struct("!qq")
"""Sequence number, send time (ns, CLOCK_REALTIME)."""
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
"""Linux's value; Python 3.11's socket module lacks the name."""
TIMESPEC = struct.Struct("@qq")


# -- the two roles run inside the namespaces (stdlib only, so they start fast) ------------------


def _sender(to: str, port: int, offered_mbit: float, max_seconds: float) -> int:
    """Print READY, read ``start until`` (epoch s) on stdin, then send at the offered rate."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect((to, port))
    pad = bytes(DATAGRAM_BYTES - HEADER.size)
    print("READY", flush=True)
    line = sys.stdin.readline().split()  # "" if the parent went away: nothing to do
    if len(line) != 2:
        return 1
    start, until = float(line[0]), float(line[1])
    until = min(until, time.time() + max_seconds)
    pps = offered_mbit * 1e6 / (DATAGRAM_BYTES * 8)
    limit = math.ceil(pps * max(0.0, until - start)) + 1
    time.sleep(min(max(0.0, start - time.time()), max_seconds))
    start = time.time()
    sent = errors = 0
    while sent < limit:
        now = time.time()
        if now >= until:
            break
        due = min(int((now - start) * pps) + 1, limit, sent + BURST_MAX)
        while sent < due:
            try:
                sock.send(HEADER.pack(sent, time.time_ns()) + pad)
            except OSError:  # ENOBUFS and the like: a lost datagram, as on a real radio
                errors += 1
            sent += 1
        time.sleep(0.001)
    sock.close()
    print(f"sender: {sent} datagrams offered, {errors} send errors", file=sys.stderr)
    return 0


def _receiver(port: int, max_seconds: float) -> int:
    """Print READY, receive until idle (or ``max_seconds``), print arrivals as JSON."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind(("", port))
    sock.settimeout(0.2)
    arrivals: list[int] = []
    seqs: list[int] = []
    sent: list[int] = []
    kernel = 0
    print("READY", flush=True)
    deadline = time.time() + max_seconds
    limit = int(max_seconds * 20_000)
    last: float | None = None
    while len(arrivals) < limit:
        now = time.time()
        if now > deadline or (last is not None and now - last > IDLE_S):
            break
        try:
            data, ancillary, _flags, _addr = sock.recvmsg(2048, socket.CMSG_SPACE(TIMESPEC.size))
        except TimeoutError:
            continue
        last = time.time()
        stamp = time.time_ns()
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                seconds, nanos = TIMESPEC.unpack(value[: TIMESPEC.size])
                stamp = seconds * 1_000_000_000 + nanos
                kernel += 1
        if len(data) < HEADER.size:
            continue
        seq, sent_ns = HEADER.unpack_from(data)
        arrivals.append(stamp)
        seqs.append(seq)
        sent.append(sent_ns)
    sock.close()
    json.dump({"arrival_ns": arrivals, "seq": seqs, "sent_ns": sent, "kernel": kernel}, sys.stdout)
    sys.stdout.write("\n")
    return 0


# -- the parent: builds the network, drives the changes, analyses -------------------------------


def _log(message: str) -> None:
    print(f"tc_change: {message}", file=sys.stderr, flush=True)


def _end(proc: subprocess.Popen[bytes]) -> None:
    """End one process we started, by its PID: terminate, then kill."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(EXIT_TIMEOUT_S)


def _wait_ready(proc: subprocess.Popen[bytes], name: str) -> None:
    """Read the child's ``READY`` line from its stdout, within ``READY_TIMEOUT_S``."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    received = b""
    deadline = time.monotonic() + READY_TIMEOUT_S
    with selectors.DefaultSelector() as selector:
        selector.register(fd, selectors.EVENT_READ)
        while b"\n" not in received:
            left = deadline - time.monotonic()
            if left <= 0:
                raise RuntimeError(f"{name} not ready after {READY_TIMEOUT_S} s")
            if not selector.select(left):
                continue
            chunk = os.read(fd, 64)
            if not chunk:
                raise RuntimeError(f"{name} exited before it was ready (exit {proc.wait()})")
            received += chunk
    if received != b"READY\n":
        raise RuntimeError(f"{name} said {received!r} instead of READY")


def _timed_change(net: Network, mbit: float) -> tuple[float, float]:
    """``set_link_rate``, stamped with ``time.time()`` before and after."""
    before = time.time()
    net.set_link_rate(mbit)
    return before, time.time()


def _traffic(
    net: Network, args: argparse.Namespace, procs: list[subprocess.Popen[bytes]]
) -> tuple[list[dict[str, float]], dict[str, Any], float]:
    """Run receiver and sender, make the changes; the changes, the arrivals, the first change."""
    from dbml.testbed.netns import OPERATOR

    script = str(Path(__file__).resolve())
    max_s = args.warmup + 2 * args.changes * args.hold + 30.0
    receiver = subprocess.Popen(
        net.exec_argv(
            OPERATOR,
            [sys.executable, script, "--role", "receiver", "--port", str(PORT),
             "--max-seconds", str(max_s)],
        ),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
    )  # fmt: skip
    procs.append(receiver)
    _wait_ready(receiver, "receiver")
    sender = subprocess.Popen(
        net.exec_argv(
            "r1",
            [sys.executable, script, "--role", "sender", "--to", net.hosts[OPERATOR].address,
             "--port", str(PORT), "--offered-mbit", str(OFFERED_MBIT),
             "--max-seconds", str(max_s)],
        ),
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )  # fmt: skip
    procs.append(sender)
    _wait_ready(sender, "sender")
    assert sender.stdin is not None
    start = time.time() + 0.05
    first = start + args.warmup
    until = first + 2 * args.changes * args.hold
    sender.stdin.write(f"{start!r} {until!r}\n".encode())
    sender.stdin.flush()
    _log(
        f"traffic at {OFFERED_MBIT} Mbit/s offered; {args.changes} pairs "
        f"{HIGH_MBIT}->{LOW_MBIT}->{HIGH_MBIT} every {args.hold} s after {args.warmup} s"
    )
    changes: list[dict[str, float]] = []
    for index in range(2 * args.changes):
        at = first + index * args.hold
        time.sleep(min(max(0.0, at - time.time()), args.hold + 1.0))
        old = net.link_mbit
        new = LOW_MBIT if index % 2 == 0 else HIGH_MBIT
        before, after = _timed_change(net, new)
        changes.append({"old": old, "new": new, "start": before, "end": after})
        if index % 2 == 1:
            _log(
                f"pair {index // 2 + 1}/{args.changes}: last call {1000 * (after - before):.1f} ms"
            )
    time.sleep(min(max(0.0, until - time.time()), args.hold + 1.0))
    sender.wait(EXIT_TIMEOUT_S + 2.0)
    out, _ = receiver.communicate(timeout=IDLE_S + 10.0)
    arrivals: dict[str, Any] = json.loads(out)
    _log(f"{len(arrivals['arrival_ns'])} datagrams received ({arrivals['kernel']} kernel stamps)")
    return changes, arrivals, first


def _back_to_back(net: Network, calls: int) -> list[float]:
    """``calls`` ``set_link_rate`` calls, one after another, no traffic: each one's ms."""
    took: list[float] = []
    deadline = time.monotonic() + 60.0
    for index in range(calls):
        if time.monotonic() > deadline:
            break
        before = time.perf_counter()
        net.set_link_rate(B2B_MBIT[index % 2])
        took.append(1000 * (time.perf_counter() - before))
    return took


def _analyse(
    changes: list[dict[str, float]], arrivals: dict[str, Any], first: float, hold: float
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Per direction figures, and the steady rates, noise and delays that say the run was sound."""
    import numpy as np

    t = np.asarray(arrivals["arrival_ns"], dtype=np.int64)
    sent = np.asarray(arrivals["sent_ns"], dtype=np.int64)
    order = np.argsort(t, kind="stable")
    base_ns = int(first * 1e9) - 10**10
    ts = (t[order] - base_ns) / 1e9  # s from 10 s before the first change: float64 keeps ns
    delay_ms = (t[order] - sent[order]) / 1e6
    offset = base_ns / 1e9
    wire_mbit = WIRE_BYTES * 8 / 1e6
    stay = round(STAY_S / GRID_S)

    def bin_mbit(grid: Any) -> Any:
        """The received rate in the 20-ms bin ending at each grid point."""
        count = np.searchsorted(ts, grid, "right") - np.searchsorted(ts, grid - BIN_S, "right")
        return count * wire_mbit / BIN_S

    def mean_mbit(lo: float, hi: float) -> float:
        count = np.searchsorted(ts, hi) - np.searchsorted(ts, lo)
        return float(count * wire_mbit / (hi - lo)) if hi > lo else math.nan

    def median_delay(lo: float, hi: float) -> float:
        part = delay_ms[np.searchsorted(ts, lo) : np.searchsorted(ts, hi)]
        return float(np.median(part)) if part.size else math.nan

    steady: dict[float, list[float]] = {HIGH_MBIT: [], LOW_MBIT: []}
    noise: dict[float, list[float]] = {HIGH_MBIT: [], LOW_MBIT: []}
    delays: dict[float, list[float]] = {HIGH_MBIT: [], LOW_MBIT: []}
    steady[HIGH_MBIT].append(mean_mbit(first - offset - 1.5, first - offset))
    figures: dict[str, dict[str, list[Any]]] = {}
    for change in changes:
        start, end, new = change["start"] - offset, change["end"] - offset, change["new"]
        grid = start + GRID_S * np.arange(round(hold / GRID_S))
        outside = np.abs(bin_mbit(grid) - new) > TOLERANCE * new
        bad = np.concatenate(([0], np.cumsum(outside)))
        effect: float | None = None
        for k in range(grid.size - stay):
            if bad[k + stay + 1] == bad[k]:
                effect = round(1000 * (grid[k] - start), 1)
                break
        inside = np.flatnonzero(~outside)
        in_band = round(1000 * (grid[inside[0]] - start), 1) if inside.size else None
        settled = grid >= start + 0.5
        steady[new].append(mean_mbit(start + 0.5, start + hold - 0.05))
        noise[new].append(float(outside[settled].mean()))
        delays[new].append(median_delay(start + hold - 0.5, start + hold - 0.05))
        entry = figures.setdefault(
            f"{change['old']:g}->{new:g}", {"call": [], "effect": [], "in": []}
        )
        entry["call"].append(round(1000 * (end - start), 2))
        entry["effect"].append(effect)
        entry["in"].append(in_band)
    directions: dict[str, Any] = {}
    for name, entry in figures.items():
        call: list[float] = entry["call"]
        directions[name] = {
            "count": len(call),
            "call_ms": {"p50": round(statistics.median(call), 2), "max": max(call)},
            "effect_ms": _p50_max(entry["effect"]),
            "first_in_band_ms": _p50_max(entry["in"]),
            "share_of_200ms_step": round(statistics.median(call) / TRACE_STEP_MS, 4),
            "call_ms_each": call,
            "effect_ms_each": entry["effect"],
        }
    seqs = np.asarray(arrivals["seq"], dtype=np.int64)
    sound = {
        "datagrams_received": int(t.size),
        "kernel_timestamps": int(arrivals["kernel"]),
        "datagrams_offered": int(seqs.max()) + 1 if seqs.size else 0,
        "received_mbit_on_wire": _medians(steady, 3),
        "steady_bins_outside_band": _medians(noise, 4),
        "queue_delay_ms_p50_end_of_hold": _medians(delays, 1),
    }
    return directions, sound


def _p50_max(values: list[float | None]) -> dict[str, Any]:
    """p50 and max of the changes that reached it, and how many did not."""
    reached = [v for v in values if v is not None]
    return {
        "p50": round(statistics.median(reached), 1) if reached else None,
        "max": max(reached) if reached else None,
        "not_reached": len(values) - len(reached),
    }


def _medians(by_rate: dict[float, list[float]], digits: int) -> dict[str, float]:
    return {f"{mbit:g}": round(statistics.median(v), digits) for mbit, v in by_rate.items() if v}


def _percentiles(took: list[float]) -> dict[str, float]:
    import numpy as np

    values = np.asarray(took)
    return {
        "p50": round(float(np.percentile(values, 50)), 2),
        "p99": round(float(np.percentile(values, 99)), 2),
        "max": round(float(values.max()), 2),
    }


def _measure(args: argparse.Namespace) -> dict[str, Any]:
    from dbml.testbed.netns import Network, leftover_namespaces, privilege_problem

    problem = privilege_problem()
    if problem is not None:
        raise SystemExit(f"tc_change: {problem}")
    procs: list[subprocess.Popen[bytes]] = []
    with Network(robots=("r1",), link_mbit=HIGH_MBIT) as net:
        _log(f"network {net.run_id} built")
        try:
            changes, arrivals, first = _traffic(net, args, procs)
        finally:
            for proc in procs:
                _end(proc)
        _log(f"{args.calls} back-to-back calls, no traffic")
        took = _back_to_back(net, args.calls)
        run_id = net.run_id
    left = [name for name in leftover_namespaces() if run_id in name]
    directions, sound = _analyse(changes, arrivals, first, args.hold)
    return {
        "setup": {
            "link_mbit": [HIGH_MBIT, LOW_MBIT],
            "pairs": args.changes,
            "warmup_s": args.warmup,
            "hold_s": args.hold,
            "offered_mbit": OFFERED_MBIT,
            "datagram_bytes": DATAGRAM_BYTES,
            "wire_bytes": WIRE_BYTES,
            "bin_ms": 1000 * BIN_S,
            "tolerance": TOLERANCE,
            "stay_ms": 1000 * STAY_S,
            "call": "Network.set_link_rate (tc qdisc change ... tbf), wall ms",
            "effect": "call start -> end of first 20-ms bin within 10 % of the new rate for 200 ms",
            "first_in_band": "call start -> end of first 20-ms bin within 10 % of the new rate",
            "steady_bins_outside_band": "share of 20-ms bins outside 10 % from 0.5 s on, no change",
        },
        "directions": directions,
        "back_to_back": {"calls": len(took), "mbit": list(B2B_MBIT), "ms": _percentiles(took)},
        "reference": {
            "trace_step_ms": TRACE_STEP_MS,
            "testbed": "runner._change_link: one set_link_rate per schedule change",
        },
        "sound": sound | {"leftover_namespaces": left},
    }


def main(argv: list[str] | None = None) -> int:
    """Run one role (hidden, inside a namespace) or the whole measurement."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--changes", type=int, default=10, help="pairs 11->5->11 (default 10)")
    parser.add_argument("--hold", type=float, default=2.0, help="s after each change (default 2)")
    parser.add_argument("--warmup", type=float, default=2.0, help="s at 11 first (default 2)")
    parser.add_argument("--calls", type=int, default=100, help="back-to-back calls (default 100)")
    hidden = argparse.SUPPRESS
    parser.add_argument("--role", choices=("sender", "receiver"), help=hidden)
    parser.add_argument("--to", help=hidden)
    parser.add_argument("--port", type=int, default=PORT, help=hidden)
    parser.add_argument("--offered-mbit", type=float, default=OFFERED_MBIT, help=hidden)
    parser.add_argument("--max-seconds", type=float, default=120.0, help=hidden)
    args = parser.parse_args(argv)
    if args.role == "sender":
        return _sender(args.to, args.port, args.offered_mbit, args.max_seconds)
    if args.role == "receiver":
        return _receiver(args.port, args.max_seconds)
    if not (1 <= args.changes <= 100 and 0.5 <= args.hold <= 10 and 1 <= args.calls <= 10_000):
        parser.error("--changes 1-100, --hold 0.5-10 s, --calls 1-10000")
    if not 0.5 <= args.warmup <= 10:
        parser.error("--warmup 0.5-10 s")
    report = _measure(args)
    json.dump(report, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
