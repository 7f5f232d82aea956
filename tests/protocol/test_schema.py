"""The wire schema: one validation of every value, and every name with a writer and a rule."""

from __future__ import annotations

import math
from typing import Any, cast

import pytest

from dbml.protocol import names
from dbml.protocol.schema import (
    PARAMETERS,
    Kind,
    ParamError,
    Scope,
    check_param,
    lookup,
)
from dbml.transports.base import ParamValue

CAMERA = "/r1/camera"


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        (names.BANDWIDTH, math.nan, r"^/dbm/max_bandwidth_in_mbit=nan is not finite$"),
        (names.BANDWIDTH, math.inf, r"is not finite$"),
        (names.BANDWIDTH, 10**400, r"is not finite$"),
        (names.BANDWIDTH, -1, r"=-1 must be within \(0, 1e\+06\]$"),
        (names.BANDWIDTH, "eleven", r"='eleven' is not a number$"),
        (names.BANDWIDTH, True, r"=True is not a number$"),
        (names.UTILIZATION, 1.5, r"=1.5 must be within \(0, 1\]$"),
        (names.PERIOD, 1e-6, r"=1e-06 must be within \[0.01, 3600\]$"),
        (names.PERIOD, math.inf, r"is not finite$"),
        (names.STRATEGY, "fastest", r"^/dbm/strategy='fastest' is not valid$"),
        (names.STRATEGY, 3, r"^/dbm/strategy=3 is not valid$"),
        (names.max_rate(CAMERA), 0, r"^/r1/camera/dbm/frequency/max=0 must be within"),
        (names.max_rate(CAMERA), 1e12, r"=1000000000000.0 must be within \(0, 1e\+06\]$"),
        (names.current_value(CAMERA), math.nan, r"frequency/current_value=nan is not finite"),
        (names.size(CAMERA), 1e15, r"message_size_in_bytes=1000000000000000.0 must be within"),
        (names.priority(CAMERA), 10**400, r"priority=1000.* is not finite$"),
        (names.priority(CAMERA), -0.5, r"priority=-0.5 must be within \[0, 1\]$"),
        (names.managed(CAMERA), "yes", r"managed='yes' is not valid$"),
        (names.STATUS_MESSAGE, "x" * 20_000, r"status_message='xxx.*\.\.\. is not valid$"),
    ],
)
def test_bad_values_are_refused_naming_key_and_value(
    name: str, value: ParamValue, message: str
) -> None:
    with pytest.raises(ParamError, match=message):
        check_param(name, value)


def test_good_values_come_back_typed_and_unknown_names_pass() -> None:
    assert check_param(names.BANDWIDTH, 11) == 11.0
    assert isinstance(check_param(names.BANDWIDTH, 11), float)
    assert check_param(names.STRATEGY, "lp") == "lp"
    assert check_param(names.managed(CAMERA), True) is True
    assert check_param(names.priority(CAMERA), None) is None  # deleted
    assert check_param("/someone/else", cast(Any, [1, 2])) == cast(Any, [1, 2])


def test_every_parameter_has_a_writer_a_rule_and_one_name() -> None:
    fields = [(p.scope, p.field) for p in PARAMETERS]
    assert len(fields) == len(set(fields))
    for parameter in PARAMETERS:
        assert parameter.writers, parameter
        if parameter.kind is Kind.NUMBER:
            assert parameter.minimum is not None or parameter.maximum is not None, parameter
        if parameter.kind is Kind.CHOICE:
            assert parameter.choices, parameter
        name = parameter.name if parameter.scope is Scope.GLOBAL else parameter.key(CAMERA)
        assert lookup(name) == (parameter, None if parameter.scope is Scope.GLOBAL else CAMERA)


def test_the_paper_names_and_their_ros2_spelling() -> None:
    assert names.BANDWIDTH == "/dbm/max_bandwidth_in_mbit"
    assert names.PERIOD == "/dbm/optimization_rate_in_seconds"
    assert names.min_rate(CAMERA) == "/r1/camera/dbm/frequency/min"
    assert names.size(CAMERA) == "/r1/camera/dbm/message_size_in_bytes"
    assert names.PRIORITY_SUFFIX == "/dbm/priority"
    assert lookup(names.min_rate(CAMERA)) is not None
    assert [p.ros2_name for p in PARAMETERS if p.scope is Scope.CHANNEL][:2] == [
        "frequency.min",
        "frequency.max",
    ]
    assert lookup("/r1/camera/dbm/unknown") is None
    assert lookup("/dbm/frequency/min") is None  # a channel's field is no global
