"""The link's schedule, and how a run followed each change of its rate."""

from __future__ import annotations

import pytest

from dbml.estimator import Phase
from dbml.experiment.analysis import Arrival, Tick, analyse, link_at
from dbml.protocol.messages import EstimatorState
from dbml.testbed import TestbedError
from dbml.testbed.options import (
    TestbedOptions,
    parse_robot_schedules,
    parse_schedule,
    parse_uplinks,
)


def test_schedule_parses_and_names_bad_values() -> None:
    assert parse_schedule("0:11,20:5,40:11") == ((0.0, 11.0), (20.0, 5.0), (40.0, 11.0))
    assert link_at(((0.0, 11.0), (20.0, 5.0)), 25.0, 11.0) == 5.0
    # 0 Mbit is an outage: the link is down until the next entry
    assert parse_schedule("0:11,20:0,30:11") == ((0.0, 11.0), (20.0, 0.0), (30.0, 11.0))
    for bad, named in (
        ("0:11,x:5", "'x:5'"),
        ("0:11,20", "'20'"),
        ("0:0", "must be up at 0 s"),
        ("0:11,5:-1", "rate '-1' must be > 0, or 0 for link down"),
        ("0:11,5:nan", "rate 'nan'"),
        ("10:5,5:11", "times must increase"),
        ("-1:5", "time '-1'"),
    ):
        with pytest.raises(TestbedError, match=named):
            parse_schedule(bad)


def test_uplinks_parse_and_name_bad_values() -> None:
    assert parse_uplinks(["R1=4", "r2=2.5"], ["R1", "R2"]) == {"R1": 4.0, "R2": 2.5}
    for bad in ("R3=4", "R1", "R1=fast", "R1=0"):
        with pytest.raises(TestbedError, match=f"--uplink={bad!r}"):
            parse_uplinks([bad], ["R1", "R2"])


def test_a_robots_own_schedule_parses_and_names_bad_values() -> None:
    assert parse_robot_schedules(["r1=0:11,20:0,30:11"], ["R1", "R2"]) == {
        "R1": ((0.0, 11.0), (20.0, 0.0), (30.0, 11.0))
    }
    for bad, named in (
        ("R3=0:11", "ROBOT=SPEC"),
        ("0:11,20:0", "ROBOT=SPEC"),
        ("R1=0:0", "must be up at 0 s"),
        ("R1=0:11,5:x", "'5:x' must be SECONDS:MBIT"),
    ):
        with pytest.raises(TestbedError, match=f"--uplink-schedule={bad!r}.*{named}"):
            parse_robot_schedules([bad], ["R1", "R2"])
    with pytest.raises(TestbedError, match="R1 has a schedule already"):
        parse_robot_schedules(["R1=0:11", "R1=0:5"], ["R1", "R2"])


def test_a_robots_own_schedule_is_no_steady_link_and_not_with_its_uplink() -> None:
    options = TestbedOptions.from_flags(uplink_schedules=["R1=0:11,20:0,30:11"])
    assert options.robot_schedules == {"R1": ((0.0, 11.0), (20.0, 0.0), (30.0, 11.0))}
    assert not options.steady
    assert options.uplinks_mbit == {}  # the optimizer's per-link limits are not asked for
    with pytest.raises(TestbedError, match="both shape"):
        TestbedOptions.from_flags(uplinks=["R1=4"], uplink_schedules=["R1=0:11"])


def test_a_drop_reports_when_latency_recovered() -> None:
    t0 = 0.0
    # delays grow for 2 s after a drop at 4 s, then are back to normal
    frames = []
    for seq in range(120):
        sent = seq * 0.1
        delay = 0.06 if not 4.0 <= sent < 6.0 else 0.06 + (sent - 4.0) * 0.4
        frames.append(Arrival(0, seq, sent, sent + delay, 50_000, 10.0))
    ticks = [Tick(t / 4, (10.0,), 5.0, 5.0) for t in range(48)]
    result = analyse(
        frames,
        ticks,
        robots=["R1"],
        t0=t0,
        step_s=1.2,
        steps=10,
        link_mbit=11.0,
        schedule=((0.0, 11.0), (4.0, 5.0)),
    )
    (change,) = result.changes
    assert change.to_mbit == 5.0
    assert change.max_latency_p95_ms is not None
    assert change.max_latency_p95_ms > 700
    # the last bad frame arrives at ~6.7 s; the first all-good 1-s window after it ends ~7.7 s
    assert change.recovery_s is not None
    assert 3.0 < change.recovery_s < 4.5


def test_a_drop_reports_the_first_cut_goodput_after_and_phases() -> None:
    t0 = 0.0
    frames = [
        Arrival(0, seq, seq * 0.1, seq * 0.1 + 0.05, 50_000, 10.0)  # 4 Mbit/s
        for seq in range(100)
    ]
    # the budget is cut 0.6 s after the drop at 4 s as ticks see it; the estimator's own
    # decision time says 0.25 s
    cut = EstimatorState(
        phase=Phase.DECREASE, received_mbit=4.0, queue_delay_s=0.1, lost=0, decided_at_s=4.25
    )
    hold = EstimatorState(phase=Phase.HOLD, received_mbit=4.0, queue_delay_s=0.0, lost=0)
    ticks = [Tick(t / 5, (10.0,), 9.0, 9.0) for t in range(23)]
    ticks.append(Tick(4.6, (10.0,), 4.0, 4.0, cut))
    ticks.extend(Tick(4.6 + t / 5, (10.0,), 4.0, 4.0, hold) for t in range(1, 28))
    result = analyse(
        frames,
        ticks,
        robots=["R1"],
        t0=t0,
        step_s=1.0,
        steps=10,
        link_mbit=11.0,
        schedule=((0.0, 11.0), (4.0, 5.0)),
    )
    (change,) = result.changes
    assert change.first_cut_s == pytest.approx(0.25)
    # the series shows the state as a line to read
    shown = {p.estimator for p in result.series if p.t_s > 4.6}
    assert shown == {cut.text, hold.text}
    assert cut.text == "decrease: received 4.00 Mbit/s, queueing 100 ms, lost 0 @4.250"
    assert change.goodput_share_after == pytest.approx(4.0 / 5.0, rel=0.05)
    first, second = result.phases
    assert (first.start_s, first.end_s, second.end_s) == (0.0, 4.0, 10.0)
    assert second.utilisation == pytest.approx(4.0 / 5.0, rel=0.05)
    assert second.latency_p95_ms == pytest.approx(50.0)
    assert second.lost == 0


def test_a_cut_without_a_stamp_is_timed_by_the_tick_that_saw_it() -> None:
    frames = [Arrival(0, seq, seq * 0.1, seq * 0.1 + 0.05, 50_000, 10.0) for seq in range(60)]
    ticks = [Tick(t / 5, (10.0,), 9.0 if t / 5 < 4.6 else 4.0, None) for t in range(30)]
    result = analyse(
        frames,
        ticks,
        robots=["R1"],
        t0=0.0,
        step_s=0.6,
        steps=10,
        link_mbit=11.0,
        schedule=((0.0, 11.0), (4.0, 5.0)),
    )
    (change,) = result.changes
    assert change.first_cut_s == pytest.approx(0.6)
