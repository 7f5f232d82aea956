"""The reports between processes (the operator's, a bridge's): named keys, malformed ones named."""

from __future__ import annotations

import json
from typing import Any

import pytest

from dbml.core.errors import SpecError
from dbml.estimator import Phase
from dbml.experiment.analysis import Arrival, Tick
from dbml.experiment.report import (
    PUBLISH_REPORT,
    TICK,
    OperatorReport,
    PublishReport,
    PublishTiming,
)
from dbml.protocol.messages import EstimatorState

FRAMES = (
    Arrival(robot=0, seq=12, sent_s=100.25, arrival_s=100.3, size_bytes=84_000, rate_hz=5.95),
    Arrival(robot=1, seq=None, sent_s=None, arrival_s=100.4, size_bytes=21_000, rate_hz=None),
)
STATE = EstimatorState(
    phase=Phase.DECREASE, received_mbit=3.2, queue_delay_s=0.04, lost=1, decided_at_s=100.125
)
REPORT = OperatorReport(
    Tick(
        t_s=100.5,
        allocated_hz=(5.95, None),
        budget_mbit=5.5,
        estimate_mbit=5.5,
        estimator=STATE,
        variants=("optimized", "full"),
    ),
    FRAMES,
)


def test_a_report_survives_a_json_line_unchanged() -> None:
    line = json.dumps(REPORT.encode())
    assert OperatorReport.decode(json.loads(line)) == REPORT
    bare = OperatorReport(Tick(1.0, (), None, None))
    assert OperatorReport.decode(json.loads(json.dumps(bare.encode()))) == bare


def test_a_frame_travels_with_named_keys() -> None:
    message = REPORT.encode()
    assert message["type"] == TICK
    assert message["frames"][0] == {
        "robot": 0,
        "seq": 12,
        "sent_s": 100.25,
        "arrival_s": 100.3,
        "size_bytes": 84_000,
        "rate_hz": 5.95,
        "ssim": None,
    }
    assert message["estimator"]["decided_at_s"] == 100.125


def _broken(path: tuple[str | int, ...], value: object) -> dict[str, Any]:
    message: dict[str, Any] = json.loads(json.dumps(REPORT.encode()))
    target: Any = message
    for step in path[:-1]:
        target = target[step]
    target[path[-1]] = value
    return message


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (("type",), "done", "type='done' is not 'tick'"),
        (("t",), "soon", "t='soon' is not a number"),
        (("frames",), None, "frames=None is not a list"),
        (("frames", 0), [0, 12], r"frames\[0\]=\[0, 12\] is not a JSON object"),
        (("frames", 1, "robot"), -1, r"frames\[1\]\.robot=-1 is not a count"),
        (("frames", 0, "seq"), 1.5, r"frames\[0\]\.seq=1\.5 is not a count"),
        (("frames", 0, "arrival_s"), None, r"frames\[0\]\.arrival_s=None is not a number"),
        (("frames", 0, "size_bytes"), True, r"frames\[0\]\.size_bytes=True is not a count"),
        (("allocated_hz", 0), "fast", r"allocated_hz\[0\]='fast' is not a number"),
        (("variants", 1), 3, r"variants\[1\]=3 is not a string"),
        (("estimator", "phase"), "up", "phase='up' is not one of"),
    ],
)
def test_a_malformed_report_names_the_field_and_the_value(
    path: tuple[str | int, ...], value: object, match: str
) -> None:
    with pytest.raises(SpecError, match=match):
        OperatorReport.decode(_broken(path, value))


PUBLISHES = PublishReport(
    (
        PublishTiming("/r1/camera/optimized", 9, 1, 2.5, 0.4),
        PublishTiming("/r2/camera/optimized", 0, 0, None, None),
    )
)


def test_a_bridges_report_survives_a_json_line_unchanged() -> None:
    message = json.loads(json.dumps(PUBLISHES.encode()))
    assert message["type"] == PUBLISH_REPORT
    assert message["publishers"][0] == {
        "topic": "/r1/camera/optimized",
        "published": 9,
        "dropped": 1,
        "max_ms": 2.5,
        "p99_ms": 0.4,
    }
    assert PublishReport.decode(message) == PUBLISHES


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        (("type",), "tick", "publish report: type='tick' is not 'publish_stats'"),
        (("publishers",), {}, "publish report: publishers={} is not a list"),
        (("publishers", 0), "r1", r"publishers\[0\]='r1' is not a JSON object"),
        (("publishers", 0, "topic"), 1, r"publishers\[0\]\.topic=1 is not a string"),
        (("publishers", 1, "dropped"), -2, r"publishers\[1\]\.dropped=-2 is not a count"),
        (("publishers", 0, "max_ms"), "long", r"publishers\[0\]\.max_ms='long' is not a number"),
    ],
)
def test_a_malformed_publish_report_names_the_field_and_the_value(
    path: tuple[str | int, ...], value: object, match: str
) -> None:
    message: Any = json.loads(json.dumps(PUBLISHES.encode()))
    target: Any = message
    for step in path[:-1]:
        target = target[step]
    target[path[-1]] = value
    with pytest.raises(SpecError, match=match):
        PublishReport.decode(message)
