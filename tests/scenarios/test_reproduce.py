"""Table 2 of the paper, typed from the printed page, against dbml's replayed scenario."""

import math

import pytest

from dbml.scenarios.reproduce import reproduce_table2
from dbml.scenarios.teleop import STEPS

# step: (R1 tc, p, f Hz, BW %), (R2 tc, p, f Hz, BW %)  -- as printed in the paper
PAPER = {
    1: ((20, 0.00, 12.37, 75.56), (10, 0.59, 16, 24.44)),
    2: ((30, 0.00, 12.37, 75.56), (20, 0.00, 16, 24.44)),
    3: ((6, 0.82, 16, 97.75), (100, 0.00, 1.48, 2.25)),
    4: ((10, 0.59, 16, 97.75), (math.inf, 0.00, 1.48, 2.25)),
    5: ((5, 0.88, 16, 97.75), (math.inf, 0.00, 1.48, 2.25)),
    6: ((15, 0.29, 13, 79.42), (15, 0.29, 13.48, 20.58)),
    7: ((2.5, 1.00, 16, 97.75), (math.inf, 0.00, 1.48, 2.25)),
    8: ((36, 0.00, 12.37, 75.56), (10, 0.59, 16, 24.44)),
    9: ((40, 0.00, 12.37, 75.56), (7, 0.76, 16, 24.44)),
    10: ((50, 0.00, 12.37, 75.56), (3, 1.00, 16, 24.44)),
}


@pytest.mark.parametrize("step", range(1, 11))
def test_every_cell_matches_the_paper(step: int) -> None:
    rows = reproduce_table2()[step - 1]
    for row, (tc, priority, rate, percent) in zip(rows, PAPER[step], strict=True):
        assert row.tc_s == tc
        assert round(row.priority, 2) == priority
        assert round(row.rate_hz, 2) == rate
        assert round(row.share * 100, 2) == percent
        assert row.match
        assert row.static_rate_hz == pytest.approx(1_375_000 / 105_000)


def test_events_stay_within_the_papers_sensor_limits() -> None:
    for step in STEPS:
        for event in step.events:
            assert 0 <= event.distance_m <= 2.0
            assert 0 <= event.speed_m_per_s <= 0.5


def test_a_wrong_rate_is_flagged() -> None:
    from dataclasses import replace

    row = reproduce_table2()[0][0]
    assert not replace(row, rate_hz=12.38).match
    assert not replace(row, share=0.7557).match
