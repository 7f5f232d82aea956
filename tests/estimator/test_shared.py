"""What every design shares: streams, silences, outages, bounds, the floor and the cap."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbml.core.errors import SpecError
from dbml.estimator import (
    MAX_SAMPLES,
    MAX_STREAMS,
    Arrival,
    BandwidthEstimator,
    Design,
    Estimate,
    EstimatorSettings,
    Phase,
    View,
    settings_of,
    shared,
)
from dbml.estimator.base import Decision, SharedSettings
from dbml.estimator.simulation import CAP_MBIT, drop_and_rise, simulate


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


def test_observe_returns_a_frames_queueing_over_its_streams_quickest() -> None:
    """A node judges a frame that queued at once; each stream against its own clock offset."""
    estimator = BandwidthEstimator(max_mbit=10.0)
    assert estimator.observe(Arrival("a", 0, 0.0, 0.030, 1_000)) == 0.0  # nothing to compare
    assert estimator.observe(Arrival("b", 0, 0.0, 5.010, 1_000)) == 0.0  # another clock
    assert estimator.observe(Arrival("a", 1, 0.1, 0.120, 1_000)) == 0.0  # quicker: the new least
    assert estimator.observe(Arrival("a", 2, 0.2, 0.370, 1_000)) == pytest.approx(0.150)
    assert estimator.observe(Arrival("b", 1, 0.1, 5.160, 1_000)) == pytest.approx(0.050)


def test_a_publisher_restart_is_not_a_loss() -> None:
    estimator = BandwidthEstimator(max_mbit=10.0)
    estimator.observe(Arrival("a", 100, 0.0, 0.01, 1_000))
    estimator.observe(Arrival("a", 0, 0.1, 0.11, 1_000))
    estimator.observe(Arrival("a", 1, 0.2, 0.21, 1_000))
    assert estimator.update(0.3).lost == 0


@pytest.mark.parametrize(
    ("field", "value"),
    [("window_s", 0.0), ("outage_s", math.nan), ("floor_fraction", 1.5), ("probe_fraction", 0.0)],
)
def test_bad_settings_name_the_field(field: str, value: float) -> None:
    """The shared ones here; each design's in its own tests (the queue's drain_s, backoff)."""
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


# -- one robot silent while the others flow (issue 20, item 2) ---------------------------------

ROBOT_FRAMES = {"r1/cam": (84_000, 0.065), "r2/cam": (21_000, 0.02)}
"""Per stream: frame size and one-way delay on an idle 11 Mbit/s link (10 Hz each: 8.4 Mbit/s)."""


def _robots(
    estimator: BandwidthEstimator, seqs: dict[str, int], *, start: float, end: float, silent: str
) -> list[Estimate]:
    """Both robots at 10 Hz from ``start`` to ``end`` but ``silent``; an update every 0.1 s."""
    estimates = []
    for k in range(round((end - start) / UPDATE_S)):
        t = start + k * UPDATE_S
        for name, (size, delay) in ROBOT_FRAMES.items():
            if name != silent:
                estimator.observe(Arrival(name, seqs[name], t - delay, t, size))
                seqs[name] += 1
        estimates.append(estimator.update(t + UPDATE_S))
    return estimates


@pytest.mark.parametrize("design", list(Design))
@pytest.mark.parametrize(
    ("dropped", "backlog_gap_s"),
    [
        (20, 0.07),  # the middleware dropped 20 frames; 10 queued ones arrive at the link's rate
        (0, 0.12),  # nothing dropped; the backlog arrives slower than it was sent: delays rise
    ],
)
def test_a_silent_robot_is_its_own_outage_not_the_links(
    dropped: int, backlog_gap_s: float, design: Design
) -> None:
    """r1's own link is out for 3 s while r2 flows; its return is not read as overuse."""
    settings = EstimatorSettings(detector=settings_of(design))
    estimator = BandwidthEstimator(max_mbit=CAP_MBIT, settings=settings)
    seqs = dict.fromkeys(ROBOT_FRAMES, 0)
    steady = _robots(estimator, seqs, start=0.0, end=5.0, silent="")
    before = estimator.estimate_mbit
    assert before == pytest.approx(CAP_MBIT)
    # r1 silent: r2 alone flows. No outage of the link, and nothing to cut for.
    alone = _robots(estimator, seqs, start=5.0, end=8.0, silent="r1/cam")
    assert not estimator.outage
    # r1 back: first what it queued meanwhile (old send times, sequence numbers skipped),
    # among r2's frames, then both as before
    size, _ = ROBOT_FRAMES["r1/cam"]
    seqs["r1/cam"] += dropped
    back = []
    t, sent = 8.0, 6.6
    while sent < 8.0 - 1e-9:
        estimator.observe(Arrival("r1/cam", seqs["r1/cam"], sent, t, size))
        seqs["r1/cam"] += 1
        estimator.observe(Arrival("r2/cam", seqs["r2/cam"], t - 0.02, t, 21_000))
        seqs["r2/cam"] += 1
        t += backlog_gap_s
        sent += UPDATE_S
        back.append(estimator.update(t))
    after = _robots(estimator, seqs, start=round(t, 1) + UPDATE_S, end=14.0, silent="")
    phases = [e.phase for e in steady + alone + back + after]
    assert Phase.DECREASE not in phases
    assert Phase.OUTAGE not in phases
    assert min(e.estimate_mbit for e in alone + back + after) >= before


# -- invariants --------------------------------------------------------------------------------

_frames = st.lists(
    st.tuples(
        st.sampled_from(["a", "b", "c"]),
        st.integers(0, 3),  # sequence step (0: a restart, >1: losses)
        st.floats(0.0, 0.3),  # time to the next frame
        st.floats(0.0, 5.0),  # one-way delay
        st.integers(1, 200_000),
        st.booleans(),  # an update after it
    ),
    max_size=120,
)


@given(
    frames=_frames,
    design=st.sampled_from(list(Design)),
    cap=st.floats(0.5, 50.0),
    start=st.floats(0.1, 60.0),
)
@settings(max_examples=60, deadline=None)
def test_the_estimate_stays_within_its_floor_and_cap(
    frames: list[tuple[str, int, float, float, int, bool]],
    design: Design,
    cap: float,
    start: float,
) -> None:
    """Whatever arrives, in whatever rhythm, the estimate is a number in [floor, cap]."""
    estimator = BandwidthEstimator(
        max_mbit=cap, initial_mbit=start, settings=EstimatorSettings(detector=settings_of(design))
    )
    floor = estimator.settings.floor_fraction * cap
    seqs: dict[str, int] = {}
    t = 0.0
    for stream, step, gap, delay, size, update in frames:
        seqs[stream] = 0 if step == 0 else seqs.get(stream, 0) + step
        t += gap
        estimator.observe(Arrival(stream, seqs[stream], t - delay, t, size))
        if update:
            estimate = estimator.update(t)
            assert floor - 1e-9 <= estimate.estimate_mbit <= cap + 1e-9
    for k in range(1, 30):  # and through the silence after them
        estimate = estimator.update(t + 0.1 * k)
        assert floor - 1e-9 <= estimate.estimate_mbit <= cap + 1e-9


# -- the detector: a strategy the loop tells and asks, never branches on -------------------------


@dataclass(frozen=True, slots=True)
class _Scripted:
    """A design that decides what it is told and records what the loop tells it."""

    estimate_mbit: list[float]
    calls: list[tuple[object, ...]]

    def detector(self, shared: SharedSettings) -> _Recorder:
        return _Recorder(self)


class _Recorder:
    def __init__(self, script: _Scripted) -> None:
        self.script = script

    def observe(self, arrival: Arrival) -> None:
        self.script.calls.append(("observe", arrival.stream, arrival.seq))

    def forget(self, stream: str | None) -> None:
        self.script.calls.append(("forget", stream))

    def decide(self, view: View) -> Decision:
        self.script.calls.append(("decide", round(view.now_s, 3), view.estimate_mbit))
        return Decision(Phase.HOLD, self.script.estimate_mbit[0])


def _scripted(estimate_mbit: float) -> tuple[BandwidthEstimator, _Scripted]:
    script = _Scripted([estimate_mbit], [])
    settings = EstimatorSettings(detector=script)
    return BandwidthEstimator(max_mbit=10.0, settings=settings), script


def test_the_loop_keeps_any_detectors_estimate_within_its_floor_and_cap() -> None:
    estimator, script = _scripted(1e9)
    estimator.observe(Arrival("a", 0, 0.0, 0.01, 1_000))
    assert estimator.update(0.1).estimate_mbit == 10.0
    script.estimate_mbit[0] = -5.0
    assert estimator.update(0.2).estimate_mbit == 10.0 * estimator.settings.floor_fraction
    decided = [c for c in script.calls if c[0] == "decide"]
    assert decided == [("decide", 0.1, 10.0), ("decide", 0.2, 10.0)]


def test_the_detector_hears_each_frame_kept_and_each_history_that_restarts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(shared, "MAX_STREAMS", 2)
    estimator, script = _scripted(5.0)
    _feed(estimator, start=0.0, end=1.0, seq=0)  # r1/cam, 10 Hz
    assert script.calls[:2] == [("observe", "r1/cam", 0), ("decide", 0.1, 10.0)]
    script.calls.clear()
    _silence(estimator, start=1.0, end=1.7)
    assert estimator.outage
    script.calls.clear()
    _silence(estimator, start=1.7, end=2.0)  # the link is down: nothing decided, all forgotten
    assert script.calls == [("forget", None)] * 3
    script.calls.clear()
    estimator.observe(Arrival("r1/cam", 30, 1.99, 2.0, 21_000))
    estimator.update(2.1)  # back: every history restarts, then a decision
    assert script.calls == [("observe", "r1/cam", 30), ("forget", None), ("decide", 2.1, 5.0)]
    estimator.observe(Arrival("r1/cam", 31, 2.09, 2.1, 21_000))  # after the outage's reset
    estimator.observe(Arrival("b", 0, 2.1, 2.15, 1_000))
    script.calls.clear()
    estimator.observe(Arrival("c", 0, 2.1, 2.15, 1_000))  # a third stream evicts r1/cam
    assert script.calls == [("forget", "r1/cam"), ("observe", "c", 0)]


def test_a_stream_back_from_its_own_silence_restarts_its_history_in_the_detector() -> None:
    estimator, script = _scripted(5.0)
    for k in range(45):  # a and b at 10 Hz; a silent from 3 s on while b flows
        t = k * UPDATE_S
        for stream in ("a", "b") if k < 30 else ("b",):
            estimator.observe(Arrival(stream, k, t, t + 0.01, 1_000))
        estimator.update(t + UPDATE_S / 2)
    assert not estimator.outage
    script.calls.clear()
    estimator.observe(Arrival("a", 45, 4.5, 4.51, 1_000))
    assert script.calls == [("forget", "a"), ("observe", "a", 45)]
