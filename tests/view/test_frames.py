"""What the live view shows, built from parameter values as a process holds them."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.protocol import names
from dbml.protocol.schema import ParamError, ParamValue, Writer
from dbml.view import frames

R1, R2 = "/r1/camera", "/r2/camera"
OPERATOR = frozenset({Writer.OPERATOR})


def table2_step1() -> dict[str, ParamValue]:
    """The values of the demo's step 1 as the operator holds them (Table 2's inputs and rates)."""
    values: dict[str, ParamValue] = {
        names.BANDWIDTH: 11.0,
        names.UTILIZATION: 1.0,
        names.STATUS: "optimal",
        names.STATUS_MESSAGE: "11.000 Mbit/s of a 11.000 Mbit/s budget allocated",
        names.ROUND: 7.0,
    }
    for topic, size, priority, rate in ((R1, 84_000, 0.0, 12.369047619), (R2, 21_000, 10 / 17, 16)):
        values |= {
            names.min_rate(topic): 1.0,
            names.max_rate(topic): 16.0,
            names.size(topic): float(size),
            names.priority(topic): priority,
            names.current_value(topic): float(rate),
            names.managed(topic): True,
        }
    return values


def test_the_budget_is_the_estimate_below_the_configured_one() -> None:
    values = table2_step1() | {names.UTILIZATION: 0.9, names.ESTIMATE: 6.0}
    budget = frames.budget_frame(values, estimator_phase="hold")
    assert budget.as_json() == {
        "max_bandwidth_mbit": 11.0,
        "utilization": 0.9,
        "budget_mbit": 6.0,
        "estimate_mbit": 6.0,
        "estimator_phase": "hold",
    }
    assert set(budget.as_json()) == set(frames.BUDGET_SCHEMA["properties"])


def test_the_topics_are_the_paper_s_names_beside_dbml_s() -> None:
    assert frames.frequency_topic(R1) == "/r1/camera/dbm/frequency/current_value"
    assert frames.delivered_topic(R1) == "/r1/camera/dbm/frequency/delivered_value"
    assert frames.image_topic(R1) == "/r1/camera/optimized"
    assert frames.ALLOCATION_TOPIC == "/dbm/allocation"


def test_what_a_viewer_may_set_is_what_an_operator_writes() -> None:
    settable = frames.settable_names([R2, R1])
    assert settable == [names.BANDWIDTH, names.UTILIZATION, names.priority(R1), names.priority(R2)]
    assert names.priority(R1) in settable
    assert names.priority(R2) in settable
    assert names.STATUS not in settable
    assert names.current_value(R1) not in settable
    assert names.size(R1) not in settable  # the publisher's, not an operator's


@pytest.mark.parametrize(
    ("name", "value", "why"),
    [
        (names.BANDWIDTH, -3, "/dbm/max_bandwidth_in_mbit=-3 must be"),
        (names.BANDWIDTH, math.nan, "/dbm/max_bandwidth_in_mbit=nan is not finite"),
        (names.BANDWIDTH, "NaN", "/dbm/max_bandwidth_in_mbit='NaN' is not a number"),
        (names.BANDWIDTH, None, "a value is required"),
        (names.BANDWIDTH, [1], "must be a bool, number or string"),
        (names.UTILIZATION, 1.5, "/dbm/max_bandwidth_utilization=1.5 must be"),
        (names.priority(R1), 2.0, "/r1/camera/dbm/priority=2.0 must be"),
        (names.priority("/r9/camera"), 0.5, "not a parameter a viewer may set"),
        (names.current_value(R1), 3.0, "not a parameter a viewer may set"),
        (names.STRATEGY, "fair", "not a parameter a viewer may set"),
        ("/" * 300, 1.0, "'" + "/" * 60),
    ],
)
def test_a_bad_setting_is_refused_naming_the_name_and_the_value(
    name: str, value: object, why: str
) -> None:
    with pytest.raises(ParamError, match=re.escape(why)) as raised:
        frames.check_setting(name, value, [R1, R2], writers=OPERATOR)
    assert len(str(raised.value)) < 200  # a name from the network is shortened


def test_a_good_setting_passes_as_the_schema_takes_it() -> None:
    assert frames.check_setting(names.BANDWIDTH, 5, [R1], writers=OPERATOR) == 5.0
    assert frames.check_setting(names.priority(R1), 1, [R1], writers=OPERATOR) == 1.0
    publisher = frozenset({Writer.PUBLISHER})  # a robot's process: its own priority source
    assert frames.check_setting(names.priority(R1), 0.5, [R1], writers=publisher) == 0.5


def test_a_setting_the_role_does_not_write_is_refused() -> None:
    optimizer = frozenset({Writer.OPTIMIZER, Writer.ESTIMATOR})
    with pytest.raises(ParamError, match=r"=5.0: this process does not write it"):
        frames.check_setting(names.BANDWIDTH, 5.0, [R1], writers=optimizer)


@given(st.integers(min_value=1, max_value=10_000_000))
def test_an_image_holds_exactly_the_frame(size: int) -> None:
    height, width = frames.image_shape(size)
    assert height * width == size
    assert 1 <= height <= width


def test_the_demo_s_frames_are_pictures_of_one_shape() -> None:
    assert frames.image_shape(84_000) == (200, 420)
    assert frames.image_shape(21_000) == (100, 210)
