"""A testbed run's arrivals and the operator's ticks as JSON lines, for bench/estimator_replay.py.

Shared by the estimator benches that take ``--trace DIR``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from dbml.experiment.runner import Snapshot

__all__ = ["write_arrivals"]


def write_arrivals(folder: Path, name: str, head: dict[str, Any], snap: Snapshot) -> Path:
    """One JSON line of the run (``head``), then one per frame and one per tick (t0-relative)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}-{time.strftime('%Y%m%dT%H%M%S')}.jsonl"
    t0 = snap.t0
    with path.open("w") as out:
        out.write(json.dumps({"kind": "run", **head}) + "\n")
        for a in snap.arrivals:
            if a.seq is None or a.sent_s is None:
                continue
            frame = {
                "kind": "frame",
                "stream": f"r{a.robot + 1}",
                "seq": a.seq,
                "sent_s": round(a.sent_s - t0, 6),
                "arrival_s": round(a.arrival_s - t0, 6),
                "size_bytes": a.size_bytes,
                "rate_hz": a.rate_hz,
            }
            out.write(json.dumps(frame) + "\n")
        for t in snap.ticks:
            tick = {
                "kind": "tick",
                "t_s": round(t.t_s - t0, 4),
                "budget_mbit": t.budget_mbit,
                "estimate_mbit": t.estimate_mbit,
                "phase": None if t.estimator is None else t.estimator.phase.value,
                "queue_s": None if t.estimator is None else t.estimator.queue_delay_s,
                "lost": None if t.estimator is None else t.estimator.lost,
                "reason": None if t.estimator is None else t.estimator.reason,
                "decided_s": None
                if t.estimator is None or t.estimator.decided_at_s is None
                else round(t.estimator.decided_at_s - t0, 4),
            }
            out.write(json.dumps(tick) + "\n")
    print(f"trace: {path}", file=sys.stderr)
    return path
