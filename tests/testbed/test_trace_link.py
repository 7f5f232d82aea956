"""A recorded trace on the testbed's link: the options, the changes applied, the analysis.

No namespace is built here: ``_change_link`` drives a stand-in network that records its calls
(the real ``tc`` changes run in tests/testbed/test_teleop.py and bench/estimator_traces.py).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from dbml.estimator.designs import DEFAULT_DESIGN, Design
from dbml.experiment.analysis import Arrival, analyse
from dbml.testbed import TestbedError
from dbml.testbed.netns import OPERATOR
from dbml.testbed.options import TestbedOptions
from dbml.testbed.result import LinkTiming
from dbml.testbed.runner import _built_mbit, _change_link, _network


@pytest.fixture
def testbed_alone() -> None:
    """No namespace is built here: not the testbed's lock (conftest's fixture of that name)."""


def _gym(path: Path, *steps: tuple[float, float]) -> Path:
    pattern = [{"capacity": kbps, "duration": ms} for kbps, ms in steps]
    path.write_text(json.dumps({"uplink": {"trace_pattern": pattern}}))
    return path


def test_a_trace_becomes_the_links_schedule_and_may_start_down(tmp_path: Path) -> None:
    trace = _gym(tmp_path / "lte.json", (0, 200), (2500, 200), (2500, 200), (800, 400))
    options = TestbedOptions.from_flags(link_trace=str(trace), estimate=True)
    assert [t for t, _ in options.link_schedule] == pytest.approx([0.0, 0.2, 0.6])
    assert [mbit for _, mbit in options.link_schedule] == [0.0, 2.5, 0.8]
    assert options.link_trace is not None
    assert options.link_trace.name == "lte"
    assert not options.steady
    # Built at its first capacity above 0: the roles meet before the trace starts.
    assert _built_mbit(options) == 2.5
    assert options.estimator_design is DEFAULT_DESIGN


def test_a_traced_link_keeps_its_usual_rates_queue_through_a_fade(tmp_path: Path) -> None:
    # 0.8 s at 10 Mbit/s, a 0.2-s fade, 0.4 s at 2: the usual rate is 10.
    trace = _gym(tmp_path / "5g.json", (10_000, 800), (10, 200), (2_000, 400))
    options = TestbedOptions.from_flags(link_trace=str(trace), estimate=True)
    # tbf's own bound at 10 Mbit/s: 200 ms of it (250,000 bytes) and its 4,000-byte burst.
    assert options.link_queue_bytes == 254_000
    assert _network(options).queue_bytes == 254_000
    # A schedule's link is re-shaped at each rate: the shaper's own queue.
    scheduled = TestbedOptions.from_flags(link_schedule="0:10,1:0.01,2:2")
    assert scheduled.link_queue_bytes is None
    assert _network(scheduled).queue_bytes is None


def test_trace_flags_are_checked(tmp_path: Path) -> None:
    trace = _gym(tmp_path / "t.json", (1000, 200))
    with pytest.raises(TestbedError, match="--link-trace and --link-schedule"):
        TestbedOptions.from_flags(link_trace=str(trace), link_schedule="0:11")
    with pytest.raises(TestbedError, match=r"--link-trace='nope\.json'.*nope\.json"):
        TestbedOptions.from_flags(link_trace="nope.json")
    down = _gym(tmp_path / "down.json", (0, 200), (0.2, 200))
    with pytest.raises(TestbedError, match="the link is never up"):
        TestbedOptions.from_flags(link_trace=str(down))
    lossy = tmp_path / "loss.json"
    lossy.write_text(
        json.dumps({"uplink": {"trace_pattern": [{"capacity": 1, "duration": 9, "loss": 0.1}]}})
    )
    with pytest.raises(TestbedError, match="netem"):
        TestbedOptions.from_flags(link_trace=str(lossy))
    with pytest.raises(TestbedError, match="--estimator-design='bbr' is not one of"):
        TestbedOptions.from_flags(estimator_design="bbr")
    chosen = TestbedOptions.from_flags(estimate=True, estimator_design="delivery-rate")
    assert chosen.estimator_design is Design.DELIVERY_RATE


class _Recorder:
    """Stands in for ``Network``: each change with the time it was asked."""

    def __init__(self) -> None:
        self.calls: list[tuple[float, str, float]] = []

    def set_link_rate(self, mbit: float, *, host: str = OPERATOR) -> None:
        self.calls.append((time.time(), host, mbit))

    def take_link_down(self, *, host: str = OPERATOR) -> None:
        self.calls.append((time.time(), host, 0.0))


def test_every_change_is_applied_on_time_and_timed(tmp_path: Path) -> None:
    trace = _gym(tmp_path / "t.json", (0, 100), (2000, 100), (3000, 100), (1000, 100))
    options = TestbedOptions.from_flags(link_trace=str(trace))
    network = _Recorder()
    timing: list[tuple[float, float]] = []
    t0 = time.time() + 0.05
    _change_link(network, options, t0, threading.Event(), timing)  # type: ignore[arg-type]
    # The trace starts down: that change is applied at 0 s too, then each one after.
    assert [(host, mbit) for _, host, mbit in network.calls] == [
        (OPERATOR, 0.0),
        (OPERATOR, 2.0),
        (OPERATOR, 3.0),
        (OPERATOR, 1.0),
    ]
    for (at, _, _), due in zip(network.calls, (0.0, 0.1, 0.2, 0.3), strict=True):
        assert at >= t0 + due - 1e-3
    assert len(timing) == 4
    summary = LinkTiming.of(timing)
    assert summary is not None
    assert summary.changes == 4
    assert summary.call_ms_max == pytest.approx(max(call for _, call in timing) * 1e3)
    assert summary.late_ms_max == pytest.approx(max(0.0, *(lag for lag, _ in timing)) * 1e3)
    assert LinkTiming.of([]) is None


def test_a_stop_ends_the_changes_at_once(tmp_path: Path) -> None:
    trace = _gym(tmp_path / "t.json", (1000, 100), (2000, 60_000))
    options = TestbedOptions.from_flags(link_trace=str(trace))
    stop = threading.Event()
    stop.set()
    network = _Recorder()
    started = time.monotonic()
    _change_link(network, options, time.time() + 30, stop, [])  # type: ignore[arg-type]
    assert network.calls == []
    assert time.monotonic() - started < 1.0


def test_a_traced_run_judges_no_change_alone() -> None:
    schedule = tuple((k * 0.2, 1.0 + (k % 5)) for k in range(100))
    frames = [
        Arrival(
            robot=0, seq=k, sent_s=k * 0.1, arrival_s=k * 0.1 + 0.02, size_bytes=1000, rate_hz=10.0
        )
        for k in range(200)
    ]
    common = {"robots": ["R1"], "t0": 0.0, "step_s": 2.0, "steps": 10, "link_mbit": 11.0}
    judged = analyse(frames, [], schedule=schedule, **common)  # type: ignore[arg-type]
    traced = analyse(frames, [], schedule=schedule, link_events=False, **common)  # type: ignore[arg-type]
    assert judged.changes
    assert judged.phases
    assert traced.changes == ()
    assert traced.phases == ()
    # A traced step carries the capacity's mean over it: 2 s of 0.2-s entries 1, 2, 3, 4, 5, ...
    assert [s.link_mbit for s in traced.steps] == pytest.approx([3.0] * 10)
    assert [s.link_mbit for s in judged.steps] == [5.0] * 10  # the rate in force at its end
