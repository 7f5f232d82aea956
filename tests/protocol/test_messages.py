"""Wire messages that are not parameters: each one's encoding, and what decoding refuses."""

from __future__ import annotations

import contextlib
import json
import math
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.core import Status, Strategy, TransportError
from dbml.protocol.messages import (
    MAX_REPORTED_CHANNELS,
    MAX_ROUND_BYTES,
    ChannelRound,
    RoundReport,
)

R1 = ChannelRound(
    topic="/r1/camera",
    managed=True,
    priority=0.0,
    min_hz=1.0,
    max_hz=16.0,
    size_bytes=84_000.0,
    normalized_priority=0.0,
    floor_hz=1.0,
    rate_hz=12.369047619047619,
    share=0.7556,
)
R2 = ChannelRound(topic="/r2/scan", managed=False, priority=0.5, min_hz=1.0, max_hz=10.0)
REPORT = RoundReport(
    round=7,
    status=Status.OPTIMAL,
    message="11.000 Mbit/s of a 11.000 Mbit/s budget allocated",
    strategy=Strategy.PAPER,
    budget_mbit=11.0,
    channels=(R1, R2),
)


def document(**changes: Any) -> bytes:
    return json.dumps(REPORT.as_json() | changes).encode()


def channel(**changes: Any) -> bytes:
    return document(channels=[R1.as_json() | changes])


def test_a_report_travels_whole() -> None:
    assert RoundReport.decode(REPORT.encode()) == REPORT
    assert REPORT.channel("/r2/scan") == R2
    assert REPORT.channel("/r3/lidar") is None
    # Only managed channels count: R2 runs at its maximum outside the budget.
    assert REPORT.allocated_mbit == pytest.approx(12.369047619047619 * 84_000 * 8 / 1e6)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\xff", r"is not JSON"),
        (b"[]", r"round report=\[\] is not an object"),
        (document(round=-1), r"round=-1 is not a count"),
        (document(round=True), r"round=True is not a count"),
        (document(status="great"), r"status='great' is not a status"),
        (document(strategy="magic"), r"strategy='magic' is not a strategy"),
        (document(status_message=None), r"status_message=None is not text"),
        (document(budget_mbit=-3), r"budget_mbit=-3 must be"),
        (document(budget_mbit=math.inf), r"budget_mbit=inf is not finite"),
        (document(channels={}), r"channels={} is not a list"),
        (channel(topic="r1 camera"), r"topic='r1 camera' must look like"),
        (channel(managed="yes"), r"/r1/camera: managed='yes' is not a boolean"),
        (channel(priority=2), r"/r1/camera: priority=2 must be within \[0, 1\]"),
        (channel(rate_hz=math.nan), r"/r1/camera: rate_hz=nan is not finite"),
        (channel(size_bytes=0), r"/r1/camera: size_bytes=0 must be"),
        (channel(share="a lot"), r"/r1/camera: share='a lot' is not a number"),
        (json.dumps({"round": 1}).encode(), r"status=None is not a status"),
    ],
)
def test_a_malformed_report_is_refused_naming_what(data: bytes, message: str) -> None:
    with pytest.raises(TransportError, match=message):
        RoundReport.decode(data)


def test_a_report_too_large_or_too_long_is_refused_unread() -> None:
    with pytest.raises(TransportError, match=f"more than {MAX_ROUND_BYTES}"):
        RoundReport.decode(b" " * (MAX_ROUND_BYTES + 1))
    many = [R2.as_json()] * (MAX_REPORTED_CHANNELS + 1)
    with pytest.raises(TransportError, match=f"at most {MAX_REPORTED_CHANNELS}"):
        RoundReport.decode(document(channels=many))


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=4,
)


@given(
    st.binary(max_size=64)
    | st.dictionaries(st.sampled_from(sorted(REPORT.as_json())), JSON).map(
        lambda d: json.dumps(REPORT.as_json() | d).encode()
    )
    | st.dictionaries(st.sampled_from(sorted(R1.as_json())), JSON).map(
        lambda d: json.dumps(REPORT.as_json() | {"channels": [R1.as_json() | d]}).encode()
    )
)
def test_anything_decodes_to_a_report_or_a_transport_error(data: bytes) -> None:
    with contextlib.suppress(TransportError):
        RoundReport.decode(data)
