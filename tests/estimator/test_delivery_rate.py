"""The ``delivery-rate`` design: no false cut on a steady link, a cut's rate from what arrived."""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbml.core.errors import SpecError
from dbml.estimator import (
    Arrival,
    BandwidthEstimator,
    DeliveryRateSettings,
    EstimatorSettings,
    Phase,
)
from dbml.estimator.simulation import CAP_MBIT, WIRE_EFFICIENCY, simulate

DELIVERY_RATE = EstimatorSettings(detector=DeliveryRateSettings())
"""The design that does not cut a steady link (docs/estimator.md); not the default."""
UPDATE_S = 0.1
"""The node's estimator interval."""


def test_a_cuts_floor_counts_only_what_arrived_by_the_judged_time() -> None:
    """A node judges 75 ms in the past; a frame reported since is not in that second's rate."""
    estimator = BandwidthEstimator(max_mbit=10.0, settings=DELIVERY_RATE)
    for i in range(21):  # 100 KB every 0.1 s up to 2.0 s: 8 Mbit/s, no queue
        estimator.observe(Arrival("a", i, i * 0.1 - 0.01, i * 0.1, 100_000))
    estimator.observe(Arrival("a", 21, 2.1, 2.4, 100_000))  # queued 0.29 s
    estimator.observe(Arrival("a", 22, 2.2, 2.8, 100_000))  # queued 0.59 s, after 2.45
    estimate = estimator.update(2.45)
    assert estimate.phase is Phase.DECREASE
    # by 2.45: 7 frames in the last second, 5.6 Mbit/s, half of it the link's rate at least
    # (the pairs say 2); the queue is deep: the budget drains at half of that
    assert estimate.estimate_mbit == pytest.approx(0.5 * 0.5 * 5.6)


# -- no false cut on a steady link (issue 20, item 3) ------------------------------------------

STEADY_TRACE = Path(__file__).parent / "traces" / "steady-11mbit.csv"
"""60 s of a steady 11 Mbit/s testbed link as the operator received it (bench/estimator_rmcat.py
--only steady --trace): the two robots' frames interleave on the link as they really did."""
REPORT_LAG_S = 0.075
"""The node judges the window its reports completed (dbml.runtime.estimator)."""
SETTLED_S = 5.0
NO_CUT_SHARE = 0.9
"""Item 3: after it settled, the estimate never falls below this share of its steady value."""


def _recorded(path: Path) -> list[Arrival]:
    rows = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    return [
        Arrival(stream, int(seq), float(sent), float(arrival), int(size))
        for stream, seq, sent, arrival, size in (row.split(",") for row in rows[1:])
    ]


def test_a_recorded_steady_link_is_never_cut() -> None:
    """By the delivery-rate design; the queue design (the default) cuts on this trace."""
    frames = _recorded(STEADY_TRACE)
    estimator = BandwidthEstimator(max_mbit=CAP_MBIT, settings=DELIVERY_RATE)
    estimates, k, t = [], 0, UPDATE_S
    while t <= frames[-1].arrival_s:
        while k < len(frames) and frames[k].arrival_s <= t - REPORT_LAG_S:
            estimator.observe(frames[k])
            k += 1
        estimate = estimator.update(t - REPORT_LAG_S)
        if t >= SETTLED_S:
            estimates.append(estimate)
        t += UPDATE_S
    values = sorted(e.estimate_mbit for e in estimates)
    steady = values[len(values) // 2]
    assert steady >= 0.95 * 11.0 * WIRE_EFFICIENCY  # the link's payload capacity, nearly all
    assert values[0] >= NO_CUT_SHARE * steady
    assert Phase.DECREASE not in {e.phase for e in estimates}


def _queueing_s(frames: list[Arrival]) -> dict[str, list[float]]:
    """Per stream, each recorded frame's delay over the stream's least: the link's jitter."""
    least: dict[str, float] = {}
    for f in frames:
        least[f.stream] = min(least.get(f.stream, math.inf), f.arrival_s - f.sent_s)
    out: dict[str, list[float]] = {}
    for f in frames:
        out.setdefault(f.stream, []).append(f.arrival_s - f.sent_s - least[f.stream])
    return out


@given(seed=st.integers(0, 2**32 - 1))
@settings(max_examples=5, deadline=None)
def test_a_steady_link_with_recorded_jitter_is_never_cut(seed: int) -> None:
    """Closed loop, with the recorded queueing of each robot added to every frame.

    On top of the model's own FIFO (harsher than the link was), with the testbed's split of
    the budget between the robots; by the delivery-rate design (the queue design cuts here).
    """
    rng = random.Random(seed)
    queueing = _queueing_s(_recorded(STEADY_TRACE))
    by_model = {"r1": queueing["r1"], "r2": queueing["r2"]}

    def jitter(stream: str, _seq: int) -> float:
        return rng.choice(by_model[stream])

    def shares(_t: float) -> dict[str, float]:  # r2 at its 16 Hz, r1 the rest
        return {"r1": 0.73, "r2": 0.27}

    trace = simulate(
        BandwidthEstimator(max_mbit=CAP_MBIT, settings=DELIVERY_RATE),
        lambda _: 11.0,
        duration_s=60,
        jitter_s=jitter,
        report_lag_s=REPORT_LAG_S,
        shares=shares,
    )
    values = sorted(e.estimate_mbit for e in trace.estimates if e.t_s >= SETTLED_S)
    steady = values[len(values) // 2]
    assert steady >= 0.95 * 11.0 * WIRE_EFFICIENCY
    assert values[0] >= NO_CUT_SHARE * steady


@pytest.mark.parametrize(
    ("field", "value"),
    [("probe_gain", 0.0), ("bw_window_s", math.inf), ("drain_gain", 1.5), ("queue_target_s", -1.0)],
)
def test_bad_settings_name_the_field(field: str, value: float) -> None:
    kwargs: dict[str, Any] = {field: value}
    with pytest.raises(SpecError, match=f"{field}={value!r}"):
        DeliveryRateSettings(**kwargs)
