"""The bandwidth estimator, closed loop over a simulated bottleneck (tests/core/link_model.py)."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from dbml.core.errors import SpecError
from dbml.core.estimator import (
    MAX_SAMPLES,
    MAX_STREAMS,
    Arrival,
    BandwidthEstimator,
    Estimate,
    EstimatorSettings,
    EstimatorState,
    Phase,
)
from tests.core.link_model import WIRE_EFFICIENCY, simulate

CAP_MBIT = 11.0 * 0.92
DEMAND_MAX_MBIT = 16 * (84_000 + 21_000) * 8e-6  # both cameras at their maximum


def drop_and_rise(t: float) -> float:
    return 11.0 if t < 20 or t >= 40 else 5.0


def test_constant_link_is_used_without_queueing() -> None:
    trace = simulate(BandwidthEstimator(max_mbit=CAP_MBIT), lambda _: 11.0, duration_s=20)
    assert trace.estimate_at(20) == pytest.approx(CAP_MBIT)
    assert trace.max_delay(2, 20) < 0.1  # an 84 KB frame alone takes 64 ms


def test_drop_is_followed_within_three_seconds() -> None:
    trace = simulate(BandwidthEstimator(max_mbit=CAP_MBIT), drop_and_rise, duration_s=40)
    # from 3 s after the drop, frames arrive with little queueing (an 84 KB frame alone: 141 ms)
    assert trace.p95_delay(23, 40) < 0.25
    assert trace.max_delay(23, 40) < 0.3
    assert trace.estimate_at(25) < 5.0 * WIRE_EFFICIENCY * 1.1
    # and the link stays used
    assert min(e.estimate_mbit for e in trace.estimates if e.t_s > 25) > 0.6 * 5.0


def test_rise_is_found_within_ten_seconds() -> None:
    trace = simulate(BandwidthEstimator(max_mbit=CAP_MBIT), drop_and_rise, duration_s=52)
    assert trace.estimate_at(39.9) < 6.0
    assert trace.estimate_at(50) >= 0.9 * 11.0


def test_without_estimation_the_drop_builds_an_ever_growing_queue() -> None:
    """The reference: the paper's constant budget on the same schedule."""
    constant = simulate(None, drop_and_rise, duration_s=30, constant_mbit=CAP_MBIT)
    assert constant.max_delay(28, 30) > 2.0


@given(
    offset_r1=st.floats(-1e4, 1e4, allow_nan=False),
    offset_r2=st.floats(-1e4, 1e4, allow_nan=False),
)
@settings(max_examples=10, deadline=None)
def test_clock_offsets_do_not_matter(offset_r1: float, offset_r2: float) -> None:
    plain = simulate(BandwidthEstimator(max_mbit=CAP_MBIT), drop_and_rise, duration_s=26)
    shifted = simulate(
        BandwidthEstimator(max_mbit=CAP_MBIT),
        drop_and_rise,
        duration_s=26,
        clock_offsets_s={"r1": offset_r1, "r2": offset_r2},
    )
    for a, b in zip(plain.estimates, shifted.estimates, strict=True):
        assert a.phase == b.phase
        assert a.estimate_mbit == pytest.approx(b.estimate_mbit, rel=1e-6)


@given(link=st.floats(3.0, 30.0), cap=st.floats(1.0, 40.0))
@settings(max_examples=20, deadline=None)
def test_never_above_the_cap_and_converges_below_the_link(link: float, cap: float) -> None:
    # Known limit: an overload of a few percent grows the queue a few ms per second, slower
    # than the base-delay window forgets, so delay alone does not see it (see the note).
    assume(abs(link * WIRE_EFFICIENCY - DEMAND_MAX_MBIT) > 0.03 * DEMAND_MAX_MBIT)
    trace = simulate(BandwidthEstimator(max_mbit=cap), lambda _: link, duration_s=30)
    assert all(e.estimate_mbit <= cap + 1e-9 for e in trace.estimates)
    # once settled the queue stays short: the estimate tracks the link, not above it
    two_frames_s = 2 * 84_000 * 8e-6 / (link * WIRE_EFFICIENCY)
    assert trace.p95_delay(20, 30) < 0.15 + two_frames_s
    # and the link is used: at least 60 % of it (or all the budget allows)
    assert trace.estimate_at(30) >= min(cap, 0.6 * link * WIRE_EFFICIENCY)


def test_losses_decrease_the_estimate() -> None:
    estimator = BandwidthEstimator(max_mbit=10.0)
    for i in range(10):
        estimator.observe(Arrival("a", i, i * 0.05, i * 0.05 + 0.01, 50_000))
    assert estimator.update(0.5).phase is not Phase.DECREASE
    estimator.observe(Arrival("a", 15, 0.55, 0.56, 50_000))  # 10..14 lost
    estimate = estimator.update(0.6)
    assert estimate.lost == 5
    assert estimate.phase is Phase.DECREASE
    assert estimate.estimate_mbit < 10.0


def test_an_idle_link_is_not_probed() -> None:
    """Receiving far less than the estimate says nothing about what more would fit."""
    estimator = BandwidthEstimator(max_mbit=20.0, initial_mbit=5.0)
    for i in range(20):
        estimator.observe(Arrival("a", i, i * 0.1, i * 0.1 + 0.01, 1_000))
        estimate = estimator.update(i * 0.1 + 0.02)
    assert estimate.phase is Phase.HOLD
    assert estimate.estimate_mbit == 5.0


def test_a_publisher_restart_is_not_a_loss() -> None:
    estimator = BandwidthEstimator(max_mbit=10.0)
    estimator.observe(Arrival("a", 100, 0.0, 0.01, 1_000))
    estimator.observe(Arrival("a", 0, 0.1, 0.11, 1_000))
    estimator.observe(Arrival("a", 1, 0.2, 0.21, 1_000))
    assert estimator.update(0.3).lost == 0


@pytest.mark.parametrize(
    ("field", "value"),
    [("window_s", 0.0), ("drain_s", math.nan), ("backoff", 1.5), ("probe_fraction", 0.0)],
)
def test_bad_settings_name_the_field(field: str, value: float) -> None:
    kwargs: dict[str, Any] = {field: value}
    with pytest.raises(SpecError, match=f"{field}={value!r}"):
        EstimatorSettings(**kwargs)


@pytest.mark.parametrize("value", [0.0, -1.0, math.inf])
def test_bad_maximum_names_the_value(value: float) -> None:
    with pytest.raises(SpecError, match=f"max_mbit={value!r}"):
        BandwidthEstimator(max_mbit=value)


UPDATE_S = 0.1
"""The node's estimator interval."""


def _feed(
    estimator: BandwidthEstimator,
    *,
    start: float,
    end: float,
    seq: int,
    delay_s: float = 0.01,
    sent_offset_s: float = 0.0,
) -> tuple[int, list[Phase]]:
    """A 10 Hz stream of 21 KB frames from ``start`` to ``end``, an update every 0.1 s."""
    phases = []
    t = start
    while t < end - 1e-9:
        estimator.observe(Arrival("r1/cam", seq, t - delay_s - sent_offset_s, t, 21_000))
        seq += 1
        t += UPDATE_S
        phases.append(estimator.update(t).phase)
    return seq, phases


def _silence(estimator: BandwidthEstimator, *, start: float, end: float) -> list[Phase]:
    steps = round((end - start) / UPDATE_S)
    return [estimator.update(start + (k + 1) * UPDATE_S).phase for k in range(steps)]


def test_silence_is_an_outage_that_keeps_the_estimate() -> None:
    estimator = BandwidthEstimator(max_mbit=CAP_MBIT)
    _feed(estimator, start=0.0, end=3.0, seq=0)
    before = estimator.estimate_mbit
    phases = _silence(estimator, start=3.0, end=5.0)
    # declared within outage_s (0.5 s) plus one update; nothing measured, nothing cut
    assert Phase.OUTAGE not in phases[:4]
    assert set(phases[6:]) == {Phase.OUTAGE}
    assert estimator.outage
    assert estimator.estimate_mbit == before


def test_the_backlog_after_an_outage_is_not_congestion() -> None:
    estimator = BandwidthEstimator(max_mbit=CAP_MBIT)
    seq, _ = _feed(estimator, start=0.0, end=3.0, seq=0)
    before = estimator.estimate_mbit
    _silence(estimator, start=3.0, end=6.0)
    # back: frames queued for seconds, then a jump of 30 sequence numbers (dropped meanwhile)
    seq, backlog = _feed(estimator, start=6.0, end=6.5, seq=seq, delay_s=3.0)
    seq, fresh = _feed(estimator, start=6.5, end=8.0, seq=seq + 30)
    assert not estimator.outage
    assert Phase.DECREASE not in backlog + fresh
    assert estimator.estimate_mbit >= before


def test_a_slow_stream_is_not_an_outage() -> None:
    estimator = BandwidthEstimator(max_mbit=CAP_MBIT)
    t, phases = 0.0, []
    for seq in range(8):  # 1 Hz: a gap of 1 s is its rhythm, not a dead link
        estimator.observe(Arrival("r2/cam", seq, t - 0.01, t, 21_000))
        phases += _silence(estimator, start=t, end=t + 1.0)
        t += 1.0
    assert Phase.OUTAGE not in phases


def test_a_second_outage_is_seen_as_soon_as_the_first() -> None:
    """The first outage's gap is not the streams' usual gap: it must not slow the next one."""
    estimator = BandwidthEstimator(max_mbit=CAP_MBIT)
    seq, _ = _feed(estimator, start=0.0, end=3.0, seq=0)
    _silence(estimator, start=3.0, end=6.0)
    assert estimator.outage
    seq, _ = _feed(estimator, start=6.0, end=6.3, seq=seq + 30)  # back for three frames
    assert not estimator.outage
    phases = _silence(estimator, start=6.3, end=7.5)
    # within outage_s (0.5 s) plus an update or two, as the first one was
    assert Phase.OUTAGE in phases[:8]


# -- the state the estimator tells others ------------------------------------------------------


def test_a_state_travels_as_json_and_reads_as_a_line() -> None:
    estimate = Estimate(5.0, 4.5, Phase.DECREASE, 3.2049, 0.0404, 0.1, 2)
    state = EstimatorState.of(estimate, decided_at_s=1_700_000_002.1234)
    assert state.text == "decrease: received 3.20 Mbit/s, queueing 40 ms, lost 2 @1700000002.123"
    back = EstimatorState.decode(state.encode())
    assert back.phase is Phase.DECREASE
    assert back.decided_at_s == 1_700_000_002.123  # to the millisecond, as it was shown
    assert back.text == state.text
    hold = EstimatorState.of(Estimate(5.0, 4.5, Phase.HOLD, 3.2, 0.0, 0.0, 0))
    assert hold.text == "hold: received 3.20 Mbit/s, queueing 0 ms, lost 0"
    assert EstimatorState.decode(hold.encode()) == hold


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("hold: received 3.20 Mbit/s", "estimator state='hold: received 3.20 Mbit/s' is not JSON"),
        ("[1]", r"estimator state=\[1\] is not a JSON object"),
        ('{"phase": "up"}', "estimator state: phase='up' is not one of increase, hold"),
        ('{"phase": "hold", "lost": -1}', "estimator state: lost=-1 is not a count"),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": "fast"}',
            "estimator state: received_mbit='fast' is not a number",
        ),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": 1, "queue_delay_s": NaN}',
            "estimator state: queue_delay_s=nan is not finite",
        ),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": 1, "queue_delay_s": 0, '
            '"decided_at_s": -2}',
            "estimator state: decided_at_s=-2 must be >= 0",
        ),
    ],
)
def test_a_malformed_state_names_the_field_and_the_value(text: str, match: str) -> None:
    with pytest.raises(SpecError, match=match):
        EstimatorState.decode(text)


def test_streams_are_bounded_by_evicting_the_one_silent_the_longest() -> None:
    """Stream names come from any peer's reports: one more evicts the silent one."""
    estimator = BandwidthEstimator(max_mbit=10.0)
    over = 10
    for i in range(MAX_STREAMS):
        estimator.observe(Arrival(f"s{i}", 0, 0.0, 0.01, 1_000))
    estimator.observe(Arrival("s0", 1, 0.1, 0.11, 1_000))  # heard again: now the newest
    for i in range(MAX_STREAMS, MAX_STREAMS + over):
        estimator.observe(Arrival(f"s{i}", 0, 0.2, 0.21, 1_000))
    streams = estimator._streams
    assert len(streams) == estimator.stream_count == MAX_STREAMS
    assert estimator.streams_evicted == over
    assert "s0" in streams
    assert not any(f"s{i}" in streams for i in range(1, over + 1))
    assert estimator._samples == sum(len(s.samples) for s in streams.values())


def test_frames_kept_are_bounded_and_their_sequence_numbers_still_count() -> None:
    estimator = BandwidthEstimator(max_mbit=10.0)
    over = 10
    for seq in range(MAX_SAMPLES + over):
        estimator.observe(Arrival("a", seq, seq * 1e-6, seq * 1e-6 + 0.01, 1_000))
    assert estimator.sample_count == len(estimator._streams["a"].samples) == MAX_SAMPLES
    assert estimator.samples_refused == over
    estimator.observe(Arrival("a", MAX_SAMPLES + over + 1, 3.0, 3.01, 1_000))  # one lost
    assert estimator.update(3.02).lost == 1
    # Every frame kept left the base window: room again (the newest was refused, too).
    estimator.observe(Arrival("a", MAX_SAMPLES + over + 2, 20.0, 20.01, 1_000))
    estimator.update(20.02)
    assert estimator.sample_count == 0
    estimator.observe(Arrival("a", MAX_SAMPLES + over + 3, 20.1, 20.11, 1_000))
    assert estimator._samples == 1
