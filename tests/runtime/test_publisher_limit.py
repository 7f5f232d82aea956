"""The rate a managed publisher's limiter runs at: derived in one place, applied in one place.

``ManagedPublisher._limit_hz`` is the rate in force (``FailSafe``) capped by the outage gate,
and ``_apply_locked`` the one place the limiter's rate changes. Checked state by state, then
over random runs of allocations, heartbeats, beacons, outages and messages: the steady path
never finds the limiter at another rate, and what goes out in any window stays within the
integral of the rate in force, capped as a hold caps it, plus the banked frames.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dbml.protocol import names
from dbml.protocol.messages import Heard, LinkBeacon
from dbml.runtime import ManagedPublisher
from dbml.runtime.failsafe import FAILSAFE_PERIODS
from dbml.runtime.outage import HOLD_MAX_S, LINK_SILENCE_S, PROBE_INTERVAL_S, PROBE_RATE_HZ
from dbml.runtime.rate import RateLimiter
from dbml.testing import BASE
from dbml.transports import Variant
from tests.runtime.test_publisher_outage import MIN_RATE_HZ, PERIOD_S, RATE_HZ, Outage

TOPIC = "/r1/camera"
OTHER = "/r2/camera"


@pytest.fixture
def fleet() -> Iterator[Outage]:
    with Outage() as outage:
        yield outage


def limit_hz(camera: ManagedPublisher, fleet: Outage) -> float:
    """What the limiter runs at, checked against the one derivation at this instant."""
    assert camera._limiter.rate_hz == camera._limit_hz(fleet.clock())
    return camera._limiter.rate_hz


def test_the_limiter_runs_at_the_one_derived_rate_in_each_state(fleet: Outage) -> None:
    camera = fleet.stream(TOPIC, 0.9, rate_hz=None)
    assert not camera.publish(b"waiting")  # awaiting a first allocation: credit spent, none sent
    assert limit_hz(camera, fleet) == MIN_RATE_HZ
    fleet.host(BASE).params.set(names.current_value(TOPIC), RATE_HZ)
    assert limit_hz(camera, fleet) == RATE_HZ  # allocated: applied on arrival, not at a publish
    fleet.say(LinkBeacon(up=True))
    fleet.say(LinkBeacon(up=False, release_s={TOPIC: 0.0}))
    assert limit_hz(camera, fleet) == RATE_HZ  # held: nothing but probes goes
    fleet.advance(PROBE_INTERVAL_S)
    assert camera.publish(b"probe")
    assert camera._limiter.rate_hz == PROBE_RATE_HZ  # its turn: a probe, capped
    assert camera._limit_hz(fleet.clock(), probe=True) == PROBE_RATE_HZ
    fleet.say(LinkBeacon(up=True, release_s={TOPIC: 0.0}))
    assert not camera.holding
    assert limit_hz(camera, fleet) == RATE_HZ  # released: the allocation again
    fleet.advance(FAILSAFE_PERIODS + 0.1)  # no allocation, no heartbeat: fail-safe
    fleet.say(LinkBeacon(up=True))
    camera.publish(b"fail-safe")
    assert limit_hz(camera, fleet) == MIN_RATE_HZ
    fleet.host(BASE).params.set(names.ROUND, 1)  # the heartbeat: the allocation stands again
    assert limit_hz(camera, fleet) == RATE_HZ


def test_past_the_holds_bound_the_limiter_runs_at_the_minimum(fleet: Outage) -> None:
    camera = fleet.stream(TOPIC, 0.9)
    fleet.say(LinkBeacon(up=True))
    round_ = 0
    while fleet.clock() < 100.0 + LINK_SILENCE_S + HOLD_MAX_S + PERIOD_S:
        round_ += 1
        fleet.host(BASE).params.set(names.ROUND, round_)  # the allocation stays fresh throughout
        fleet.advance(PERIOD_S)
    assert not camera.holding
    camera.publish(b"outlasted")
    assert limit_hz(camera, fleet) == MIN_RATE_HZ  # not the allocation of 10 Hz
    fleet.say(LinkBeacon(up=True, release_s={TOPIC: 0.0}))
    assert limit_hz(camera, fleet) == RATE_HZ


def test_a_slower_allocation_below_the_probe_rate_caps_its_probes_itself(fleet: Outage) -> None:
    slow_hz = PROBE_RATE_HZ / 4
    camera = fleet.stream(TOPIC, 0.9, rate_hz=slow_hz)
    fleet.say(LinkBeacon(up=True))
    fleet.say(LinkBeacon(up=False, release_s={TOPIC: 0.0}))
    camera.publish(b"probe")
    assert camera._limiter.rate_hz == slow_hz


# -- random runs ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Advance:
    seconds: float


@dataclass(frozen=True, slots=True)
class Source:
    """A sensor at ``rate_hz`` for ``seconds``; with ``beacons``, the link says "up" each 0.1 s."""

    rate_hz: float
    seconds: float
    beacons: bool


@dataclass(frozen=True, slots=True)
class Allocate:
    rate_hz: float


@dataclass(frozen=True, slots=True)
class Heartbeat:
    pass


@dataclass(frozen=True, slots=True)
class Period:
    period_s: float


@dataclass(frozen=True, slots=True)
class Beacon:
    up: bool
    release_s: float
    heard: Heard | None


Step = Advance | Source | Allocate | Heartbeat | Period | Beacon

STEPS = st.one_of(
    st.builds(Advance, st.floats(0.001, 3.0)),  # up to a hold or a fail-safe
    st.builds(Source, st.floats(1.0, 100.0), st.floats(0.05, 5.0), st.booleans()),
    st.builds(Allocate, st.floats(0.2, 40.0)),
    st.just(Heartbeat()),
    st.builds(Period, st.floats(0.2, 2.0)),
    st.builds(
        Beacon,
        st.booleans(),
        st.sampled_from([0.0, 0.05, 0.3]),
        st.one_of(
            st.none(),
            st.builds(Heard, st.integers(0, 50), st.integers(0, 20)),
        ),
    ),
)


@dataclass(frozen=True, slots=True)
class Snapshot:
    """From ``t_s`` on, until the next: what the rate the limiter may run at depends on."""

    t_s: float
    allocated_hz: float | None
    deadline_s: float
    hold_from_s: float | None
    link_deadline_s: float

    def limit_hz(self, t_s: float) -> float:
        """The rate in force (``FailSafe.rate_hz``) capped as a hold caps it, at ``t_s``.

        A held channel sends probes alone, each at most at ``PROBE_RATE_HZ``; past
        ``HOLD_MAX_S`` it runs at the minimum at most.
        """
        fresh = self.allocated_hz is not None and t_s <= self.deadline_s
        rate_hz = self.allocated_hz if fresh and self.allocated_hz is not None else MIN_RATE_HZ
        start_s = self.hold_from_s
        if start_s is None and t_s > self.link_deadline_s:
            start_s = self.link_deadline_s
        if start_s is None:
            return rate_hz
        return min(rate_hz, PROBE_RATE_HZ if t_s - start_s <= HOLD_MAX_S else MIN_RATE_HZ)

    def breaks(self) -> list[float]:
        """Where ``limit_hz`` may change before the next snapshot."""
        start_s = self.link_deadline_s if self.hold_from_s is None else self.hold_from_s
        return [self.deadline_s, self.link_deadline_s, start_s + HOLD_MAX_S]


def run(fleet: Outage, camera: ManagedPublisher, steps: list[Step]) -> list[Snapshot]:
    """Take ``steps``; after each, the steady path's promise holds. What the limit hung on when."""
    allocation, gate = camera._allocation, camera._gate
    schedule: list[Snapshot] = []

    def note() -> None:
        rate_hz, until = camera._steady
        if fleet.clock() <= until:  # publish asks the limiter alone: it runs at that rate
            assert camera._limiter.rate_hz == rate_hz
        schedule.append(
            Snapshot(
                fleet.clock(),
                allocation.allocated_hz,
                allocation.deadline,
                gate._hold_from,
                gate.link_deadline,
            )
        )

    note()
    heartbeats = 0
    for step in steps:
        match step:
            case Advance(seconds):
                fleet.advance(seconds)
            case Source(rate_hz, seconds, beacons):
                beacon_at = fleet.clock()
                for _ in range(max(1, round(rate_hz * seconds))):
                    camera.publish(b"frame")
                    note()
                    fleet.advance(1 / rate_hz)
                    if beacons and fleet.clock() >= beacon_at:
                        fleet.say(LinkBeacon(up=True))
                        beacon_at += 0.1
                        note()
            case Allocate(rate_hz):
                fleet.host(BASE).params.set(names.current_value(TOPIC), rate_hz)
            case Heartbeat():
                heartbeats += 1
                fleet.host(BASE).params.set(names.ROUND, heartbeats)
            case Period(period_s):
                fleet.host(BASE).params.set(names.PERIOD, period_s)
            case Beacon(up, release_s, heard):
                word = None if heard is None else {TOPIC: heard}
                fleet.say(LinkBeacon(up, {TOPIC: release_s, OTHER: 0.1}, heard=word))
        note()
    return schedule


def integral(schedule: list[Snapshot], start_s: float, end_s: float) -> float:
    """Frames earned over [start_s, end_s] at the rate the limiter may run at."""
    total = 0.0
    for now, then in itertools.pairwise(schedule):
        lo, hi = max(start_s, now.t_s), min(end_s, then.t_s)
        if hi <= lo:
            continue
        points = sorted({lo, hi, *(t for t in now.breaks() if lo < t < hi)})
        for a, b in itertools.pairwise(points):
            total += (b - a) * now.limit_hz((a + b) / 2)
    return total


@settings(max_examples=150, deadline=None)
@given(st.lists(STEPS, max_size=40))
@example([Allocate(10.0), Source(20.0, 5.0, beacons=True)])  # into the fail-safe
@example(  # a hold, probes, a release owing what went into the dead link, a new period
    [
        Allocate(16.0),
        Source(30.0, 1.0, beacons=True),
        Beacon(up=False, release_s=0.0, heard=None),
        Source(30.0, 2.0, beacons=False),
        Heartbeat(),
        Beacon(up=True, release_s=0.05, heard=Heard(3, 1)),
        Source(30.0, 1.0, beacons=True),
        Period(0.2),
        Source(30.0, 1.0, beacons=True),
    ]
)
@example(  # a hold past its bound, the optimizer alive: the minimum, then the allocation
    [Allocate(16.0), Source(30.0, 0.5, beacons=True)]
    + [Source(30.0, 0.9, beacons=False), Heartbeat()] * 7
    + [Source(30.0, 1.0, beacons=True)]
)
def test_what_goes_out_never_exceeds_the_integral_of_the_derived_rate(steps: list[Step]) -> None:
    """Through allocations, heartbeats, fail-safes, holds, probes and releases alike.

    In every window from a message on: at most the integral of the rate in force, capped as a
    hold caps it, plus the banked frames; and whenever ``publish`` would take the steady path,
    the limiter runs at the allocation it assumes.
    """
    fleet = Outage()
    camera = fleet.stream(TOPIC, 0.9, rate_hz=None)
    sent: list[float] = []
    fleet.operator.subscribe(TOPIC, lambda _s: sent.append(fleet.clock()), Variant.OPTIMIZED)
    fleet.say(LinkBeacon(up=True))
    schedule = run(fleet, camera, steps)
    for i, start in enumerate(sent):
        for window_s in (0.25, 1.0):
            count = sum(1 for s in sent[i:] if s < start + window_s)
            bound = integral(schedule, start, start + window_s) + RateLimiter.BANKED_FRAMES
            assert count <= bound + 1e-6, (start, window_s, count, bound)
