import math

import numpy as np
import pytest

from dbml.core import (
    ChannelSpec,
    DbmlError,
    LinkSpec,
    Problem,
    SpecError,
    Status,
    Strategy,
    allocate,
)

R1_BYTES, R2_BYTES = 84_000, 21_000


def teleop(p1: float, p2: float, *, bandwidth_mbit: float = 11, **kwargs: object) -> Problem:
    return Problem(
        (
            ChannelSpec("/r1/camera", 1, 16, R1_BYTES, p1),
            ChannelSpec("/r2/camera", 1, 16, R2_BYTES, p2),
        ),
        bandwidth_mbit=bandwidth_mbit,
        **kwargs,  # type: ignore[arg-type]
    )


# Table 2 of the paper as printed: raw priority (eq. 7 of the printed tc) -> f (Hz), bandwidth %.
# The priorities are exact fractions of the printed tc so the test does not depend on eq. 7's code.
TABLE2 = [
    # p1, p2, f1, f2, bw1, bw2
    (0.0, 10 / 17, 12.37, 16, 75.56, 24.44),
    (0.0, 0.0, 12.37, 16, 75.56, 24.44),
    (14 / 17, 0.0, 16, 1.48, 97.75, 2.25),
    (10 / 17, 0.0, 16, 1.48, 97.75, 2.25),
    (15 / 17, 0.0, 16, 1.48, 97.75, 2.25),
    (5 / 17, 5 / 17, 13, 13.48, 79.42, 20.58),
    (1.0, 0.0, 16, 1.48, 97.75, 2.25),
    (0.0, 10 / 17, 12.37, 16, 75.56, 24.44),
    (0.0, 13 / 17, 12.37, 16, 75.56, 24.44),
    (0.0, 1.0, 12.37, 16, 75.56, 24.44),
]


@pytest.mark.parametrize("strategy", [Strategy.PAPER, Strategy.LP])
@pytest.mark.parametrize(("step", "row"), list(enumerate(TABLE2, start=1)))
def test_table2_rows(strategy: Strategy, step: int, row: tuple[float, ...]) -> None:
    p1, p2, f1, f2, bw1, bw2 = row
    allocation = allocate(teleop(p1, p2), strategy=strategy)
    assert allocation.status is Status.OPTIMAL
    r1, r2 = allocation.channels
    assert round(r1.rate_hz, 2) == f1
    assert round(r2.rate_hz, 2) == f2
    assert round(r1.share * 100, 2) == bw1
    assert round(r2.share * 100, 2) == bw2
    assert allocation.total_bytes_per_s == pytest.approx(1_375_000)


def test_step1_exact_values() -> None:
    allocation = allocate(teleop(0.0, 10 / 17))
    r1, r2 = allocation.channels
    assert r1.floor_hz == 1.0
    assert r2.floor_hz == 16.0
    assert r2.normalized_priority == 1.0
    assert r1.rate_hz == pytest.approx((1_375_000 - 16 * 21_000) / 84_000)
    assert r1.bytes_per_s == pytest.approx(1_039_000)
    assert allocation.budget_bytes_per_s == 1_375_000


def test_static_is_the_papers_fixed_baseline() -> None:
    allocation = allocate(teleop(1.0, 0.0), strategy="static")
    # 1,375,000 B/s over 105,000 bytes per pair of frames: 13.095 Hz for both, whatever priority.
    np.testing.assert_allclose(allocation.rate_hz, [1_375_000 / 105_000] * 2)
    np.testing.assert_array_equal(allocation.floor_hz, [1.0, 1.0])


def test_static_caps_at_max_and_respects_min() -> None:
    roomy = allocate(teleop(0, 0, bandwidth_mbit=100), strategy="static")
    np.testing.assert_array_equal(roomy.rate_hz, [16.0, 16.0])
    problem = Problem(
        (ChannelSpec("/big", 1, 5, 1000), ChannelSpec("/needy", 8, 9, 1000)),
        bandwidth_mbit=10_000 / 125_000,
    )
    # B / sum w = 5 Hz is below /needy's minimum of 8: it gets 8, /big what fits (2 Hz).
    allocation = allocate(problem, strategy="static")
    assert allocation.status is Status.OPTIMAL
    np.testing.assert_allclose(allocation.rate_hz, [2.0, 8.0])


def test_fair_splits_equal_priorities_equally() -> None:
    # The paper's proposed modification, Step 2: both robots at 13.1 Hz.
    allocation = allocate(teleop(0.0, 0.0), strategy="fair")
    np.testing.assert_allclose(allocation.rate_hz, [1_375_000 / 105_000] * 2)


def test_fair_honours_priority_floors_and_maximums() -> None:
    step6 = allocate(teleop(5 / 17, 5 / 17), strategy="fair")
    # Floors 13 and 4 Hz; water level at 13.095 Hz sits above both.
    np.testing.assert_allclose(step6.rate_hz, [1_375_000 / 105_000] * 2)
    step3 = allocate(teleop(14 / 17, 0.0), strategy="fair")
    np.testing.assert_allclose(step3.rate_hz, [16.0, 31_000 / 21_000])


def test_everything_fits_means_everything_at_max() -> None:
    for strategy in Strategy:
        allocation = allocate(teleop(0.3, 0.7, bandwidth_mbit=100), strategy=strategy)
        assert allocation.status is Status.OPTIMAL
        np.testing.assert_allclose(allocation.rate_hz, [16.0, 16.0])


def test_utilization_reserves_bandwidth() -> None:
    allocation = allocate(teleop(0.0, 0.0, utilization=0.5))
    assert allocation.budget_bytes_per_s == 687_500
    assert allocation.total_bytes_per_s == pytest.approx(687_500)
    # share stays relative to the full link
    assert sum(c.share for c in allocation.channels) == pytest.approx(0.5)


def test_infeasible_floors_are_pulled_back_within_budget() -> None:
    # R1 at priority 1 on 5 Mbit/s: floors 16 + 1 Hz need 1,365,000 B/s = 10.92 Mbit/s.
    allocation = allocate(teleop(1.0, 0.0, bandwidth_mbit=5))
    assert allocation.status is Status.INFEASIBLE
    assert allocation.message.startswith(
        "priority floors need 10.920 Mbit/s but the budget allows 5.000 Mbit/s"
    )
    assert allocation.total_bytes_per_s == pytest.approx(625_000)
    assert allocation.total_bytes_per_s <= 625_000 * (1 + 1e-12)
    # Pulled back toward fmin by one factor: R2's floor is its minimum, R1 takes the rest.
    np.testing.assert_allclose(allocation.rate_hz, [(625_000 - 21_000) / 84_000, 1.0])


def test_infeasible_minimums_run_at_a_common_fraction() -> None:
    # Minimum 1 Hz each needs 105,000 B/s = 0.84 Mbit/s; give 0.42 Mbit/s.
    for strategy in Strategy:
        allocation = allocate(teleop(0.5, 0.5, bandwidth_mbit=0.42), strategy=strategy)
        assert allocation.status is Status.INFEASIBLE
        assert allocation.message.startswith(
            "minimum rates need 0.840 Mbit/s but the budget allows 0.420 Mbit/s"
        )
        assert "50.0% of its minimum" in allocation.message
        np.testing.assert_allclose(allocation.rate_hz, [0.5, 0.5])


def test_lp_honours_an_uplink() -> None:
    # R1's own uplink carries 4 Mbit/s = 500,000 B/s: R1 gets 500,000 / 84,000 Hz, R2 its max.
    problem = teleop(0.0, 0.0, links=(LinkSpec("r1-uplink", 4, ("/r1/camera",)),))
    allocation = allocate(problem, strategy="lp")
    assert allocation.status is Status.OPTIMAL
    np.testing.assert_allclose(allocation.rate_hz, [500_000 / 84_000, 16.0], rtol=1e-7)


def test_lp_tie_break_with_a_shared_radio_prefers_small_messages() -> None:
    # A radio of 8 Mbit/s (1,000,000 B/s) under both cameras: same bytes either way, but the
    # tie-break takes the most messages, so R2 (small frames) goes to 16 Hz and R1 gets the rest.
    problem = teleop(0.0, 0.0, links=(LinkSpec("radio", 8, ("/r1/camera", "/r2/camera")),))
    allocation = allocate(problem, strategy="lp")
    np.testing.assert_allclose(
        allocation.rate_hz, [(1_000_000 - 336_000) / 84_000, 16.0], rtol=1e-7
    )


def test_lp_infeasible_link_is_reported_and_respected() -> None:
    # R1 at priority 1 needs 16 Hz = 10.752 Mbit/s, but its uplink has 4.
    problem = teleop(1.0, 0.0, links=(LinkSpec("r1-uplink", 4, ("/r1/camera",)),))
    allocation = allocate(problem, strategy="lp")
    assert allocation.status is Status.INFEASIBLE
    assert allocation.message.startswith(
        "priority floors need 10.752 Mbit/s but link 'r1-uplink' allows 4.000 Mbit/s"
    )
    assert allocation.rate_hz[0] * 84_000 <= 500_000 * (1 + 1e-9)
    assert allocation.total_bytes_per_s <= 1_375_000 * (1 + 1e-9)


@pytest.mark.parametrize("strategy", ["paper", "static", "fair"])
def test_other_strategies_reject_links(strategy: str) -> None:
    problem = teleop(0.0, 0.0, links=(LinkSpec("r1-uplink", 4, ("/r1/camera",)),))
    with pytest.raises(
        SpecError, match=rf"strategy='{strategy}' does not support links .*use strategy 'lp'"
    ):
        allocate(problem, strategy=strategy)


def test_unknown_strategy() -> None:
    with pytest.raises(
        SpecError, match=r"strategy='greedy' is not one of: paper, static, fair, lp"
    ):
        allocate(teleop(0, 0), strategy="greedy")
    assert issubclass(SpecError, DbmlError)


def test_allocation_is_read_only_and_ordered() -> None:
    allocation = allocate(teleop(0.0, 0.5))
    assert allocation.topics == ("/r1/camera", "/r2/camera")
    assert [c.topic for c in allocation.channels] == ["/r1/camera", "/r2/camera"]
    with pytest.raises(ValueError, match="read-only"):
        allocation.rate_hz[0] = 0.0
    assert set(allocation.rates_by_topic()) == {"/r1/camera", "/r2/camera"}
    assert allocation.success
    assert not math.isnan(allocation.total_bytes_per_s)
