"""The oracle: the teleoperation scenario with a perfect estimate over a recorded link.

Expected values are worked out by hand from the trace and the paper's numbers: a payload of
0.957 of the shaped rate is 119,625 bytes/s per shaped Mbit/s, and 10.12 Mbit/s (11 x 0.92) is a
budget of 1,265,000 bytes/s.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbml.core.errors import SpecError
from dbml.experiment.oracle import (
    bottleneck_departures,
    oracle_budget,
    simulate_fixed_budget,
    simulate_oracle,
)
from dbml.scenarios.teleop import PAPER_TABLE2
from dbml.scenarios.traces import LinkTrace, parse_plain_trace

PAYLOAD_PER_MBIT = 119_625.0
"""Bytes/s of payload per shaped Mbit/s: 125,000 x 0.957."""
CAP_MBIT = 10.12
"""The testbed's budget: 11 Mbit/s x 0.92."""
CAP_BYTES_PER_S = 1_265_000.0


def trace(text: str) -> LinkTrace:
    return parse_plain_trace(text, name="test")


def test_the_budget_is_the_payload_capped_at_the_configured_maximum() -> None:
    link = trace("0:11,10:5,20:0")
    assert oracle_budget(link, 0.0, max_budget_mbit=CAP_MBIT) == CAP_MBIT  # 10.527 > 10.12
    assert oracle_budget(link, 9.99, max_budget_mbit=CAP_MBIT) == CAP_MBIT
    assert oracle_budget(link, 15.0, max_budget_mbit=CAP_MBIT) == pytest.approx(4.785)
    assert oracle_budget(link, 25.0, max_budget_mbit=CAP_MBIT) == 0.0
    with pytest.raises(SpecError, match="max_budget_mbit=0"):
        oracle_budget(link, 0.0, max_budget_mbit=0)


def test_a_frame_departs_exactly_across_a_capacity_change_mid_frame() -> None:
    # 8 Mbit/s (957,000 B/s of payload) until 1 s, then 4 (478,500 B/s): 0.05 s at 8 carries
    # 47,850 of the 84,000 bytes, the other 36,150 take 0.07555 s at 4.
    (departure,) = bottleneck_departures(trace("0:8,1:4"), [(0.95, 84_000)])
    assert departure == pytest.approx(1.0 + 36_150 / 478_500, abs=1e-12)
    assert departure == pytest.approx(1.0755485893, abs=1e-9)


def test_a_link_down_for_a_second_holds_the_queue() -> None:
    # down until 1 s, then 10 Mbit/s = 1,196,250 B/s of payload
    departures = bottleneck_departures(trace("0:0,1:10"), [(0.0, 84_000), (0.5, 21_000)])
    assert departures[0] == pytest.approx(1.0 + 84_000 / 1_196_250, abs=1e-12)
    assert departures[1] == pytest.approx(1.0 + 105_000 / 1_196_250, abs=1e-12)
    assert departures[0] is not None
    assert departures[0] - 0.0 >= 1.0


def test_a_frame_on_a_link_that_stays_down_never_departs() -> None:
    # 5 Mbit/s = 598,125 B/s until 1 s, then down for good
    first, second = bottleneck_departures(trace("0:5,1:0"), [(0.0, 1_000), (0.99, 84_000)])
    assert first == pytest.approx(1_000 / 598_125, abs=1e-12)
    assert second == math.inf


def test_frames_are_lost_only_when_the_wait_ahead_exceeds_max_queue_s() -> None:
    link = trace("0:0,10:10")  # down 10 s, then 1,196,250 B/s
    frames = [(0.0, 1_000), (1.0, 1_000), (2.0, 1_000), (3.0, 1_000), (8.5, 1_000)]
    # the first finds the queue empty; the next three would wait 9, 8 and 7 s; the last 1.5 s
    assert bottleneck_departures(link, frames, max_queue_s=2.0) == pytest.approx(
        [10 + 1_000 / 1_196_250, None, None, None, 10 + 2_000 / 1_196_250]
    )
    kept = bottleneck_departures(link, frames, max_queue_s=20.0)
    assert kept == pytest.approx([10 + k * 1_000 / 1_196_250 for k in range(1, 6)])


@settings(max_examples=60, deadline=None)
@given(
    mbit=st.floats(0.1, 100.0),
    frames=st.lists(
        st.tuples(st.floats(0.0, 10.0), st.integers(1, 200_000)), min_size=1, max_size=30
    ),
)
def test_on_a_constant_link_the_fifo_is_the_textbook_recursion(
    mbit: float, frames: list[tuple[float, int]]
) -> None:
    frames.sort()
    rate = mbit * PAYLOAD_PER_MBIT
    expected, free = [], 0.0
    for send, size in frames:
        free = max(send, free) + size / rate
        expected.append(free)
    got = bottleneck_departures(trace(f"0:{mbit!r}"), frames, max_queue_s=math.inf)
    assert got == pytest.approx(expected, rel=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    rates=st.lists(st.sampled_from([0.0, 0.5, 3.0, 11.0]), min_size=1, max_size=8),
    frames=st.lists(
        st.tuples(st.floats(0.0, 8.0), st.integers(1, 100_000)), min_size=1, max_size=30
    ),
)
def test_departures_keep_fifo_order_and_never_beat_the_fastest_rate(
    rates: list[float], frames: list[tuple[float, int]]
) -> None:
    frames.sort()
    link = trace(",".join(f"{k}:{r}" for k, r in enumerate([*rates, 11.0])))
    fastest = 11.0 * PAYLOAD_PER_MBIT
    previous = 0.0
    for (send, size), departure in zip(
        frames, bottleneck_departures(link, frames, max_queue_s=math.inf), strict=True
    ):
        assert departure is not None
        assert departure >= max(send, previous) + size / fastest * (1 - 1e-9)
        previous = departure


def test_on_a_constant_link_the_oracle_delivers_its_whole_budget() -> None:
    # 11 Mbit/s carries 10.527 of payload, above the 10.12 cap. At 1,265,000 B/s the paper's
    # allocation fills the budget in every step: both cameras at 16 Hz would need 1,680,000, the
    # minimums 105,000 (and floors that do not fit are pulled back until they do).
    run = simulate_oracle(trace("0:11"), step_s=2.0, max_budget_mbit=CAP_MBIT)
    assert run.duration_s == 20.0
    assert run.budget_bytes == pytest.approx(CAP_BYTES_PER_S * 20)
    assert run.capacity_payload_bytes == pytest.approx(11 * PAYLOAD_PER_MBIT * 20)
    assert run.delivered_bytes == pytest.approx(CAP_BYTES_PER_S * 20, rel=0.02)
    assert run.utilisation == pytest.approx(10.12 / 10.527, rel=0.02)
    assert run.budget_share == pytest.approx(1.0, rel=0.02)
    assert run.frames_lost == 0
    assert run.frames_queued <= 2  # at most a frame per camera still on the wire
    assert len(run.windows) == 20
    for window in run.windows:
        assert window.capacity_mbit == pytest.approx(10.527)
        assert window.budget_mbit == pytest.approx(CAP_MBIT)
        assert window.goodput_mbit == pytest.approx(CAP_MBIT, abs=0.7)  # one 84-KB frame
    # the queue stays short: an 84-KB frame alone takes 84,000 / 1,315,875 = 63.8 ms
    assert run.latency_p50_ms is not None
    assert run.latency_p50_ms == pytest.approx(63.84, abs=0.01)
    assert run.latency_p99_ms is not None
    assert run.latency_p99_ms < 63.84 + 16.0 + 1.0  # at worst behind a 21-KB frame (16 ms)


def test_with_the_papers_budget_the_cameras_send_at_table_2s_rates() -> None:
    # 20 Mbit/s carries 19.14 of payload: the 11-Mbit cap is the paper's own budget
    run = simulate_oracle(trace("0:20"), step_s=2.0, max_budget_mbit=11.0)
    expected = 2.0 * sum(r1.rate_hz + r2.rate_hz for r1, r2 in PAPER_TABLE2)  # 476.5
    assert run.frames_sent == pytest.approx(expected, abs=4)


def test_eight_robots_also_fill_the_budget() -> None:
    # minimums 4 x 84,000 + 4 x 21,000 = 420,000 B/s, maximums 16 x that: the budget is filled
    run = simulate_oracle(trace("0:20"), robots=8, step_s=1.0, max_budget_mbit=CAP_MBIT)
    assert run.delivered_bytes == pytest.approx(CAP_BYTES_PER_S * 10, rel=0.03)


def test_after_a_drop_the_oracle_follows_the_payload() -> None:
    run = simulate_oracle(trace("0:11,10:5"), step_s=2.0, max_budget_mbit=CAP_MBIT)
    budget = (10.12 * 10 + 5 * 0.957 * 10) * 125_000  # 18,631,250 bytes
    assert run.budget_bytes == pytest.approx(budget)
    assert run.delivered_bytes == pytest.approx(budget, rel=0.02)
    assert run.frames_lost == 0
    late = run.windows[12]
    assert (late.capacity_mbit, late.budget_mbit) == pytest.approx((4.785, 4.785))
    assert late.goodput_mbit == pytest.approx(4.785, abs=0.7)


def test_during_an_outage_nothing_is_sent_or_delivered() -> None:
    run = simulate_oracle(trace("0:11,5:0,6:11"), step_s=1.0, max_budget_mbit=CAP_MBIT)
    down = run.windows[5]
    assert (down.t_s, down.goodput_mbit, down.capacity_mbit, down.budget_mbit) == (5, 0, 0, 0)
    assert run.frames_lost == 0
    assert run.budget_bytes == pytest.approx(CAP_BYTES_PER_S * 9)


def test_far_above_the_budget_latency_is_one_frames_transmission() -> None:
    # 1,000 Mbit/s = 119,625,000 B/s: 0.702 ms for 84 KB, 0.176 ms for 21 KB
    run = simulate_oracle(trace("0:1000"), step_s=2.0, max_budget_mbit=CAP_MBIT)
    assert run.latency_p50_ms is not None
    assert run.latency_p99_ms is not None
    assert 0.1755 <= run.latency_p50_ms <= run.latency_p99_ms
    assert run.latency_p99_ms == pytest.approx(84_000 / 119_625, abs=1e-6)
    assert run.utilisation == pytest.approx(10.12 / 957, rel=0.02)


def test_window_capacities_add_up_to_the_traces_payload() -> None:
    link = trace("0:3,2.5:0.5,4.25:6")
    run = simulate_oracle(link, step_s=0.75, max_budget_mbit=CAP_MBIT)
    assert run.duration_s == 7.5
    assert len(run.windows) == 8
    assert run.windows[-1].capacity_mbit == pytest.approx(5.742)  # the half window [7, 7.5)
    # [2, 3): half a second at 3, half at 0.5, times 0.957
    assert run.windows[2].capacity_mbit == pytest.approx((1.5 + 0.25) * 0.957)
    megabits = sum(w.capacity_mbit * (min(w.t_s + 1, 7.5) - w.t_s) for w in run.windows)
    assert megabits * 125_000 == pytest.approx(run.capacity_payload_bytes)
    assert run.capacity_payload_bytes == pytest.approx((7.5 + 0.875 + 19.5) * PAYLOAD_PER_MBIT)


def test_a_fixed_budget_delivers_itself_below_the_link() -> None:
    # 5 Mbit/s of budget on an 11-Mbit/s link: 625,000 B/s sent and delivered, the rest idle
    run = simulate_fixed_budget(trace("0:11"), budget_mbit=5.0, step_s=2.0)
    assert run.budget_bytes == pytest.approx(625_000 * 20)
    assert run.delivered_bytes == pytest.approx(625_000 * 20, rel=0.03)
    assert run.utilisation == pytest.approx(5 / 10.527, rel=0.03)
    assert run.frames_lost == 0
    # no queue at half the link: a frame's own time (21 KB: 15.96 ms, 84 KB: 63.84), at
    # worst behind one frame of the other camera
    assert run.latency_p50_ms is not None
    assert run.latency_p99_ms is not None
    assert 15.95 <= run.latency_p50_ms <= run.latency_p99_ms < 63.84 + 15.96 + 1.0


def test_a_fixed_budget_sends_into_an_outage_the_oracle_sees() -> None:
    # Down from 5 to 6 s: the oracle sends nothing in it; a fixed budget of 2 Mbit/s sends
    # about 2 frames a second of 84 KB and 1 of 21 KB, which wait for the link's return.
    link = trace("0:11,5:0,6:11")
    fixed = simulate_fixed_budget(link, budget_mbit=2.0, step_s=2.0)
    oracle = simulate_oracle(link, step_s=2.0, max_budget_mbit=2.0)
    assert oracle.latency_p99_ms is not None
    assert fixed.latency_p99_ms is not None
    assert oracle.latency_p99_ms < 100.0
    assert fixed.latency_p99_ms > 500.0
    assert fixed.budget_bytes == pytest.approx(250_000 * 20)
    assert oracle.budget_bytes == pytest.approx(250_000 * 19)
    with pytest.raises(SpecError, match="budget_mbit=0"):
        simulate_fixed_budget(link, budget_mbit=0.0, step_s=2.0)


def test_a_run_is_repeatable() -> None:
    link = trace("0:3,2:0.5,4:6")
    first = simulate_oracle(link, step_s=0.6, max_budget_mbit=CAP_MBIT)
    assert simulate_oracle(link, step_s=0.6, max_budget_mbit=CAP_MBIT) == first


@pytest.mark.parametrize(
    ("options", "field"),
    [
        ({"step_s": 0.0}, "step_s=0"),
        ({"max_budget_mbit": -1.0}, "max_budget_mbit=-1"),
        ({"reallocate_s": 0.001}, "reallocate_s=0.001"),
        ({"max_queue_s": -1.0}, "max_queue_s=-1"),
        ({"strategy": "nope"}, "strategy='nope'"),
        ({"robots": 1}, "robots=1"),
    ],
)
def test_a_bad_option_names_itself(options: dict[str, object], field: str) -> None:
    arguments: dict[str, object] = {"step_s": 1.0, "max_budget_mbit": CAP_MBIT, **options}
    with pytest.raises(SpecError, match=field):
        simulate_oracle(trace("0:11"), **arguments)  # type: ignore[arg-type]
