"""Reception reports and the estimator node over the memory transport, on manual clocks."""

from __future__ import annotations

import logging

import pytest

from dbml.estimator import Phase
from dbml.estimator import shared as estimator_shared
from dbml.protocol import names
from dbml.protocol.keys import LINK_TOPIC, RECEPTION_TOPIC
from dbml.protocol.messages import (
    EstimatorState,
    Heard,
    LinkBeacon,
    ReceivedFrame,
    ReceptionReport,
)
from dbml.protocol.metadata import pack_meta
from dbml.runtime import estimator as node_estimator
from dbml.runtime.estimator import (
    MAX_REPORTERS,
    WAKE_GAP_S,
    WAKE_QUEUE_S,
    LinkEstimator,
)
from dbml.runtime.optimizer import OptimizerNode
from dbml.runtime.outage import HEARD_WAIT_S, PROBE_INTERVAL_S
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.reception import (
    EARLY_FLUSH_QUEUE_S,
    REPORT_INTERVAL_S,
    ReceptionReporter,
)
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports import MemoryNetwork, MemoryTransport, Variant
from dbml.transports.base import Role, Sample
from dbml.transports.memory import ManualClock

WALL_S = 1_700_000_000.0
"""The base station's wall clock at its monotonic 0."""
FRAME_BYTES = 100_000
RATE_HZ = 10.0  # 8 Mbit/s


class Link:
    """A robot sending frames to an operator whose reports reach an estimating base station.

    The three hosts have unrelated clocks: the operator's is 1000 s ahead of the base
    station's, the robot's send stamps 50 s behind.
    """

    def __init__(self) -> None:
        network = self.network = MemoryNetwork()
        self.op_clock = ManualClock(1000.0)
        self.base_clock = ManualClock(0.0)
        self.operator = MemoryTransport(network, host="op", clock=self.op_clock)
        self.base = MemoryTransport(network, host="base", clock=self.base_clock)
        self.base.params.set(names.BANDWIDTH, 10.0)
        self.base.params.set(names.UTILIZATION, 0.9)
        self.changes = 0
        self.states: list[object] = []
        self.estimator = LinkEstimator(
            self.base, on_change=self._changed, wall_clock_s=lambda: WALL_S + self.base_clock()
        )
        self.reporter = ReceptionReporter(self.operator)
        self.received: list[Sample] = []
        self.subscriber = ManagedSubscriber(
            self.operator, "/cam", self.received.append, reporter=self.reporter
        )
        robot = MemoryTransport(network, host="r1")
        self.raw = robot.declare_publisher("/cam", Variant.OPTIMIZED)
        robot.graph.announce(Role.PUBLISHER, "/cam", Variant.FULL)  # a live channel, as a
        # managed publisher announces it: the estimator takes reports of live channels only
        self.t = 0.0
        self.seq = 0

    def listen(self, host: str, *topics: str) -> None:
        """Live channels ``topics`` (a robot publishes them) that ``host`` subscribes to."""
        transport = MemoryTransport(self.network, host=host)
        robot = MemoryTransport(self.network, host="r9")
        for topic in topics:
            robot.graph.announce(Role.PUBLISHER, topic, Variant.FULL)
            transport.graph.announce(Role.SUBSCRIBER, topic, Variant.OPTIMIZED)

    def _changed(self) -> None:
        self.changes += 1
        self.states.append(self.base.params.get(names.ESTIMATOR_STATE))

    def run(self, seconds: float, *, delay_growth: float = 0.0, skip: int = 0) -> None:
        """Send at 10 Hz for ``seconds``; one-way delay grows by ``delay_growth`` s per s."""
        end = self.t + seconds
        while self.t < end - 1e-9:
            self.t += 1 / RATE_HZ
            delay = 0.05 + delay_growth * self.t
            self.op_clock.advance(1000.0 + self.t + delay - self.op_clock())
            meta = pack_meta(self.seq, round((self.t - 50.0) * 1e9), RATE_HZ)
            self.raw.put(bytes(FRAME_BYTES), attachment=meta)
            self.seq += 1 + skip
            self.reporter.flush()
            self.base_clock.advance(self.t + delay + 0.2 - self.base_clock())
            self.estimator.tick()


def test_a_link_that_carries_everything_keeps_the_configured_budget() -> None:
    link = Link()
    link.run(3.0)
    assert len(link.received) == 30
    state = link.estimator.tick()
    assert state is not None
    assert state.phase is Phase.INCREASE
    assert state.received_mbit == pytest.approx(8.0, rel=0.25)  # 4-5 frames in the window
    assert link.estimator.budget_mbit() == pytest.approx(9.0)  # 10 Mbit/s x 0.9: the cap
    assert link.base.params.get(names.ESTIMATE) == pytest.approx(9.0)
    published = EstimatorState.decode(str(link.base.params.get(names.ESTIMATOR_STATE)))
    assert published.phase is Phase.INCREASE
    assert published.text.startswith("increase: received")


def test_growing_delay_lowers_the_budget_and_pokes_the_optimizer() -> None:
    link = Link()
    optimizer = OptimizerNode(link.base, budget_mbit=link.estimator.budget_mbit)
    link.run(2.0)
    before = link.changes
    link.run(1.0, delay_growth=0.5)  # the link carries 2/3 of what is sent
    estimate = link.estimator.budget_mbit()
    assert estimate is not None
    assert estimate < 8.0
    assert link.changes > before
    assert float(link.base.params.get(names.ESTIMATE) or 0) == pytest.approx(estimate, rel=0.01)
    assert optimizer.budget_mbit() == estimate  # the estimate replaces bandwidth x utilization
    assert optimizer.optimize().budget_mbit == estimate
    optimizer.stop()


def test_a_cut_carries_the_wall_clock_time_it_was_decided() -> None:
    """The testbed times a cut from it: the operator's ticks would see it only every 0.2 s."""
    link = Link()
    link.run(2.0)
    link.run(1.0, delay_growth=0.5)
    states = [EstimatorState.decode(str(s)) for s in link.states]
    cuts = [s for s in states if s.phase is Phase.DECREASE]
    assert cuts, link.states
    decided = cuts[0].decided_at_s
    assert decided is not None, cuts[0]
    assert 2.0 < decided - WALL_S < 3.5  # the base's clock at the decision
    assert cuts[0].text.endswith(f" @{decided:.3f}")  # and the monitor's line shows it
    assert not any(s.decided_at_s is not None for s in states if s.phase is Phase.INCREASE)
    # the hold that follows, at the cut's estimate, still says when the cut was decided: a
    # woken tick may publish it before a reader polls
    after = states[states.index(cuts[0]) + 1]
    assert after.phase is Phase.HOLD
    assert after.decided_at_s == decided


def _down(link: Link) -> list[LinkBeacon]:
    """Frames for 2 s, then 2 s without one (an outage); the beacons the operator hears."""
    beacons: list[LinkBeacon] = []
    link.operator.subscribe(LINK_TOPIC, lambda s: beacons.append(LinkBeacon.decode(s.payload)))
    link.run(2.0)
    assert beacons
    assert all(b.up and b.heard is None for b in beacons)  # no outage: not said
    for _ in range(20):
        link.t += 0.1
        link.base_clock.advance(0.1)
        link.estimator.tick()
    assert not beacons[-1].up
    assert beacons[-1].heard is None
    link.estimator.tick()  # still down, nothing arrived: nobody is heard
    return beacons


def _heard_after(beacons: list[LinkBeacon], down: int) -> Heard | None:
    after = [b for b in beacons[down:] if b.up]
    assert after, beacons[down:]
    assert all(b.heard is not None for b in after)
    return (after[-1].heard or {}).get("/cam")


def test_after_an_outage_the_beacon_names_the_channels_heard_again() -> None:
    link = Link()
    beacons = _down(link)
    down = len(beacons)
    link.run(0.5)
    # what a release owes is counted from it: the newest frame, and the five since the return
    # (the ones before the outage are more than a second old)
    assert _heard_after(beacons, down) == Heard(newest_seq=link.seq - 1, recent_frames=5)


def test_the_beacon_counts_the_last_second_of_arrivals_only() -> None:
    link = Link()
    beacons = _down(link)
    down = len(beacons)
    link.run(1.5)  # 15 frames since the return, 10 of them in the last second
    assert _heard_after(beacons, down) == Heard(newest_seq=link.seq - 1, recent_frames=10)


def test_a_restarted_publishers_numbers_are_its_newest() -> None:
    link = Link()
    beacons = _down(link)
    down = len(beacons)
    link.seq = 1  # the robot's process restarted during the outage
    link.run(0.5)
    assert _heard_after(beacons, down) == Heard(newest_seq=5, recent_frames=5)


def test_a_channel_heard_on_two_hosts_counts_as_the_one_that_heard_least() -> None:
    """A second subscriber's host heard two of the five, the older ones.

    Not seven frames, nor the newest of both: a release owes what the slower path may still
    carry.
    """
    link = Link()
    link.listen("op2", "/cam")
    beacons = _down(link)
    down = len(beacons)
    link.run(0.5)
    late = tuple(
        ReceivedFrame("/cam", seq, 0, 0.0, FRAME_BYTES) for seq in (link.seq - 5, link.seq - 4)
    )
    report = ReceptionReport("op2", link.base_clock(), late).encode()
    link.estimator._on_report(Sample(RECEPTION_TOPIC, report, None))
    link.estimator.tick()
    assert _heard_after(beacons, down) == Heard(newest_seq=link.seq - 4, recent_frames=5)


def test_the_channels_a_beacon_counts_are_bounded_by_the_ones_heard_last(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Channel names come from any peer's reports: one more evicts the one heard longest ago."""
    monkeypatch.setattr(node_estimator, "HEARD_MAX", 2)
    link = Link()
    link.listen("op", *(f"/t{k}" for k in range(5)))
    beacons = _down(link)
    down = len(beacons)
    link.run(0.5)
    others = tuple(ReceivedFrame(f"/t{k}", 1, 0, 0.0, 10) for k in range(5))
    report = ReceptionReport("op", link.base_clock(), others).encode()
    with caplog.at_level(logging.WARNING, logger="dbml.estimator"):
        link.estimator._on_report(Sample(RECEPTION_TOPIC, report, None))
        link.estimator.tick()
    last = [b for b in beacons[down:] if b.up][-1]
    assert last.heard is not None
    assert set(last.heard) == {"/t3", "/t4"}  # the last two reported, no more
    assert [r.getMessage() for r in caplog.records] == [
        "(host, channel) pairs heard: 2 held, the most kept; evicting the oldest "
        "(told once until half of them are gone)"
    ]
    link.run(0.1)  # the real channel again: it evicts the one heard longest ago
    last = [b for b in beacons[down:] if b.up][-1]
    assert set(last.heard or {}) == {"/t4", "/cam"}


def test_channels_no_beacon_can_name_are_forgotten() -> None:
    """Channels heard once: what they filled is gone once no beacon can name it."""
    link = Link()
    link.listen("op", *(f"/t{k}" for k in range(50)))
    link.run(0.5)
    others = tuple(ReceivedFrame(f"/t{k}", 1, 0, 0.0, 10) for k in range(50))
    report = ReceptionReport("op", link.base_clock(), others).encode()
    link.estimator._on_report(Sample(RECEPTION_TOPIC, report, None))
    assert len(link.estimator._arrived) == 51
    link.run(0.5)  # within the release's window: still counted
    assert len(link.estimator._arrived) == 51
    link.run(1.0)  # past it, and no outage: only the real channel is left
    assert list(link.estimator._arrived) == [("op", "/cam")]
    beacons = _down(link)  # in an outage and its release order, what came after it counts
    down = len(beacons)
    link.run(0.5)
    assert _heard_after(beacons, down) == Heard(newest_seq=link.seq - 1, recent_frames=5)


def test_lost_frames_lower_the_budget() -> None:
    link = Link()
    link.run(2.0)
    link.run(0.5, skip=1)  # every other frame lost
    estimate = link.estimator.budget_mbit()
    assert estimate is not None
    assert estimate < 9.0


def test_the_estimate_never_exceeds_the_configured_budget_when_it_changes() -> None:
    link = Link()
    link.run(1.0)
    link.base.params.set(names.BANDWIDTH, 5.0)
    link.run(0.3)
    assert link.estimator.budget_mbit() == pytest.approx(4.5)


def test_no_budget_configured_means_no_estimate() -> None:
    link = Link()
    link.base.params.set(names.BANDWIDTH, None)
    assert link.estimator.tick() is None
    assert link.estimator.budget_mbit() is None


def test_close_withdraws_the_estimate() -> None:
    link = Link()
    link.run(0.5)
    link.estimator.close()
    assert link.base.params.get(names.ESTIMATE) is None
    assert link.base.params.get(names.ESTIMATOR_STATE) is None


def test_reports_are_sent_only_while_someone_listens() -> None:
    network = MemoryNetwork()
    operator = MemoryTransport(network, host="op")
    reporter = ReceptionReporter(operator)
    sample = Sample("/cam", b"x" * 10, pack_meta(0, 0, 1.0))
    reporter.record(sample)
    assert reporter.flush() == 0  # nobody subscribed to the reports
    got: list[Sample] = []
    MemoryTransport(network, host="base").subscribe(RECEPTION_TOPIC, got.append)
    reporter.record(sample)
    reporter.record(Sample("/cam", b"y", None))  # not from a dbml publisher: ignored
    assert reporter.flush() == 1
    report = ReceptionReport.decode(got[0].payload)
    assert report.host == "op"
    assert [(f.topic, f.seq, f.size_bytes) for f in report.frames] == [("/cam", 0, 10)]


def test_a_report_the_estimators_arithmetic_cannot_take_is_refused_and_it_ticks_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A 400-digit frame size once passed the decode and broke the next tick (int to float)."""
    link = Link()
    link.run(0.5)
    huge = b"1" + b"0" * 400
    report = b'{"host": "op", "now_s": 0.0, "frames": [["/cam", 99, 0, 0.0, ' + huge + b"]]}"
    with caplog.at_level(logging.WARNING, logger="dbml.estimator"):
        for _ in range(1000):  # a flood of them is one line (a while)
            link.estimator._on_report(Sample(RECEPTION_TOPIC, report, None))
    assert [r.getMessage()[:55] for r in caplog.records] == [
        "ignoring a reception report: malformed reception report"
    ]
    assert "frames[0].size_bytes=1000" in caplog.records[0].getMessage()
    link.run(0.5)
    assert link.estimator.tick() is not None
    assert link.estimator.budget_mbit() == pytest.approx(9.0)


def test_clock_offsets_are_kept_for_at_most_max_reporters_hosts(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A report's host name is the network's word: made-up ones cannot grow the table."""
    link = Link()
    link.run(0.5)
    assert list(link.estimator._offsets) == ["op"]
    forger = link.operator.declare_publisher(RECEPTION_TOPIC)
    bound = MAX_REPORTERS
    with caplog.at_level(logging.WARNING, logger="dbml.estimator"):
        for i in range(bound + 5):
            forger.put(ReceptionReport(f"forged-{i}", 0.0, ()).encode())
    offsets = link.estimator._offsets
    assert len(offsets) == bound
    assert "op" not in offsets  # silent the longest: evicted first
    assert "forged-0" not in offsets
    assert f"forged-{bound + 4}" in offsets
    assert [r.getMessage() for r in caplog.records if r.name == "dbml.estimator"] == [
        f"reporting hosts: {bound} held, the most kept; evicting the oldest "
        "(told once until half of them are gone)"
    ]
    link.run(0.5)  # the real host reports again: its offset is learnt anew
    assert "op" in offsets
    assert len(offsets) == bound


def test_streams_and_frames_past_the_estimators_bounds_are_logged_once_per_flood(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The core estimator only counts what it evicts and refuses: its node says it, unlocked."""
    for module in (estimator_shared, node_estimator):
        monkeypatch.setattr(module, "MAX_STREAMS", 8)
        monkeypatch.setattr(module, "MAX_SAMPLES", 16)
    clock = ManualClock(0.0)
    network = MemoryNetwork()
    base = MemoryTransport(network, host="base", clock=clock)
    base.params.set(names.BANDWIDTH, 10.0)
    robot = MemoryTransport(network, host="r1")
    for i in range(12):  # live channels: the estimator takes reports of those only
        robot.graph.announce(Role.PUBLISHER, f"/t{i}", Variant.FULL)
    estimator = LinkEstimator(base)
    told: list[tuple[str, bool]] = []  # each warning, and whether the estimator's lock was held

    class Told(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.WARNING:
                told.append((record.getMessage(), estimator._lock.locked()))

    def report(*frames: tuple[str, int]) -> None:
        received = tuple(ReceivedFrame(topic, seq, 0, 0.0, 1_000) for topic, seq in frames)
        payload = ReceptionReport("h", clock(), received).encode()
        estimator._on_report(Sample(RECEPTION_TOPIC, payload, None))

    handler = Told()
    logging.getLogger("dbml.estimator").addHandler(handler)
    try:
        assert estimator.tick() is not None  # the core estimator is made by the first tick
        report(*((f"/t{i}", 0) for i in range(12)))  # 4 streams more than the bound
        report(*((f"/t{i}", 1) for i in range(8, 12)))  # heard again: nothing evicted
        report(*(("/t11", seq) for seq in range(2, 22)))  # 12 held: 4 more kept, 16 refused
        core = estimator._estimator
        assert core is not None
        assert (core.streams_evicted, core.samples_refused) == (4, 16)
        assert (core.stream_count, core.sample_count) == (8, 16)
        clock.advance(20.0)  # every frame leaves the base window: both floods are over
        estimator.tick()
        assert (core.stream_count, core.sample_count) == (0, 0)
    finally:
        logging.getLogger("dbml.estimator").removeHandler(handler)
        estimator.close()
    assert told == [
        (
            "streams followed: 8 held, the most kept; evicting the oldest "
            "(told once until half of them are gone)",
            False,
        ),
        (
            "frames kept: 16 held, the most kept; refusing new ones "
            "(told once until half of them are gone)",
            False,
        ),
        ("streams followed: room again; 4 evicted meanwhile", False),
        ("frames kept: room again; 16 refused meanwhile", False),
    ]


def _frame(link: Link, *, queued_s: float, after_s: float = 1 / RATE_HZ) -> None:
    """One frame ``after_s`` after the last, ``queued_s`` later than the link's usual 0.05 s."""
    link.t += after_s
    link.op_clock.advance(1000.0 + link.t + 0.05 + queued_s - link.op_clock())
    meta = pack_meta(link.seq, round((link.t - 50.0) * 1e9), RATE_HZ)
    link.raw.put(bytes(FRAME_BYTES), attachment=meta)
    link.seq += 1
    link.base_clock.advance(link.t + 0.05 + queued_s + 0.2 - link.base_clock())  # as ``run``


def test_a_frame_that_queued_is_reported_at_once_at_most_once_an_interval() -> None:
    """The estimator cuts sooner; a congested link at most doubles the reports."""
    link = Link()
    link.run(1.0)
    wake = link.reporter._worker._wake
    _frame(link, queued_s=EARLY_FLUSH_QUEUE_S * 0.9)
    assert not wake.is_set()  # within the usual spread: the periodic flush takes it
    _frame(link, queued_s=EARLY_FLUSH_QUEUE_S * 1.1)
    assert wake.is_set()
    wake.clear()
    _frame(link, queued_s=EARLY_FLUSH_QUEUE_S * 1.1, after_s=REPORT_INTERVAL_S / 2)
    assert not wake.is_set()  # one early flush an interval
    _frame(link, queued_s=EARLY_FLUSH_QUEUE_S * 1.1, after_s=REPORT_INTERVAL_S * 0.6)
    assert wake.is_set()  # the next interval


def test_a_report_of_a_frame_that_queued_wakes_the_estimator_at_once() -> None:
    link = Link()
    link.run(1.0)
    wake = link.estimator._worker._wake
    _frame(link, queued_s=WAKE_QUEUE_S * 0.9)
    link.reporter.flush()
    assert not wake.is_set()  # the next tick judges it
    _frame(link, queued_s=WAKE_QUEUE_S * 1.1)
    link.reporter.flush()
    assert wake.is_set()
    wake.clear()
    link.estimator.tick()
    _frame(link, queued_s=WAKE_QUEUE_S * 1.1, after_s=WAKE_GAP_S / 2)
    link.reporter.flush()
    assert not wake.is_set()  # it just judged: a wake waits WAKE_GAP_S after a tick


# -- a flood of made-up reporting hosts never keeps a real channel's release waiting ------------

FLOOD_HOSTS = 10_000
FLOOD_CHANNELS = 5_000
CAMERA = "/r1/camera"


class OutageLink:
    """A robot's managed publisher, an operator reporting what it receives, an estimating base.

    One manual clock; ``up`` False is a dead link (the operator receives nothing), and the
    publisher hears the estimator's beacons as it would over the link's other direction.
    """

    def __init__(self) -> None:
        self.clock = ManualClock(100.0)
        network = MemoryNetwork()
        self.base = MemoryTransport(network, host="base", clock=self.clock)
        self.base.params.set(names.BANDWIDTH, 10.0)
        self.base.params.set(names.UTILIZATION, 0.9)
        self.estimator = LinkEstimator(self.base, wall_clock_s=self.clock)
        operator = MemoryTransport(network, host="op", clock=self.clock)
        self.reporter = ReceptionReporter(operator)
        self.up = True
        self.beacons: list[LinkBeacon] = []
        operator.subscribe(CAMERA, self._receive, Variant.OPTIMIZED)
        operator.graph.announce(Role.SUBSCRIBER, CAMERA, Variant.OPTIMIZED)  # as subscribers do
        operator.subscribe(LINK_TOPIC, lambda s: self.beacons.append(LinkBeacon.decode(s.payload)))
        self.operator = operator
        robot = MemoryTransport(network, host="r1", clock=self.clock)
        self.camera = ManagedPublisher(
            robot,
            CAMERA,
            min_rate_hz=1.0,
            max_rate_hz=16.0,
            priority=0.9,
            wall_clock_ns=lambda: round(self.clock() * 1e9),
        )
        self.base.params.set(names.current_value(CAMERA), RATE_HZ)
        self.forger = MemoryTransport(network, host="forger", clock=self.clock)
        self.rounds = 0

    def _receive(self, sample: Sample) -> None:
        if self.up:
            self.reporter.record(sample)

    def step(self, *, flood: bool = False) -> None:
        """0.1 s: a frame, the operator's report, the optimizer's heartbeat, the estimator.

        ``flood``: and a forged report, before the tick, of ``FLOOD_CHANNELS`` made-up channels
        from the operator's own host (the reports are not authenticated).
        """
        self.clock.advance(1 / RATE_HZ)
        self.camera.publish(bytes(FRAME_BYTES // 10))
        self.reporter.flush()
        if flood:
            forged = self.forger.declare_publisher(RECEPTION_TOPIC)
            frames = tuple(
                ReceivedFrame(f"/forged{k}/camera", self.rounds, 0, self.clock(), 1_000)
                for k in range(FLOOD_CHANNELS)
            )
            forged.put(ReceptionReport("op", self.clock(), frames).encode())
            forged.close()
        self.rounds += 1
        self.base.params.set(names.ROUND, self.rounds)
        self.estimator.tick()

    def flood(self) -> None:
        """A report from each of ``FLOOD_HOSTS`` made-up hosts.

        Of the camera (the live channel whose release is at stake) from half of them, of a
        made-up channel from the others.
        """
        forged = self.forger.declare_publisher(RECEPTION_TOPIC)
        for k in range(FLOOD_HOSTS):
            topic = CAMERA if k % 2 else f"/forged{k}/camera"
            frame = ReceivedFrame(topic, 1, 0, self.clock(), 1_000)
            forged.put(ReceptionReport(f"forged-{k}", self.clock(), (frame,)).encode())
        forged.close()


@pytest.mark.parametrize("when", ["before the channel", "in the outage", "every tick"])
def test_a_flood_of_forged_reporters_never_keeps_a_channels_release_waiting(when: str) -> None:
    """Forged reports from 10,000 hosts, then the link out: the real channel is still heard.

    Back from the outage, the camera (which sent into the dead link: its probes) waits to be
    heard before it releases. It is heard at the first report after the link is back, so it
    releases long before ``HEARD_WAIT_S``, the bound on a wait for a channel never heard.
    ``every tick``: a forged report of 5,000 made-up channels from the operator's own host
    between each real report and the tick.
    """
    link = OutageLink()
    every = when == "every tick"
    link.step()  # the first tick makes the core estimator
    if when == "before the channel":
        link.flood()
    for _ in range(20):  # 2 s up
        link.step(flood=every)
    assert not link.camera.holding
    link.up = False
    for _ in range(15):  # 1.5 s down: declared, and held
        link.step(flood=every)
    assert link.camera.holding
    assert not link.beacons[-1].up
    if when == "in the outage":
        link.flood()
    link.up = True
    back = link.clock()
    while link.camera.holding and link.clock() - back < 2 * HEARD_WAIT_S:
        link.step(flood=every)
    released = link.clock() - back
    assert not link.camera.holding
    # the first probe after the link is back (one every PROBE_INTERVAL_S), its report, a tick
    assert released <= PROBE_INTERVAL_S + 2 / RATE_HZ < HEARD_WAIT_S
    heard = [b.heard for b in link.beacons if b.up and b.heard and CAMERA in b.heard]
    assert heard, "the release was not on the camera's own word"
    link.estimator.close()
    link.camera.close()
