"""The rate ledger: which increases fit while decreases are not yet applied (no network)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbml.runtime.ledger import Limit, RateLedger

TIMEOUT_S = 0.25
BUDGET = Limit(frozenset({"a", "b", "c"}), 1_000.0)


def test_an_increase_waits_for_the_decrease_that_makes_its_room_then_for_its_drain() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    # a runs 600 B/s and goes down to 200; b runs 400 and wants 800: only once a is down.
    ledger.decrease("a", before_bytes_per_s=600.0, drain_s=0.05, now=10.0)
    current = {"a": 200.0, "b": 400.0}
    assert ledger.admit({"b": 800.0}, current, [BUDGET]) == {}
    ledger.acknowledged("a", now=10.02)
    assert ledger.settle(10.03) == []
    assert ledger.admit({"b": 800.0}, current, [BUDGET]) == {}  # its last frame may be queued
    assert ledger.next_change_s() == pytest.approx(10.07)
    assert ledger.settle(10.07) == []
    assert ledger.pending == frozenset()
    assert ledger.admit({"b": 800.0}, current, [BUDGET]) == {"b": 800.0}


def test_an_increase_that_fits_beside_an_unapplied_decrease_goes_at_once() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=600.0, drain_s=0.05, now=10.0)
    current = {"a": 200.0, "b": 100.0, "c": 0.0}
    # 600 + 100 + 300 = 1,000: c's first allocation fits; b's rise too would not.
    assert ledger.admit({"c": 300.0, "b": 200.0}, current, [BUDGET]) == {"c": 300.0}
    # order decides
    assert ledger.admit({"b": 200.0, "c": 300.0}, current, [BUDGET]) == {"b": 200.0}


def test_an_unacknowledged_decrease_counts_as_applied_after_the_timeout_and_is_named() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=600.0, drain_s=0.05, now=10.0)
    assert ledger.next_change_s() == pytest.approx(10.25)
    assert ledger.settle(10.2) == []
    assert ledger.admit({"b": 800.0}, {"a": 200.0, "b": 400.0}, [BUDGET]) == {}
    assert ledger.settle(10.25) == ["a"]
    assert ledger.admit({"b": 800.0}, {"a": 200.0, "b": 400.0}, [BUDGET]) == {"b": 800.0}


def test_a_late_acknowledgement_still_drains_in_full() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=600.0, drain_s=0.2, now=10.0)
    ledger.acknowledged("a", now=10.2)
    assert ledger.next_change_s() == pytest.approx(10.4)
    assert ledger.settle(10.3) == []
    assert ledger.pending == {"a"}
    assert ledger.settle(10.4) == []
    assert ledger.pending == frozenset()


def test_a_second_decrease_before_the_first_settled_keeps_the_higher_rate_before() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=600.0, drain_s=0.0, now=10.0)
    ledger.decrease("a", before_bytes_per_s=300.0, drain_s=0.0, now=10.1)
    assert ledger.committed("a", 100.0) == 600.0
    assert ledger.committed("b", 100.0) == 100.0


def test_a_link_limits_its_own_channels_only() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    uplink = Limit(frozenset({"a"}), 300.0)
    current = {"a": 100.0, "b": 100.0}
    assert ledger.admit({"a": 400.0, "b": 700.0}, current, [BUDGET, uplink]) == {"b": 700.0}
    assert ledger.admit({"x": 5_000.0}, current, [BUDGET, uplink]) == {"x": 5_000.0}  # in no limit


def test_a_decrease_of_a_channel_gone_still_counts_until_it_settles() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=600.0, drain_s=0.0, now=10.0)
    assert ledger.admit({"b": 500.0}, {"b": 0.0}, [BUDGET]) == {}
    ledger.forget(["b"])
    assert ledger.admit({"b": 500.0}, {"b": 0.0}, [BUDGET]) == {"b": 500.0}


def test_a_rise_goes_part_of_the_way_once_the_room_made_reaches_its_floor() -> None:
    """A rise of 400 -> 800 paid by two cuts of 200: its first half waits for one of them."""
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=400.0, drain_s=0.0, now=10.0)
    ledger.decrease("c", before_bytes_per_s=200.0, drain_s=0.0, now=10.0)
    current = {"a": 200.0, "b": 400.0, "c": 0.0}
    assert ledger.admit({"b": 800.0}, current, [BUDGET], floors={"b": 600.0}) == {}
    ledger.acknowledged("c", now=10.01)
    ledger.settle(10.01)  # 200 of room: enough for a floor of 600, not for one of 650
    assert ledger.admit({"b": 800.0}, current, [BUDGET], floors={"b": 650.0}) == {}
    assert ledger.admit({"b": 800.0}, current, [BUDGET], floors={"b": 600.0}) == {"b": 600.0}
    current["b"] = 600.0  # the step was pushed; the rest goes in full only
    assert ledger.admit({"b": 800.0}, current, [BUDGET]) == {}
    ledger.acknowledged("a", now=10.02)
    ledger.settle(10.02)
    assert ledger.admit({"b": 800.0}, current, [BUDGET]) == {"b": 800.0}


def test_a_step_takes_the_room_there_is_and_the_next_rise_fits_beside_it_or_not() -> None:
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    ledger.decrease("a", before_bytes_per_s=500.0, drain_s=0.0, now=10.0)
    current = {"a": 100.0, "b": 300.0, "c": 0.0}  # committed 500 + 300: 200 of room
    wanted = {"b": 700.0, "c": 100.0}
    assert ledger.admit(wanted, current, [BUDGET], floors={"b": 450.0}) == {"b": 500.0}
    assert ledger.admit(wanted, current, [BUDGET], floors={"b": 550.0}) == {"c": 100.0}
    assert ledger.admit(wanted, current, [BUDGET]) == {"c": 100.0}  # no floor: no step


spends = st.floats(min_value=0.0, max_value=600.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(
    before=st.dictionaries(st.sampled_from("abc"), spends, max_size=3),
    current=st.fixed_dictionaries(dict.fromkeys("abc", spends)),
    wanted=st.dictionaries(st.sampled_from("abc"), spends, min_size=1, max_size=3),
    floors=st.dictionaries(st.sampled_from("abc"), spends, max_size=3),
)
def test_what_is_admitted_never_takes_the_committed_sum_over_a_limit_it_was_within(
    before: dict[str, float],
    current: dict[str, float],
    wanted: dict[str, float],
    floors: dict[str, float],
) -> None:
    """And greedy: an increase refused would neither fit nor reach its floor beside those before.

    A step reaches its floor and stops short of the rise.
    """
    ledger = RateLedger(ack_timeout_s=TIMEOUT_S)
    for topic, rate in before.items():
        ledger.decrease(topic, before_bytes_per_s=rate, drain_s=0.0, now=0.0)
    committed = {t: max(current[t], before.get(t, 0.0)) for t in "abc"}
    admitted = ledger.admit(wanted, current, [BUDGET], floors=floors)
    load = dict(committed)
    for topic, spend in wanted.items():
        rises = spend > load[topic]
        room = BUDGET.bytes_per_s - sum(load.values())
        fits = load[topic] + room * (1 + 1e-9) + 1e-9 * BUDGET.bytes_per_s >= spend
        steps = topic in floors and room > 0 and load[topic] + room >= floors[topic]
        assert (topic in admitted) == (not rises or fits or steps), (topic, load)
        if topic not in admitted:
            continue
        goes = admitted[topic]
        if rises and not fits:
            assert floors[topic] <= goes < spend
        else:
            assert goes == spend
        load[topic] = max(load[topic], goes)
    if sum(committed.values()) <= BUDGET.bytes_per_s:
        assert sum(load.values()) <= BUDGET.bytes_per_s * (1 + 1e-9)
