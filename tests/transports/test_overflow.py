"""What a structure fed by the network says when it is flooded: once, or once per interval."""

from __future__ import annotations

import logging
import math

import pytest

from dbml.transports.overflow import ThrottledLog

log = logging.getLogger("dbml.test")


def test_a_flood_of_bad_values_is_logged_once_per_interval_with_a_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    now = [0.0]
    throttled = ThrottledLog(10.0, log=log, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="dbml.test"):
        for _ in range(1000):  # a 1 kHz NaN publisher, for one second
            throttled.warning("/a/dbm/priority", "%s: ignoring priority %r", "/a", math.nan)
            now[0] += 0.001
        throttled.warning("/b/dbm/priority", "%s: ignoring priority %r", "/b", 2.0)
        now[0] = 10.5
        throttled.warning("/a/dbm/priority", "%s: ignoring priority %r", "/a", math.nan)
    assert [r.getMessage() for r in caplog.records] == [
        "/a: ignoring priority nan (1 value(s) ignored; logged at most every 10 s)",
        "/b: ignoring priority 2.0 (1 value(s) ignored; logged at most every 10 s)",
        "/a: ignoring priority nan (1000 value(s) ignored; logged at most every 10 s)",
    ]


def test_the_keys_remembered_are_bounded(caplog: pytest.LogCaptureFixture) -> None:
    throttled = ThrottledLog(10.0, log=log, clock=lambda: 0.0, bound=2)
    with caplog.at_level(logging.WARNING, logger="dbml.test"):
        for key in ("a", "b", "a", "c", "a", "b"):  # "c" pushes the oldest out: "b"
            throttled.warning(key, "%s", key)
    assert [r.getMessage().split(" ")[0] for r in caplog.records] == ["a", "b", "c", "b"]
    assert len(throttled._state) == 2
