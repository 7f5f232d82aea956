"""Recorded link traces: OpenNetLab gym's JSON and ``SECONDS:MBIT`` text, checked entry by entry.

The gym documents below are written here in the gym's format (the repository has no licence:
none of its files is copied); their values mirror its traces' kinds (200-ms steps, a zero
capacity, an outlier of 8,039,999 kbit/s).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.core.errors import ConfigError
from dbml.scenarios.traces import (
    MAX_TRACE_ENTRIES,
    MAX_TRACE_MBIT,
    LinkTrace,
    load_trace,
    parse_gym_trace,
    parse_plain_trace,
)


def gym(*steps: object) -> str:
    return json.dumps({"type": "video", "uplink": {"trace_pattern": list(steps)}})


def test_a_gym_trace_is_kbit_per_s_for_ms_one_after_another() -> None:
    trace = parse_gym_trace(
        gym(
            {"capacity": 0, "duration": 200},
            {"capacity": 1720, "duration": 200},
            {"capacity": 1720, "duration": 199},
            {"capacity": 3040.5, "duration": 400},
        ),
        name="4G",
    )
    assert [e.at_s for e in trace.entries] == pytest.approx([0.0, 0.2, 0.4, 0.599])
    assert [e.mbit for e in trace.entries] == [0.0, 1.72, 1.72, 3.0405]
    assert trace.duration_s == pytest.approx(0.999)
    # The schedule keeps each change once: down, then 1.72 from 0.2 s, then 3.0405.
    assert [t for t, _ in trace.schedule] == pytest.approx([0.0, 0.2, 0.599])
    assert [mbit for _, mbit in trace.schedule] == [0.0, 1.72, 3.0405]
    assert trace.first_up_mbit == 1.72
    assert trace.mbit_at(0.1) == 0.0
    assert trace.mbit_at(0.5) == 1.72
    assert trace.mbit_at(5.0) == 3.0405  # past the end: the last rate
    # 0.2 s down, 0.399 s at 1.72, 0.4 s at 3.0405
    assert trace.megabits(0.0, 0.999) == pytest.approx(0.399 * 1.72 + 0.4 * 3.0405)
    assert trace.megabits(0.3, 0.5) == pytest.approx(0.2 * 1.72)
    assert not trace.impaired


def test_the_usual_rate_is_the_median_over_the_time_the_link_is_up() -> None:
    # 0.2 s down, 0.2 s at 9 (a burst), 0.3 s at 0.01 (a fade), then 2.5: half the up time is
    # reached within the 2.5-Mbit/s stretch.
    trace = parse_plain_trace("0:0, 0.2:9, 0.4:0.01, 0.7:2.5, 1.6:2.5", name="radio")
    assert trace.median_up_mbit == 2.5
    # A long fade is the usual rate when it is most of the up time.
    faded = parse_gym_trace(
        gym(
            {"capacity": 9000, "duration": 100},
            {"capacity": 10, "duration": 4900},
            {"capacity": 9000, "duration": 100},
        ),
        name="faded",
    )
    assert faded.median_up_mbit == 0.01  # by count of entries it would be 9
    never = parse_gym_trace(gym({"capacity": 0, "duration": 200}), name="down")
    assert never.median_up_mbit is None


def test_an_outlier_is_clamped_and_counted() -> None:
    trace = parse_gym_trace(
        gym({"capacity": 2760, "duration": 200}, {"capacity": 8039999, "duration": 200}),
        name="4G_3mbps",
    )
    assert trace.entries[1].mbit == MAX_TRACE_MBIT
    assert trace.clamped == 1


def test_a_capacity_below_tc_resolution_takes_the_link_down() -> None:
    trace = parse_gym_trace(
        gym({"capacity": 0.5, "duration": 200}, {"capacity": 2.4, "duration": 200}), name="x"
    )
    assert [e.mbit for e in trace.entries] == [0.0, 0.0024]


def test_loss_and_rtt_are_kept_as_impairments() -> None:
    trace = parse_gym_trace(
        gym({"capacity": 1000, "duration": 500, "loss": 0.2, "rtt": 400, "jitter": 10}),
        name="loss",
    )
    entry = trace.entries[0]
    assert (entry.loss, entry.delay_ms, entry.jitter_ms) == (0.2, 200.0, 10.0)
    assert trace.impaired


@pytest.mark.parametrize(
    ("document", "names"),
    [
        ("not json", "not JSON"),
        (json.dumps({"downlink": {}}), "uplink is missing"),
        (json.dumps({"uplink": {}}), "uplink.trace_pattern is missing"),
        (json.dumps({"uplink": {"trace_pattern": []}}), "uplink.trace_pattern=[]"),
        (gym({"capacity": -1, "duration": 200}), "uplink.trace_pattern[0].capacity=-1"),
        (gym({"capacity": "fast", "duration": 200}), "capacity='fast'"),
        (gym({"capacity": 1, "duration": 0}), "uplink.trace_pattern[0].duration=0 must be > 0"),
        (gym({"capacity": 1, "duration": True}), "duration=True"),
        (gym({"capacity": 1}), "uplink.trace_pattern[0].duration is missing"),
        (gym({"capacity": 1, "duration": 9, "loss": 1.5}), "loss=1.5 must be >= 0 and <= 1"),
        (gym({"capacity": 1, "duration": 1e12}), "lasts past"),
        (gym(5), "uplink.trace_pattern[0]=5 must be an object"),
        (gym({"capacity": None, "duration": 200}), "capacity=None must be >= 0"),
        (
            '{"uplink": {"trace_pattern": [{"capacity": 1' + "0" * 400 + ', "duration": 1}]}}',
            "capacity=1000",
        ),
        ('{"uplink": {"trace_pattern": [{"capacity": 1' + "0" * 5000 + "}]}}", "not JSON"),
    ],
)
def test_a_bad_gym_trace_names_the_entry_and_the_value(document: str, names: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_gym_trace(document, name="t")
    assert names in str(err.value)
    assert "\n" not in str(err.value)


def test_too_many_entries_names_the_bound() -> None:
    steps = [{"capacity": 1, "duration": 1}] * (MAX_TRACE_ENTRIES + 1)
    with pytest.raises(ConfigError, match=f"more than {MAX_TRACE_ENTRIES:,}"):
        parse_gym_trace(json.dumps({"uplink": {"trace_pattern": steps}}), name="big")


def test_a_plain_trace_is_seconds_and_mbit() -> None:
    trace = parse_plain_trace("# RFC 8867 5.1, scaled\n0:4.4\n40:11, 60:2.6\n80:4.4\n", name="r")
    assert trace.schedule == ((0.0, 4.4), (40.0, 11.0), (60.0, 2.6), (80.0, 4.4))
    assert trace.duration_s == 100.0  # the last rate lasts as long as the one before
    assert trace.megabits(0, 100) == pytest.approx(40 * 4.4 + 20 * 11 + 20 * 2.6 + 20 * 4.4)


@pytest.mark.parametrize(
    ("text", "names"),
    [
        ("", "no SECONDS:MBIT entry"),
        ("0:11\n20", "'20' must be SECONDS:MBIT"),
        ("0:11,20:x", "'20:x' must be SECONDS:MBIT"),
        ("0:11,20:-1", "rate '-1' must be a number >= 0"),
        ("0:11,20:5,10:3", "times must increase ('10:3')"),
        ("5:11", "the first entry must be at 0 s"),
        ("0:nan", "rate 'nan'"),
    ],
)
def test_a_bad_plain_trace_names_the_entry(text: str, names: str) -> None:
    with pytest.raises(ConfigError, match="trace 'p'") as err:
        parse_plain_trace(text, name="p")
    assert names in str(err.value)


def test_a_file_is_read_by_its_content(tmp_path: Path) -> None:
    (tmp_path / "lte.json").write_text(gym({"capacity": 500, "duration": 200}))
    (tmp_path / "steps.txt").write_text("0:11\n20:5\n")
    assert load_trace(tmp_path / "lte.json").entries[0].mbit == 0.5
    assert load_trace(tmp_path / "lte.json").name == "lte"
    assert load_trace(tmp_path / "steps.txt").schedule == ((0.0, 11.0), (20.0, 5.0))
    with pytest.raises(ConfigError, match=r"missing\.json"):
        load_trace(tmp_path / "missing.json")
    (tmp_path / "bin").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_trace(tmp_path / "bin")
    (tmp_path / "bom.json").write_bytes(
        b"\xef\xbb\xbf" + gym({"capacity": 800, "duration": 9}).encode()
    )
    assert load_trace(tmp_path / "bom.json").entries[0].mbit == 0.8  # read as JSON, not as text


@given(
    st.lists(
        st.tuples(
            st.floats(min_value=1_000, max_value=5_000), st.floats(min_value=1, max_value=1_000)
        ),
        min_size=1,
        max_size=40,
    ),
    st.floats(min_value=0, max_value=50),
    st.floats(min_value=0, max_value=50),
)
def test_the_integral_adds_up_over_any_split(
    steps: list[tuple[float, float]], a: float, b: float
) -> None:
    trace: LinkTrace = parse_gym_trace(
        gym(*({"capacity": kbps, "duration": ms} for kbps, ms in steps)), name="h"
    )
    end = trace.duration_s
    lo, hi = sorted((min(a, end), min(b, end)))
    whole = trace.megabits(0, end)
    assert trace.megabits(0, lo) + trace.megabits(lo, hi) + trace.megabits(hi, end) == (
        pytest.approx(whole, rel=1e-9, abs=1e-9)
    )
    assert trace.megabits(0, trace.duration_s) == pytest.approx(
        sum(kbps / 1e3 * (ms / 1e3) for kbps, ms in steps), rel=1e-9
    )


def test_a_recorded_outlier_is_clamped_to_the_largest_capacity_that_is_not() -> None:
    steps = [(2760, 200), (3040, 200), (80100, 200), (2200, 200), (8039999, 200), (0, 200)]
    trace = parse_gym_trace(
        gym(*({"capacity": kbps, "duration": ms} for kbps, ms in steps)), name="4G"
    )
    # median of the capacities above 0: 3.04 Mbit/s; 80.1 and 8,039.999 are over 10 times it
    assert [e.mbit for e in trace.entries] == [2.76, 3.04, 3.04, 2.2, 3.04, 0.0]
    assert trace.clamped == 2
    # A plain trace is taken as written: a jump of 50 times is the user's own.
    assert parse_plain_trace("0:1,1:1,2:1,3:50", name="p").entries[-1].mbit == 50.0


def test_a_file_past_the_bound_is_refused_without_reading_it_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dbml.scenarios import traces

    monkeypatch.setattr(traces, "MAX_TRACE_BYTES", 64)
    (tmp_path / "long.txt").write_text("0:11\n" * 20)  # 100 bytes
    with pytest.raises(ConfigError, match="more than 64 bytes"):
        load_trace(tmp_path / "long.txt")
