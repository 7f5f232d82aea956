"""A ladder and an encoding as parameters carry them: round trips, and bad values named."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.core.errors import SpecError
from dbml.core.ladder import MAX_RUNGS, Rung
from dbml.protocol import names
from dbml.protocol.ladders import (
    decode_rungs,
    encode_rungs,
    encoding_label,
    parse_encoding,
    parse_rung_label,
)
from dbml.protocol.schema import ParamError, check_param

rungs = st.builds(
    Rung,
    st.floats(1, 1e6),
    st.floats(0, 1),
    st.sampled_from([1.0, 0.5, 0.25]),
    st.one_of(st.none(), st.integers(1, 100)),
)


@given(st.lists(rungs, min_size=1, max_size=MAX_RUNGS))
def test_a_ladder_survives_its_text(ladder: list[Rung]) -> None:
    back = decode_rungs(encode_rungs(tuple(ladder)))
    assert len(back) == len(ladder)
    for got, sent in zip(back, ladder, strict=True):
        assert got.size_bytes == pytest.approx(sent.size_bytes, abs=0.5)
        assert got.quality == pytest.approx(sent.quality, abs=1e-4)
        assert (got.scale, got.jpeg_quality) == (sent.scale, sent.jpeg_quality)


@given(st.sampled_from([1.0, 0.5, 0.25, 0.75]), st.one_of(st.none(), st.integers(1, 100)))
def test_an_encoding_survives_its_label(scale: float, quality: int | None) -> None:
    assert parse_encoding(encoding_label(scale, quality)) == (scale, quality)
    assert parse_rung_label(encoding_label(scale, quality)) == ((scale, quality), None)


@given(st.sampled_from([1.0, 0.5, 0.25]), st.integers(1, 100), st.floats(0.5, 1e9))
def test_the_bytes_a_rung_was_counted_at_survive_its_label(
    scale: float, quality: int, size_bytes: float
) -> None:
    label = encoding_label(scale, quality, size_bytes=size_bytes)
    assert parse_rung_label(label) == ((scale, quality), max(round(size_bytes), 1))
    assert parse_encoding(label) == (scale, quality)


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("[[0, 0.9, 1.0, 50]]", "size_bytes=0"),
        ("[[1000, 1.5, 1.0, 50]]", "quality=1.5"),
        ("[[1000, 0.9, 1.0, 500]]", "jpeg_quality=500"),
        ("[[1000, 0.9, 0, 50]]", "scale=0"),
        ("[[1000, 0.9, 1.0]]", "[1000, 0.9, 1.0]"),
        ("[]", "[]"),
        ("{oops", "{oops"),
        (json.dumps([[1000, 0.9, 1.0, 50]] * (MAX_RUNGS + 1)), f"more than {MAX_RUNGS}"),
    ],
)
def test_a_bad_ladder_is_refused_naming_its_value(text: str, named: str) -> None:
    with pytest.raises(ParamError) as caught:
        check_param(names.ladder("/r1/camera"), text)
    message = str(caught.value)
    assert "/r1/camera/dbm/ladder" in message
    assert named in message
    assert "\n" not in message


_BAD_LABELS = ["x2 q50", "x1 q0", "x1 q101", "1 q50", "x0.5", "", "x0 raw"]
_BAD_BYTES = ["x1 q50 0B", "x1 q50 12", "x1 q50 -3B", "x1 q50 9999999999B", "x1 q50 1.5B"]


@pytest.mark.parametrize("label", [*_BAD_LABELS, *_BAD_BYTES])
def test_a_bad_encoding_is_refused_naming_it(label: str) -> None:
    with pytest.raises(SpecError, match="encoding="):
        parse_encoding(label)
    with pytest.raises(ParamError, match="/r1/camera/dbm/encoding/current_value"):
        check_param(names.encoding("/r1/camera"), label)


def test_a_preference_is_one_of_three() -> None:
    assert check_param(names.preference("/r1/camera"), "keep_rate") == "keep_rate"
    with pytest.raises(ParamError, match="fastest"):
        check_param(names.preference("/r1/camera"), "fastest")
    with pytest.raises(ParamError, match=r"quality/min=1\.2"):
        check_param(names.min_quality("/r1/camera"), 1.2)
