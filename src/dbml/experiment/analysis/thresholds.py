"""The thresholds that judge a run, and the windows it is measured over, named once."""

from __future__ import annotations

__all__ = [
    "APPLIED_LAG_S",
    "BUDGET_BACK_FRACTION",
    "BUDGET_BACK_S",
    "FIRST_CUT_S",
    "GOODPUT_AFTER_FRACTION",
    "GOODPUT_AFTER_S",
    "GOODPUT_FRACTION",
    "LIVE_FRAMES",
    "LIVE_WINDOW_S",
    "MAX_P95_MS",
    "OUTAGE_AFTER_S",
    "OUTAGE_RECOVERY_S",
    "PEAK_P95_AFTER_DROP_MS",
    "RATE_TOLERANCE",
    "RATE_TOLERANCE_HZ",
    "RECOVERED_FLOOR_HZ",
    "RECOVERED_P95_MS",
    "RECOVERY_S",
    "STUCK_WINDOW_S",
    "WINDOW_S",
    "WINDOW_STEP_S",
]

RATE_TOLERANCE = 0.05
"""A delivered rate within 5 % of the allocation is the allocation (the paper's claim)."""
RATE_TOLERANCE_HZ = 0.3
"""The demo's floor on the tolerance: a few-Hz stream in a short step has few frames to time."""
MAX_P95_MS = 200.0
"""A steady link keeps every robot's one-way p95 latency under this (teleoperation's limit)."""
RECOVERED_P95_MS = 250.0
"""After a drop, a window whose p95 is under this (and loses nothing) counts as recovered."""
RECOVERY_S = 3.0
"""After a drop, latency and losses are back within this (the estimator's promise)."""
GOODPUT_FRACTION = 0.9
"""On a steady link with no capped uplink, dbml's goodput is at least this share of the link."""
BUDGET_BACK_FRACTION = 0.9
"""After a rise, the budget counts as back once it reaches this share of the new link."""
BUDGET_BACK_S = 10.0
"""After a rise, the estimated budget is back within this."""
FIRST_CUT_S = 0.3
"""After a drop, the estimator cuts the budget within this (GCC: about a round trip + 100 ms)."""
PEAK_P95_AFTER_DROP_MS = 250.0
"""After a drop, no window's p95 latency reaches this."""
GOODPUT_AFTER_FRACTION = 0.85
"""From ``GOODPUT_AFTER_S`` after a drop, goodput is at least this share of the new rate."""
GOODPUT_AFTER_S = 3.0
"""After a change, goodput is judged from this long on: the estimator has settled by then."""
WINDOW_S = 1.0
"""Rolling windows of the time series and the recovery measurement."""
WINDOW_STEP_S = 0.25
"""One point of the time series every this many seconds."""
LIVE_WINDOW_S = 2.0
"""A live view's readings cover this long: smoother than one second, still current."""
LIVE_FRAMES = 400
"""A live view reads at most this many of the newest frames (all of ``LIVE_WINDOW_S``)."""
OUTAGE_AFTER_S = 5.0
"""After an outage, every 1-s window of this long is held against the budget."""
OUTAGE_RECOVERY_S = 3.0
"""After a link comes back, every robot behind it delivers its allocation again within this."""
RECOVERED_FLOOR_HZ = 1.0
"""A robot delivers its allocation in a 1-s window when within ``RATE_TOLERANCE`` of it or one
frame: where a window's edge falls between two frames decides that one."""
STUCK_WINDOW_S = 2.0
"""A robot not at its allocation in any window of a run's last this long is stuck."""
APPLIED_LAG_S = 0.25
"""A frame's applied rate is an allocation the operator saw in force this close to its send
time: the operator reads the allocation every 0.2 s, the publisher applies it when pushed."""
