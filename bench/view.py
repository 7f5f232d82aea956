"""The live view's cost per round, against the optimizer's own round, at 2 and at 320 channels.

One process, the memory transport: N managed channels (publishers on their own hosts, a remote
subscriber each), an optimizer, and the operator's ``LiveView`` writing to a real foxglove-sdk
sink (a WebSocket server with a client subscribed to every channel, and an MCAP recording). Each
round is ``OptimizerNode.optimize()`` (timed: the reference), then the view's look after it,
timed by the view itself (``LiveView.cost``). The view runs on its own thread, so its cost is
CPU taken beside the optimizer, not time added to a round: ``bench/reaction.py --foxglove``
measures whether it slows the reaction across processes.

    python bench/view.py [--rounds 50] [--channels 2 320] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from dbml import (
    DbmSettings,
    ManagedPublisher,
    ManagedSubscriber,
    MemoryNetwork,
    OptimizerNode,
    open_transport,
)
from dbml.protocol.schema import Writer
from dbml.view.client import FoxgloveClient
from dbml.view.live import LiveView, open_view
from dbml.view.target import ViewTarget

SIZES = (84_000, 21_000)
"""Table 2's two cameras, alternating."""
LOOK_TIMEOUT_S = 5.0
CONNECT_S = 5.0


def _wait(predicate: Any, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.001)
    return True


def measure(channels: int, rounds: int) -> dict[str, Any]:
    network = MemoryNetwork()
    publishers = []
    subscribers = []
    for i in range(channels):
        topic = f"/r{i + 1}/camera"
        publisher = ManagedPublisher(
            open_transport("memory", network=network, host=f"robot{i + 1}"),
            topic,
            min_rate_hz=1,
            max_rate_hz=16,
            priority=(i % 10) / 10,
        )
        publisher.publish(bytes(SIZES[i % 2]))
        publishers.append(publisher)
    operator = open_transport("memory", network=network, host="operator")
    for publisher in publishers:
        subscribers.append(ManagedSubscriber(operator, publisher.topic, lambda _s: None))
    optimizer = OptimizerNode(
        open_transport("memory", network=network, host="base"),
        settings=DbmSettings(max_bandwidth_mbit=11 * channels / 2),
        report_interval_s=0.0,  # every round reported: the view shows each one
    )
    optimizer.optimize()
    with tempfile.TemporaryDirectory(prefix="dbml-view-bench-") as tmp:
        target = ViewTarget.from_flags("127.0.0.1:0", str(Path(tmp) / "view.mcap"))
        assert target is not None
        view: LiveView = open_view(operator, target, writers=frozenset({Writer.OPERATOR}))
        stop = threading.Event()
        connected = threading.Event()
        received: list[int] = []

        def watch() -> None:
            endpoint = view.endpoint
            assert endpoint is not None
            with FoxgloveClient(f"ws://{endpoint}", timeout_s=CONNECT_S) as client:
                connected.set()
                client.pump(stop.is_set, timeout_s=600)
                received.append(sum(len(m) for m in client.messages.values()))

        viewer = threading.Thread(target=watch, daemon=True)
        viewer.start()
        if not connected.wait(CONNECT_S):
            raise SystemExit("the Foxglove client did not connect")
        optimize_ms = []
        for _ in range(rounds):
            before = view.cost.looks
            start = time.perf_counter()
            optimizer.optimize()
            optimize_ms.append((time.perf_counter() - start) * 1e3)
            _wait(lambda before=before: view.cost.looks > before, LOOK_TIMEOUT_S)
        cost = view.cost
        stop.set()
        viewer.join(timeout=10)
        view.close()
        recording = (Path(tmp) / "view.mcap").stat().st_size
    optimizer.stop()
    for subscriber in subscribers:
        subscriber.close()
    for publisher in publishers:
        publisher.close()
    return {
        "channels": channels,
        "rounds": rounds,
        "optimize_ms_mean": round(statistics.fmean(optimize_ms), 3),
        "optimize_ms_max": round(max(optimize_ms), 3),
        "view_looks": cost.looks,
        "view_look_ms_mean": round(cost.mean_ms, 3),
        "view_look_ms_max": round(cost.max_ms, 3),
        "view_over_optimize": round(cost.mean_ms / statistics.fmean(optimize_ms), 3),
        "client_messages": received[0] if received else None,
        "recording_bytes": recording,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--channels", type=int, nargs="+", default=[2, 320])
    parser.add_argument("--json", action="store_true", help="JSON only")
    args = parser.parse_args()
    results = [measure(n, args.rounds) for n in args.channels]
    document: dict[str, Any] = {
        "benchmark": "view_cost_per_round",
        "reference": "OptimizerNode.optimize() of the same round, same process",
        "results": results,
    }
    if not args.json:
        for row in results:
            print(
                f"{row['channels']:>4} channels: optimize {row['optimize_ms_mean']:.3f} ms, "
                f"view look {row['view_look_ms_mean']:.3f} ms ({row['view_over_optimize']:.2f}x)"
            )
    print(json.dumps(document))


if __name__ == "__main__":
    main()
