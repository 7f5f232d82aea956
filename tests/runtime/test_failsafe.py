"""The allocation in force and the fail-safe, alone: plain numbers for the clock, no transport."""

from __future__ import annotations

import pytest

from dbml.runtime.failsafe import FAILSAFE_PERIODS, FailSafe

START_S = 100.0
MIN_HZ = 1.0
MAX_HZ = 16.0
PERIOD_S = 0.5
DEADLINE_S = FAILSAFE_PERIODS * PERIOD_S


def fresh(now: float = START_S) -> FailSafe:
    return FailSafe(min_rate_hz=MIN_HZ, max_rate_hz=MAX_HZ, now=now, period_s=PERIOD_S)


def test_a_new_channel_waits_at_its_minimum_until_the_deadline() -> None:
    allocation = fresh()
    assert allocation.rate_hz(START_S) == MIN_HZ
    assert allocation.waiting(START_S + DEADLINE_S)  # the deadline itself is still in time
    assert not allocation.lapsed(START_S + DEADLINE_S)
    later = START_S + DEADLINE_S + 0.01
    assert not allocation.waiting(later)
    assert allocation.lapsed(later)
    assert allocation.rate_hz(later) == MIN_HZ


def test_an_allocation_is_in_force_and_clamped_to_the_maximum() -> None:
    allocation = fresh()
    assert allocation.allocate(12.0, START_S) == 12.0
    assert allocation.rate_hz(START_S + 1.0) == 12.0
    assert not allocation.waiting(START_S)
    assert allocation.allocate(1e6, START_S + 1.0) == MAX_HZ
    assert allocation.allocated_hz == MAX_HZ
    assert allocation.rate_hz(START_S + 1.0) == MAX_HZ


def test_silence_for_the_periods_falls_back_to_the_minimum_and_is_noted_once() -> None:
    allocation = fresh()
    allocation.allocate(12.0, START_S)
    assert allocation.rate_hz(START_S + DEADLINE_S) == 12.0
    assert allocation.note_lapse(START_S + DEADLINE_S) is None
    late = START_S + DEADLINE_S + 0.1
    assert allocation.rate_hz(late) == MIN_HZ
    assert allocation.note_lapse(late) == pytest.approx(DEADLINE_S + 0.1)
    assert allocation.note_lapse(late + 1.0) is None  # said once
    assert allocation.lapse_noted
    assert allocation.allocate(9.0, late + 2.0) == 9.0  # an optimizer is back
    assert not allocation.lapse_noted
    assert allocation.rate_hz(late + 2.0) == 9.0


def test_a_heartbeat_renews_an_allocation_but_allocates_nothing() -> None:
    allocation = fresh()
    allocation.allocate(12.0, START_S + 2.0)
    assert allocation.heartbeat(START_S + 3.0) == 12.0
    assert allocation.rate_hz(START_S + 3.0 + DEADLINE_S) == 12.0
    assert allocation.rate_hz(START_S + 3.0 + DEADLINE_S + 0.01) == MIN_HZ


def test_a_heartbeat_renews_the_wait_for_a_first_allocation() -> None:
    """A fleet joining at once is admitted over several rounds: the optimizer is alive."""
    allocation = fresh()
    for k in range(1, 20):  # ten deadlines' worth of rounds, one every period
        now = START_S + k * PERIOD_S
        assert allocation.heartbeat(now) is None
        assert allocation.waiting(now + DEADLINE_S)
        assert allocation.note_lapse(now + DEADLINE_S) is None
    last = START_S + 19 * PERIOD_S
    assert allocation.lapsed(last + DEADLINE_S + 0.01)  # silence still ends in the fail-safe


def test_a_long_wait_is_noted_once_and_ends_with_the_allocation() -> None:
    allocation = fresh()
    assert allocation.note_long_wait(START_S + DEADLINE_S) is None  # not longer than usual
    allocation.heartbeat(START_S + DEADLINE_S)
    waited = allocation.note_long_wait(START_S + DEADLINE_S + 0.5)
    assert waited == pytest.approx(DEADLINE_S + 0.5)
    assert allocation.note_long_wait(START_S + DEADLINE_S + 1.0) is None  # said once
    allocation.allocate(12.0, START_S + DEADLINE_S + 1.0)
    assert allocation.note_long_wait(START_S + DEADLINE_S + 1.0) is None  # allocated


def test_a_heartbeat_after_the_fail_safe_allocates_nothing() -> None:
    allocation = fresh()
    late = START_S + DEADLINE_S + 0.1
    assert allocation.note_lapse(late) is not None
    assert allocation.heartbeat(late + 0.1) is None
    assert allocation.lapsed(late + 0.1)
    assert allocation.rate_hz(late + 0.1) == MIN_HZ


def test_a_new_period_moves_the_deadline_from_the_last_word() -> None:
    allocation = fresh()
    allocation.allocate(12.0, START_S)
    allocation.set_period(2 * PERIOD_S)
    assert allocation.deadline == START_S + 2 * DEADLINE_S
    assert allocation.rate_hz(START_S + 2 * DEADLINE_S) == 12.0


def test_the_wait_for_a_first_allocation_counts_from_the_known_size() -> None:
    allocation = fresh()
    sized = START_S + DEADLINE_S - 0.1
    allocation.size_known(sized)
    assert allocation.waiting(sized + DEADLINE_S)
    assert allocation.lapsed(sized + DEADLINE_S + 0.01)


def test_a_size_does_not_restart_the_wait_once_the_fail_safe_was_noted() -> None:
    allocation = fresh()
    late = START_S + DEADLINE_S + 0.1
    assert allocation.note_lapse(late) is not None
    allocation.size_known(late)
    assert allocation.lapsed(late)
    assert not allocation.waiting(late)


def test_a_size_does_not_renew_an_allocation() -> None:
    allocation = fresh()
    allocation.allocate(12.0, START_S)
    allocation.size_known(START_S + DEADLINE_S)
    assert allocation.rate_hz(START_S + DEADLINE_S + 0.01) == MIN_HZ


def test_in_force_is_what_the_rate_in_force_says_up_to_its_deadline() -> None:
    allocation = fresh()
    assert allocation.in_force() is None
    allocation.allocate(12.0, START_S)
    rate, until = allocation.in_force() or (0.0, 0.0)
    assert (rate, until) == (12.0, START_S + DEADLINE_S)
    assert allocation.rate_hz(until) == rate
    assert allocation.rate_hz(until + 0.01) == MIN_HZ
