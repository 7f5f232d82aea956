"""The wire messages that are not parameters: what each encodes, and what each refuses.

Everything here arrives from the network: a decode takes only what its message can be, refuses
the rest with the field and the value named, and never raises anything but its error.
"""

from __future__ import annotations

import contextlib
import json
import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dbml.core import Status, Strategy
from dbml.core.errors import SpecError, TransportError
from dbml.estimator import Estimate, Phase
from dbml.protocol.messages import (
    HEARD_MAX,
    HEARD_RECENT_MAX,
    MAX_BEACON_BYTES,
    MAX_NAME_CHARS,
    MAX_REASON_CHARS,
    MAX_REPORT_BYTES,
    MAX_REPORT_FRAMES,
    MAX_REPORTED_CHANNELS,
    MAX_ROUND_BYTES,
    RELEASE_MAX_CHANNELS,
    RELEASE_MAX_S,
    ChannelRound,
    EstimatorState,
    Heard,
    LinkBeacon,
    ReceivedFrame,
    ReceptionReport,
    RoundReport,
)
from dbml.protocol.metadata import SEQ_MAX
from dbml.protocol.schema import MAX_TEXT_CHARS

TOPICS = st.from_regex(r"(/[A-Za-z0-9_.~-]{1,12}){1,4}", fullmatch=True)
HOSTS = st.from_regex(r"[A-Za-z0-9_.~-]{1,24}", fullmatch=True)
FINITE = st.floats(allow_nan=False, allow_infinity=False)
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=12), inner, max_size=6)
    ),
    max_leaves=30,
)
"""Any JSON document (NaN and infinities too, as Python's json writes them)."""
LONGEST_TOPIC = "/" + "t" * (MAX_NAME_CHARS - 1)


# -- the estimator's state ---------------------------------------------------------------------


def test_a_state_travels_as_json_and_reads_as_a_line() -> None:
    estimate = Estimate(5.0, 4.5, Phase.DECREASE, 3.2049, 0.0404, 0.1, 2)
    state = EstimatorState.of(estimate, decided_at_s=1_700_000_002.1234)
    assert state.text == "decrease: received 3.20 Mbit/s, queueing 40 ms, lost 2 @1700000002.123"
    back = EstimatorState.decode(state.encode())
    assert back.phase is Phase.DECREASE
    assert back.decided_at_s == 1_700_000_002.123  # to the millisecond, as it was shown
    assert back.text == state.text
    hold = EstimatorState.of(Estimate(5.0, 4.5, Phase.HOLD, 3.2, 0.0, 0.0, 0))
    assert hold.text == "hold: received 3.20 Mbit/s, queueing 0 ms, lost 0"
    assert EstimatorState.decode(hold.encode()) == hold


def test_a_state_says_why() -> None:
    cut = Estimate(5.0, 4.5, Phase.DECREASE, 3.2, 0.2, 0.5, 0, reason="queue 200 ms rising")
    state = EstimatorState.of(cut)
    assert state.text.endswith("lost 0 (queue 200 ms rising)")
    assert EstimatorState.decode(state.encode()).reason == "queue 200 ms rising"
    long = Estimate(5.0, 4.5, Phase.HOLD, 3.2, 0.0, 0.0, 0, reason="x" * (MAX_REASON_CHARS + 9))
    assert len(EstimatorState.of(long).reason) == MAX_REASON_CHARS  # cut to what travels


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("hold: received 3.20 Mbit/s", "estimator state='hold: received 3.20 Mbit/s' is not JSON"),
        ("[1]", r"estimator state=\[1\] is not a JSON object"),
        ('{"phase": "up"}', "estimator state: phase='up' is not one of increase, hold"),
        ('{"phase": "hold", "lost": -1}', "estimator state: lost=-1 is not a count"),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": "fast"}',
            "estimator state: received_mbit='fast' is not a number",
        ),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": 1, "queue_delay_s": NaN}',
            "estimator state: queue_delay_s=nan is not finite",
        ),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": 1, "queue_delay_s": 0, '
            '"decided_at_s": -2}',
            "estimator state: decided_at_s=-2 must be >= 0",
        ),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": 1, "queue_delay_s": 0, '
            '"reason": "a\\nb"}',
            "estimator state: reason='a\\\\nb' is not a line of at most 120 printable",
        ),
        (
            '{"phase": "hold", "lost": 0, "received_mbit": 1, "queue_delay_s": 0, "reason": 7}',
            "estimator state: reason=7 is not a line",
        ),
    ],
)
def test_a_malformed_state_names_the_field_and_the_value(text: str, match: str) -> None:
    with pytest.raises(SpecError, match=match):
        EstimatorState.decode(text)


def test_a_state_longer_than_a_status_text_is_refused_unparsed() -> None:
    text = json.dumps({"phase": "hold", "pad": "x" * MAX_TEXT_CHARS})
    with pytest.raises(SpecError, match=f"is longer than {MAX_TEXT_CHARS} characters"):
        EstimatorState.decode(text)


@given(
    phase=st.sampled_from(list(Phase)),
    received=st.floats(0, 1e6),
    queue=st.floats(0, 1e3),
    lost=st.integers(0, SEQ_MAX),
    decided=st.none() | st.floats(0, 4e9),
)
def test_a_state_round_trips_as_it_reads(
    phase: Phase, received: float, queue: float, lost: int, decided: float | None
) -> None:
    state = EstimatorState(
        phase=phase, received_mbit=received, queue_delay_s=queue, lost=lost, decided_at_s=decided
    )
    back = EstimatorState.decode(state.encode())
    assert back.as_json() == state.as_json()  # rounded for reading, as it travels
    assert back.text == EstimatorState.from_json(state.as_json()).text


@given(document=JSON_VALUES)
def test_any_json_is_a_state_or_a_spec_error(document: object) -> None:
    with contextlib.suppress(SpecError):
        EstimatorState.decode(json.dumps(document))


# -- the link beacon ---------------------------------------------------------------------------

BAD_BEACONS = [
    b'{"up": true, "release_s": {"/r1/camera": NaN}}',
    b'{"up": true, "release_s": {"/r1/camera": Infinity}}',
    b'{"up": true, "release_s": {"/r1/camera": 1e400}}',
    b'{"up": true, "release_s": {"/r1/camera": -1}}',
    b'{"up": true, "release_s": {"/r1/camera": 3e9}}',
    b'{"up": true, "release_s": {"/r1/camera": 1' + b"0" * 400 + b"}}",
    b'{"up": true, "release_s": {"/r1/camera": true}}',
    b'{"up": true, "release_s": {"/r1/camera": "0"}}',
    b'{"up": true, "release_s": []}',
    b'{"up": "false"}',
    b'{"up": 0}',
    b'{"up": true, "sent_s": NaN}',
    b'{"up": true, "sent_s": -Infinity}',
    b'{"up": true, "heard": "/r1/camera"}',
    b'{"up": true, "heard": [1]}',
    b'{"up": true, "heard": {"/r1/camera": true}}',
    b'{"up": true, "heard": ["/r1/camera"]}',
    b'{"up": true, "heard": {"/r1/camera": [1]}}',
    b'{"up": true, "heard": {"/r1/camera": [1, 2, 3]}}',
    b'{"up": true, "heard": {"/r1/camera": [-1, 0]}}',
    b'{"up": true, "heard": {"/r1/camera": [1, -1]}}',
    b'{"up": true, "heard": {"/r1/camera": [1.5, 0]}}',
    b'{"up": true, "heard": {"/r1/camera": [true, 0]}}',
    b'{"up": true, "heard": {"/r1/camera": [1, "2"]}}',
    b'{"up": true, "heard": {"/r1/camera": [1, ' + str(HEARD_RECENT_MAX + 1).encode() + b"]}}",
    b'{"up": true, "heard": {'
    + b",".join(b'"/a%d": [0, 0]' % k for k in range(HEARD_MAX + 1))
    + b"}}",
    b"[" * 100_000 + b"]" * 100_000,
    b"[true]",
    b"\xff\xfe",
    b"{not json",
]
"""Malformed beacons (the publisher's outage tests send them too)."""


@pytest.mark.parametrize("data", BAD_BEACONS, ids=lambda d: d[:40].decode("latin-1"))
def test_a_malformed_beacon_is_refused(data: bytes) -> None:
    with pytest.raises(TransportError, match="malformed link beacon"):
        LinkBeacon.decode(data)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b'{"sent_s": 1}', "up is missing"),
        (b'{"up": "false"}', "up='false' is not a boolean"),
        (b'{"up": true, "release_s": {"/r1/camera": -1}}', r"release_s\['/r1/camera'\]=-1 must be"),
        (
            b'{"up": true, "release_s": {"r1 camera": 0}}',
            "release_s key='r1 camera' is not a topic",
        ),
        (b'{"up": true, "heard": {"/r1/camera": [1, -1]}}', r"heard\['/r1/camera'\]=\[1, -1\]"),
        (b'{"up": true, "heard": {"nope": [1, 1]}}', "heard key='nope' is not a topic"),
        (b'{"up": true, "sent_s": NaN}', "sent_s=nan is not finite"),
        (
            b'{"up": true, "release_s": {"/' + b"t" * MAX_NAME_CHARS + b'": 0}}',
            f"is not a name of at most {MAX_NAME_CHARS}",
        ),
        (
            b'{"up": true, "release_s": {'
            + b",".join(b'"/a%d": 0' % k for k in range(RELEASE_MAX_CHANNELS + 1))
            + b"}}",
            f"release_s is not an object of at most {RELEASE_MAX_CHANNELS} entries",
        ),
        (b" " * (MAX_BEACON_BYTES + 1), f"{MAX_BEACON_BYTES + 1} bytes, more than"),
    ],
)
def test_a_malformed_beacon_names_the_field_and_the_value(data: bytes, match: str) -> None:
    with pytest.raises(TransportError, match=match):
        LinkBeacon.decode(data)


def test_an_encoded_beacon_round_trips() -> None:
    beacon = LinkBeacon(up=False, release_s={"/r1/camera": 0.5}, sent_s=12.5)
    assert LinkBeacon.decode(beacon.encode()) == beacon
    heard = LinkBeacon(
        up=True, sent_s=1.0, heard={"/r1/camera": Heard(12, 3), "/r2/camera": Heard(0, 0)}
    )
    assert LinkBeacon.decode(heard.encode()) == heard
    assert json.loads(beacon.encode())["up"] is False


HEARDS = st.builds(Heard, st.integers(0, SEQ_MAX), st.integers(0, HEARD_RECENT_MAX))


@given(
    up=st.booleans(),
    release=st.dictionaries(TOPICS, st.floats(0.0, RELEASE_MAX_S), max_size=8),
    sent=FINITE,
    heard=st.none() | st.dictionaries(TOPICS, HEARDS, max_size=8),
)
def test_every_beacon_within_its_bounds_round_trips(
    up: bool, release: dict[str, float], sent: float, heard: dict[str, Heard] | None
) -> None:
    beacon = LinkBeacon(up, release, sent, heard)
    assert LinkBeacon.decode(beacon.encode()) == beacon


def test_the_largest_beacon_fits_its_byte_bound() -> None:
    """Every channel it may name, each of the longest name: what is sent is what is taken."""
    names = [f"{LONGEST_TOPIC[: -len(str(k))]}{k}" for k in range(HEARD_MAX)]
    beacon = LinkBeacon(
        up=True,
        release_s={n: math.nextafter(RELEASE_MAX_S, 0.0) for n in names[:RELEASE_MAX_CHANNELS]},
        sent_s=-1.2345678901234567e308,
        heard={n: Heard(SEQ_MAX, HEARD_RECENT_MAX) for n in names},
    )
    data = beacon.encode()
    assert len(data) <= MAX_BEACON_BYTES
    assert LinkBeacon.decode(data) == beacon


@settings(max_examples=200)
@given(data=st.binary(max_size=200) | JSON_VALUES.map(lambda v: json.dumps(v).encode()))
def test_anything_is_a_beacon_or_a_transport_error(data: bytes) -> None:
    with contextlib.suppress(TransportError):
        LinkBeacon.decode(data)


# -- the reception report ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b'{"host": "op"}', "now_s is missing"),
        (b'{"now_s": 1, "frames": []}', "host is missing"),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", 1e400, 0, 0.0, 10]]}', r"seq=inf"),
        (
            b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 0, 0.0, Infinity]]}',
            "size_bytes=inf",
        ),
        (
            b'{"host": "op", "now_s": 1, "frames": [["/cam", -1, 0, 0.0, 10]]}',
            r"frames\[0\]\.seq=-1",
        ),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", 1.5, 0, 0.0, 10]]}', r"\.seq=1\.5"),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", "1", 0, 0.0, 10]]}', r"\.seq='1'"),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", true, 0, 0.0, 10]]}', r"\.seq=True"),
        (
            b'{"host": "op", "now_s": 1, "frames": [["/cam", 18446744073709551616, 0, 0.0, 10]]}',
            r"\.seq=18446744073709551616 is not an integer in \[0, 18446744073709551615\]",
        ),
        (
            b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 9223372036854775808, 0.0, 10]]}',
            r"frames\[0\]\.sent_ns=9223372036854775808",
        ),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 0, NaN, 10]]}', r"arrival_s=nan"),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 0, "0", 10]]}', r"arrival_s='0'"),
        (
            b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 0, 0.0, 1' + b"0" * 400 + b"]]}",
            r"frames\[0\]\.size_bytes=1000",
        ),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 0, 0.0, 2000000000]]}', "size_bytes"),
        (b'{"host": "op", "now_s": 1, "frames": [["/cam", 1, 0, 0.0]]}', r"frames\[0\]=\["),
        (b'{"host": "op", "now_s": 1, "frames": [["cam", 1, 0, 0.0, 10]]}', "topic='cam' is not"),
        (b'{"host": "op", "now_s": 1, "frames": [[7, 1, 0, 0.0, 10]]}', r"\.topic=7 is not a name"),
        (b'{"host": "o p", "now_s": 1, "frames": []}', "host='o p' is not a host name"),
        (b'{"host": 1, "now_s": 1, "frames": []}', "host=1 is not a name"),
        (b'{"host": "op", "now_s": NaN, "frames": []}', "now_s=nan is not finite"),
        (b'{"host": "op", "now_s": "1", "frames": []}', "now_s='1' is not a number"),
        (b'{"host": "op", "now_s": 1, "frames": {}}', "frames is not a list"),
        (b"[1, 2]", "the report is not an object"),
        (b"\xff\xfe", "malformed reception report"),
        (b"[" * 100_000 + b"]" * 100_000, "malformed reception report"),
        (b" " * (MAX_REPORT_BYTES + 1), f"{MAX_REPORT_BYTES + 1} bytes, more than"),
    ],
)
def test_a_malformed_report_names_the_field_and_the_value(data: bytes, match: str) -> None:
    with pytest.raises(TransportError, match="malformed reception report") as raised:
        ReceptionReport.decode(data)
    assert raised.match(match)


def test_a_report_of_more_frames_than_a_flush_holds_is_refused() -> None:
    frame = ReceivedFrame("/cam", 1, 0, 0.0, 10)
    report = ReceptionReport("op", 1.0, (frame,) * (MAX_REPORT_FRAMES + 1))
    with pytest.raises(
        TransportError, match=f"frames is not a list of at most {MAX_REPORT_FRAMES}"
    ):
        ReceptionReport.decode(report.encode())


FRAMES = st.builds(
    ReceivedFrame,
    TOPICS,
    st.integers(0, SEQ_MAX),
    st.integers(-(2**63), 2**63 - 1),
    FINITE,
    st.integers(0, 10**9),
)


@given(host=HOSTS, now=FINITE, frames=st.lists(FRAMES, max_size=8))
def test_every_report_within_its_bounds_round_trips(
    host: str, now: float, frames: list[ReceivedFrame]
) -> None:
    report = ReceptionReport(host, now, tuple(frames))
    assert ReceptionReport.decode(report.encode()) == report


def test_the_largest_report_fits_its_byte_bound() -> None:
    frame = ReceivedFrame(LONGEST_TOPIC, SEQ_MAX, -(2**63), -1.2345678901234567e-300, 10**9)
    report = ReceptionReport("h" * MAX_NAME_CHARS, 1.0, (frame,) * MAX_REPORT_FRAMES)
    data = report.encode()
    assert len(data) <= MAX_REPORT_BYTES
    assert ReceptionReport.decode(data) == report


@settings(max_examples=200)
@given(data=st.binary(max_size=200) | JSON_VALUES.map(lambda v: json.dumps(v).encode()))
def test_anything_is_a_report_or_a_transport_error(data: bytes) -> None:
    with contextlib.suppress(TransportError):
        ReceptionReport.decode(data)


# -- the round report ------------------------------------------------------------------------------

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


def round_document(**changes: Any) -> bytes:
    return json.dumps(REPORT.as_json() | changes).encode()


def round_channel(**changes: Any) -> bytes:
    return round_document(channels=[R1.as_json() | changes])


def test_a_round_report_travels_whole() -> None:
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
        (round_document(round=-1), r"round=-1 is not a count"),
        (round_document(round=True), r"round=True is not a count"),
        (round_document(status="great"), r"status='great' is not a status"),
        (round_document(strategy="magic"), r"strategy='magic' is not a strategy"),
        (round_document(status_message=None), r"status_message=None is not text"),
        (round_document(budget_mbit=-3), r"budget_mbit=-3 must be"),
        (round_document(budget_mbit=math.inf), r"budget_mbit=inf is not finite"),
        (round_document(channels={}), r"channels={} is not a list"),
        (round_channel(topic="r1 camera"), r"round channel topic='r1 camera' is not a topic"),
        (round_channel(topic="/" + "t" * MAX_NAME_CHARS), r"is not a name of at most 1024"),
        (round_channel(min_hz=16.0, max_hz=1.0), r"min_hz=16.0 is above max_hz=1.0"),
        (
            round_document(channels=[R1.as_json(), R1.as_json()]),
            r"channels name a topic twice",
        ),
        (round_channel(managed="yes"), r"/r1/camera: managed='yes' is not a boolean"),
        (round_channel(priority=2), r"/r1/camera: priority=2 must be within \[0, 1\]"),
        (round_channel(rate_hz=math.nan), r"/r1/camera: rate_hz=nan is not finite"),
        (round_channel(size_bytes=0), r"/r1/camera: size_bytes=0 must be"),
        (round_channel(share="a lot"), r"/r1/camera: share='a lot' is not a number"),
        (json.dumps({"round": 1}).encode(), r"status=None is not a status"),
    ],
)
def test_a_malformed_round_report_is_refused_naming_what(data: bytes, message: str) -> None:
    with pytest.raises(TransportError, match=message):
        RoundReport.decode(data)


def test_a_round_report_too_large_or_too_long_is_refused_unread() -> None:
    with pytest.raises(TransportError, match=f"more than {MAX_ROUND_BYTES}"):
        RoundReport.decode(b" " * (MAX_ROUND_BYTES + 1))
    many = [R2.as_json()] * (MAX_REPORTED_CHANNELS + 1)
    with pytest.raises(TransportError, match=f"at most {MAX_REPORTED_CHANNELS}"):
        RoundReport.decode(round_document(channels=many))


ROUND_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=4,
)


@given(
    st.binary(max_size=64)
    | st.dictionaries(st.sampled_from(sorted(REPORT.as_json())), ROUND_JSON).map(
        lambda d: json.dumps(REPORT.as_json() | d).encode()
    )
    | st.dictionaries(st.sampled_from(sorted(R1.as_json())), ROUND_JSON).map(
        lambda d: json.dumps(REPORT.as_json() | {"channels": [R1.as_json() | d]}).encode()
    )
)
def test_anything_is_a_round_report_or_a_transport_error(data: bytes) -> None:
    with contextlib.suppress(TransportError):
        RoundReport.decode(data)
