"""The optimizer node's rules, on the memory transport (deterministic, one round at a time)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from dataclasses import replace

import pytest

from dbml.core import DbmSettings, LinkSpec, Status, Strategy
from dbml.protocol import names
from dbml.protocol.keys import ROUND_TOPIC
from dbml.runtime import ManagedPublisher, ManagedSubscriber, OptimizerNode, Round
from dbml.runtime.optimizer import ACK_TIMEOUT_S, MAX_CHANNELS, _Outcome
from dbml.runtime.params import ChannelParams, DbmParams
from dbml.runtime.rounds import RoundFollower
from dbml.testing import Fleet
from dbml.transports import ManualClock, MemoryNetwork, MemoryTransport, ParamValue, Role, Variant
from tests.conftest import wait_for

R1, R2 = "/r1/camera", "/r2/camera"
SIZES = {R1: 84_000, R2: 21_000}


def two_robots(
    *, mbit: float = 11.0, strategy: Strategy = Strategy.PAPER, links: tuple[LinkSpec, ...] = ()
) -> Fleet:
    """The paper's section 4: two robots (their sizes known), an operator and an optimizer."""
    fleet = Fleet(settings=DbmSettings(mbit, 1.0, 1.0, strategy), links=links)
    for topic, size in SIZES.items():
        fleet.publisher(topic, size_bytes=size)
    return fleet


def rate_writes(fleet: Fleet) -> list[tuple[str, float]]:
    """Every rate the optimizer writes from now on, in order: (topic, Hz)."""
    writes: list[tuple[str, float]] = []

    def record(name: str, value: object) -> None:
        if name.endswith("/dbm/frequency/current_value") and isinstance(value, float):
            writes.append((name.removesuffix("/dbm/frequency/current_value"), value))

    fleet.operator.params.watch(record)
    return writes


def test_remote_subscribers_make_channels_managed_and_get_table2_rates() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R2, 10 / 17)  # step 1: R1 tc 20 s, R2 tc 10 s
    result = fleet.optimizer.optimize()
    assert result.status is Status.OPTIMAL
    assert {c.topic for c in result.channels if c.managed} == {R1, R2}
    rates = fleet.rates()
    assert round(rates[R1], 2) == 12.37
    assert rates[R2] == 16.0
    assert fleet.operator.params.get(names.managed(R1)) is True
    assert fleet.operator.params.get(names.STATUS) == "optimal"


def test_unmanaged_channels_run_at_maximum() -> None:
    fleet = two_robots()
    ManagedSubscriber(MemoryTransport(fleet.network, host="r1"), R1, lambda s: None)  # local only
    fleet.optimizer.optimize()
    assert fleet.rates() == {R1: 16.0, R2: 16.0}
    assert fleet.operator.params.get(names.managed(R1)) is False


def test_a_channel_returns_to_maximum_when_its_last_remote_subscriber_leaves() -> None:
    fleet = two_robots(mbit=5)
    first, second = fleet.watch(R1), fleet.watch(R1)
    fleet.watch(R2)
    fleet.optimizer.optimize()
    assert fleet.rates()[R1] < 16
    first.close()
    fleet.optimizer.optimize()
    assert fleet.rates()[R1] < 16  # one remote subscriber is still there
    second.close()
    fleet.optimizer.optimize()
    assert fleet.rates()[R1] == 16.0


def test_decreases_are_applied_before_increases_and_the_budget_holds_throughout() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R1, 1.0)  # step 7: R1 16 Hz, R2 1.48 Hz
    fleet.optimizer.optimize()
    writes = rate_writes(fleet)
    fleet.priority(R1, 0.0)
    fleet.priority(R2, 1.0)  # step 10: R1 12.37 Hz, R2 16 Hz
    fleet.optimizer.optimize()
    assert [topic for topic, _ in writes] == [R1, R2]  # R1 goes down first
    applied = {R1: 16.0, R2: 31_000 / 21_000}
    for topic, rate in writes:
        applied[topic] = rate
        assert sum(applied[t] * SIZES[t] for t in applied) <= 1_375_000 * (1 + 1e-9)


def test_infeasible_budget_is_reported_and_rates_still_fit(
    caplog: pytest.LogCaptureFixture,
) -> None:
    fleet = two_robots(mbit=0.5)
    fleet.watch(R1)
    fleet.watch(R2)
    with caplog.at_level(logging.WARNING, logger="dbml.optimizer"):
        result = fleet.optimizer.optimize()
    assert result.status is Status.INFEASIBLE
    assert fleet.operator.params.get(names.STATUS) == "infeasible"
    message = fleet.operator.params.get(names.STATUS_MESSAGE)
    assert isinstance(message, str)
    assert message.startswith("minimum rates need 0.840 Mbit/s but the budget allows 0.500 Mbit/s")
    assert "infeasible" in caplog.text
    rates = fleet.rates()
    assert sum(rates[t] * SIZES[t] for t in rates) <= 62_500 * (1 + 1e-9)


def test_budget_changes_at_runtime() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.operator.params.set(names.BANDWIDTH, 5.0)
    fleet.optimizer.optimize()
    rates = fleet.rates()
    assert sum(rates[t] * SIZES[t] for t in rates) == pytest.approx(625_000)


def test_a_channel_without_a_size_yet_stays_at_minimum() -> None:
    fleet = two_robots()
    silent = ManagedPublisher(
        MemoryTransport(fleet.network, host="r3"), "/r3/lidar", min_rate_hz=2, max_rate_hz=10
    )
    fleet.watch("/r3/lidar")
    fleet.optimizer.optimize()
    assert silent.current_rate_hz() == 2.0


def test_lp_honours_a_configured_uplink() -> None:
    fleet = two_robots(strategy=Strategy.LP, links=(LinkSpec("r1-uplink", 4, (R1,)),))
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.optimizer.optimize()
    rates = fleet.rates()
    assert rates[R1] * 84_000 <= 500_000 * (1 + 1e-9)
    assert rates[R1] == pytest.approx(500_000 / 84_000)
    assert rates[R2] == 16.0


def test_a_links_capacity_shares_the_utilization() -> None:
    fleet = two_robots(strategy=Strategy.LP, links=(LinkSpec("r1-uplink", 4, (R1,)),))
    fleet.operator.params.set(names.UTILIZATION, 0.92)  # headers take the rest of every link
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.optimizer.optimize()
    assert fleet.rates()[R1] == pytest.approx(0.92 * 500_000 / 84_000)


def test_a_dead_publisher_is_forgotten() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.publishers[R1].close()
    result = fleet.optimizer.optimize()
    assert [c.topic for c in result.channels] == [R2]


def test_reacts_at_once_to_a_priority_change_and_coalesces_bursts() -> None:
    fleet = two_robots()
    fleet.operator.params.set(names.PERIOD, 60.0)  # the period alone would never react in time
    fleet.watch(R1)
    fleet.watch(R2)
    rounds: list[int] = []
    original = fleet.optimizer.optimize

    def counting() -> Round:
        rounds.append(1)
        return original()

    fleet.optimizer.optimize = counting  # type: ignore[method-assign]
    fleet.optimizer.start()
    try:
        wait_for(lambda: len(rounds) >= 1, what="the first round")
        wait_for(lambda: round(fleet.rates()[R1], 2) == 12.37, what="the initial allocation")
        before = len(rounds)
        done = threading.Event()

        def burst() -> None:
            for i in range(50):
                fleet.priority(R1, (i + 1) / 50)
            done.set()

        burst()
        wait_for(done.is_set)
        wait_for(lambda: fleet.rates()[R1] == 16.0, timeout_s=2, what="R1 at 16 Hz")
        assert len(rounds) - before < 50  # 50 changes, far fewer rounds
    finally:
        fleet.optimizer.stop()


def test_a_restarted_optimizer_orders_changes_by_what_publishers_run() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R2, 1.0)  # R1 12.37 Hz, R2 16 Hz
    fleet.optimizer.optimize()
    fleet.optimizer.stop()
    successor = OptimizerNode(MemoryTransport(fleet.network, host="base2"))
    fleet.priority(R2, 0.0)
    fleet.priority(R1, 1.0)  # R1 16 Hz, R2 1.48 Hz
    writes = rate_writes(fleet)
    successor.optimize()
    # It has pushed nothing yet, but the publishers' acknowledgements say R2 must go down first.
    assert [topic for topic, _ in writes] == [R2, R1]


def test_a_round_that_raises_is_tried_again_a_period_later_not_at_once() -> None:
    fleet = Fleet(settings=DbmSettings(11.0, 1.0, 0.5), clock=time.monotonic)
    calls: list[float] = []

    def failing() -> Round:
        calls.append(time.monotonic())
        raise RuntimeError("a round that fails")

    fleet.optimizer.optimize = failing  # type: ignore[method-assign]
    fleet.optimizer.start()
    try:
        wait_for(lambda: len(calls) >= 2, timeout_s=5, what="a second round")
        assert calls[1] - calls[0] >= 0.45
    finally:
        fleet.close()


def test_a_rate_moved_by_float_noise_only_is_not_pushed_again() -> None:
    """A solver's rounding (1.000000000000011 Hz for a floor of 1) is no change to push."""
    fleet = two_robots()
    paper_steady(fleet)
    before = dict(fleet.rates())
    allocate = fleet.optimizer._allocate

    def noisy(managed: list[ChannelParams], dbm: DbmParams) -> _Outcome:
        outcome = allocate(managed, dbm)
        return replace(outcome, rates_hz={t: r * (1 + 1e-14) for t, r in outcome.rates_hz.items()})

    fleet.optimizer._allocate = noisy  # type: ignore[method-assign]
    writes = rate_writes(fleet)
    result = fleet.optimize()
    assert writes == []
    assert result.rates_hz == before
    assert fleet.rates() == before


class HeldAcks:
    """A host's acknowledgements of its rates held back, as a slow route holds them."""

    def __init__(self, fleet: Fleet, host: str) -> None:
        store = fleet.host(host).params
        self._set = store.set
        self._held: list[tuple[str, ParamValue]] = []

        def hold(name: str, value: ParamValue) -> None:
            if name.endswith("/dbm/frequency/applied_value"):
                self._held.append((name, value))
            else:
                self._set(name, value)

        store.set = hold  # type: ignore[method-assign]

    def release(self) -> None:
        held, self._held = self._held, []
        for name, value in held:
            self._set(name, value)


def r2_down_r1_up(fleet: Fleet) -> None:
    """R1 12.37 -> 16 Hz, R2 16 -> 1.48 Hz: R1's rise needs the room R2's cut frees."""
    fleet.priority(R2, 0.0)
    fleet.priority(R1, 1.0)


def paper_steady(fleet: Fleet) -> None:
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R2, 1.0)
    fleet.optimize()
    assert round(fleet.rates()[R1], 2) == 12.37
    assert fleet.rates()[R2] == 16.0


def test_an_increase_waits_for_the_decrease_it_needs_and_the_heartbeat_does_not() -> None:
    fleet = two_robots()
    paper_steady(fleet)
    acks = HeldAcks(fleet, "r2")
    r2_down_r1_up(fleet)
    writes = rate_writes(fleet)
    first = fleet.optimize()
    second = fleet.optimize()  # the next round: R2 has still said nothing
    assert [(t, round(hz, 2)) for t, hz in writes] == [(R2, 1.48)]
    assert fleet.get(names.ROUND) == second.number == first.number + 1
    assert round(fleet.rates()[R1], 2) == 12.37
    acks.release()
    fleet.optimizer.admit()
    assert writes[1:] == [(R1, 16.0)]
    assert fleet.rates() == {R1: 16.0, R2: pytest.approx(1.48, abs=0.01)}


def six_robots_r6_rising() -> tuple[Fleet, dict[str, float]]:
    """Six 10-kB cameras on 4 Mbit/s, and the rates before r6's priority goes 0.2 -> 1.

    r6 then rises 2.11 -> 5.29 Hz, paid by r3 (8.33 -> 6.43), r4 and r5 (3.78 -> 3.14 each).
    """
    fleet = Fleet(settings=DbmSettings(4.0, 1.0, 1.0))
    topics = [f"/r{k}/camera" for k in range(1, 7)]
    for topic in topics:
        fleet.publisher(topic, size_bytes=10_000)
        fleet.watch(topic)
        fleet.priority(topic, 0.5)
    fleet.priority("/r6/camera", 0.2)
    fleet.optimize()
    return fleet, fleet.rates()


def test_a_rise_paid_by_many_goes_half_way_once_most_of_its_room_is_made(
    caplog: pytest.LogCaptureFixture,
) -> None:
    fleet, before = six_robots_r6_rising()
    acks = [HeldAcks(fleet, "r4"), HeldAcks(fleet, "r5")]  # r3's cut alone: over half the rise
    writes = rate_writes(fleet)
    fleet.priority("/r6/camera", 1.0)
    with caplog.at_level(logging.WARNING, logger="dbml.optimizer"):
        fleet.optimize()
    assert "written by another node" not in caplog.text  # the step is its own write
    rates = fleet.rates()
    wanted = 5.29
    assert round(rates["/r3/camera"], 2) == 6.43
    assert before["/r6/camera"] + (wanted - before["/r6/camera"]) / 2 <= rates["/r6/camera"]
    assert rates["/r6/camera"] < wanted - 0.5
    # What each may send: r4 and r5 at their rates before, as they have not said otherwise.
    committed = rates | {t: before[t] for t in ("/r4/camera", "/r5/camera")}
    assert sum(committed.values()) * 10_000 <= 500_000 * (1 + 1e-9)
    fleet.optimizer.admit()  # nothing new: no second step
    for held in acks:
        held.release()
    with caplog.at_level(logging.WARNING, logger="dbml.optimizer"):
        fleet.optimizer.admit()
    assert "written by another node" not in caplog.text
    assert round(fleet.rates()["/r6/camera"], 2) == wanted
    assert [round(hz, 2) for t, hz in writes if t == "/r6/camera"] == [
        round(rates["/r6/camera"], 2),
        wanted,
    ]


def test_a_rise_waits_whole_while_the_room_made_is_under_half_of_it() -> None:
    fleet, before = six_robots_r6_rising()
    acks = HeldAcks(fleet, "r3")  # r4 and r5's cuts: 12.8 of the 31.8 kB/s it needs
    fleet.priority("/r6/camera", 1.0)
    fleet.optimize()
    assert fleet.rates()["/r6/camera"] == before["/r6/camera"]
    acks.release()
    fleet.optimizer.admit()
    assert round(fleet.rates()["/r6/camera"], 2) == 5.29


def test_a_decrease_not_acknowledged_in_time_counts_as_applied(
    caplog: pytest.LogCaptureFixture,
) -> None:
    fleet = two_robots()
    paper_steady(fleet)
    HeldAcks(fleet, "r2")
    r2_down_r1_up(fleet)
    fleet.optimize()
    fleet.advance(ACK_TIMEOUT_S * 0.9)
    fleet.optimizer.admit()
    assert round(fleet.rates()[R1], 2) == 12.37
    fleet.advance(ACK_TIMEOUT_S * 0.1)
    with caplog.at_level(logging.WARNING, logger="dbml.optimizer"):
        fleet.optimizer.admit()
    assert fleet.rates()[R1] == 16.0
    assert f"no acknowledgement of a decrease from ['{R2}']" in caplog.text


def test_over_a_network_an_increase_waits_until_the_decreased_channels_frames_crossed() -> None:
    """A frame sent just before the decrease applied may be queued behind its acknowledgement."""
    fleet = two_robots()
    fleet.optimizer._transport.delivers_at_once = False  # type: ignore[misc]
    paper_steady(fleet)
    r2_down_r1_up(fleet)
    fleet.optimize()  # R2 acknowledges at once
    drain_s = SIZES[R2] / (11e6 / 8)  # one of its frames at the budget's rate
    fleet.advance(drain_s * 0.98)
    fleet.optimizer.admit()
    assert round(fleet.rates()[R1], 2) == 12.37
    fleet.advance(drain_s * 0.02)
    fleet.optimizer.admit()
    assert fleet.rates()[R1] == 16.0


def test_the_drain_counts_from_when_the_acknowledgement_arrived() -> None:
    """Not from when the optimizer next looked: a round a period later owes no drain."""
    fleet = two_robots()
    fleet.optimizer._transport.delivers_at_once = False  # type: ignore[misc]
    paper_steady(fleet)
    acks = HeldAcks(fleet, "r2")
    r2_down_r1_up(fleet)
    fleet.optimize()
    fleet.advance(0.1)
    acks.release()  # arrives now; the optimizer is not woken (a test steps it)
    fleet.advance(SIZES[R2] / (11e6 / 8) + 0.005)
    fleet.optimizer.admit()
    assert fleet.rates()[R1] == 16.0


def test_a_running_optimizer_pushes_a_waiting_increase_when_the_acknowledgement_comes() -> None:
    fleet = Fleet(settings=DbmSettings(11.0, 1.0, 60.0), clock=time.monotonic, ack_timeout_s=30)
    for topic, size in SIZES.items():
        fleet.publisher(topic, size_bytes=size)
    try:
        fleet.watch(R1)
        fleet.watch(R2)
        fleet.priority(R2, 1.0)
        fleet.optimizer.start()
        wait_for(lambda: fleet.rates()[R2] == 16.0, what="the first allocation")
        acks = HeldAcks(fleet, "r2")
        r2_down_r1_up(fleet)
        wait_for(lambda: fleet.rates()[R2] < 2, what="R2's decrease")
        assert round(fleet.rates()[R1], 2) == 12.37
        acks.release()  # long before the 30-s timeout and the 60-s period
        wait_for(lambda: fleet.rates()[R1] == 16.0, timeout_s=5, what="R1's increase")
    finally:
        fleet.close()


def test_a_round_pushes_each_host_its_channels_and_everyone_the_heartbeat() -> None:
    """A robot's batch holds its own channels' values: its size is the robot's, not the fleet's.

    Status and heartbeat go to everyone.
    """
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    batches: list[tuple[str | None, dict[str, object]]] = []
    store = fleet.optimizer._transport.params
    set_many = store.set_many

    def spy(values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
        batches.append((host, dict(values)))
        set_many(values, host=host)

    store.set_many = spy  # type: ignore[method-assign]
    fleet.optimizer.optimize()
    by_host = dict(batches)
    assert len(batches) == len(by_host) == 3
    assert by_host["r1"] == {
        names.current_value(R1): fleet.rates()[R1],
        names.managed(R1): True,
    }
    assert by_host["r2"] == {
        names.current_value(R2): fleet.rates()[R2],
        names.managed(R2): True,
    }
    assert set(by_host[None]) == {names.STATUS, names.STATUS_MESSAGE, names.ROUND}
    writes = rate_writes(fleet)
    for _ in range(3):  # nothing changes: only the heartbeat goes out
        fleet.optimizer.optimize()
    assert batches[3:] == [(None, {names.ROUND: k}) for k in (2, 3, 4)]
    assert writes == []


def test_a_restarted_publisher_hears_its_unchanged_rate_again() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.optimizer.optimize()
    allocated = fleet.rates()[R1]
    assert allocated < 16
    fleet.publishers[R1].close()
    restarted = ManagedPublisher(
        MemoryTransport(fleet.network, host="r1"), R1, min_rate_hz=1, max_rate_hz=16
    )
    restarted.publish(b"\0" * SIZES[R1])
    assert restarted.current_rate_hz() == 1.0  # a new channel starts at its minimum
    fleet.optimizer.optimize()
    assert restarted.current_rate_hz() == allocated


def test_a_forged_publisher_on_the_operators_host_changes_nothing() -> None:
    """A token saying "/r1/camera is published on your host" beside the real one on r1.

    It once switched the operator to the full-rate stream and unmanaged the channel (1.59 x B).
    """
    fleet = two_robots(mbit=5)
    subscriber = fleet.watch(R1)
    fleet.watch(R2)
    fleet.optimizer.optimize()
    allocated = fleet.rates()
    forger = MemoryTransport(fleet.network, host="operator")
    forger.graph.announce(Role.PUBLISHER, R1, Variant.FULL)
    fleet.optimizer.optimize()
    assert subscriber.variant is Variant.OPTIMIZED
    assert fleet.optimizer.last_round is not None
    assert {c.topic for c in fleet.optimizer.last_round.channels if c.managed} == {R1, R2}
    assert fleet.rates() == allocated


def test_a_burst_of_triggered_rounds_writes_the_heartbeat_once_a_half_period() -> None:
    """The heartbeat wakes every robot: the rounds a burst of changes brings do not all carry it.

    A periodic round always does; the publishers' fail-safe waits three periods.
    """
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    beats: list[ParamValue] = []
    fleet.host("r1").params.watch(lambda n, v: beats.append(v) if n == names.ROUND else None)
    fleet.priority(R1, 1.0)
    optimizer = fleet.optimizer
    optimizer._round()  # the first is periodic
    assert len(beats) == 1
    writes = rate_writes(fleet)
    for step in range(4):  # a change every 0.1 s: a round each, 0.1-0.4 s after the heartbeat
        fleet.advance(0.1)
        fleet.priority(R2, 0.2 * (step + 1))
        optimizer._round()
    assert len(writes) == 8  # each change was pushed at once, both robots' rates
    assert len(beats) == 1
    fleet.advance(0.15)  # past half a period since the heartbeat
    fleet.priority(R2, 1.0)
    optimizer._round()
    assert len(beats) == 2
    fleet.advance(0.3)  # 0.3 s since it
    fleet.priority(R2, 0.1)
    optimizer._round()
    assert len(beats) == 2
    fleet.advance(1.0)  # a period since the last round: due, whatever the last heartbeat
    optimizer._round()
    assert len(beats) == 3
    fleet.close()


def test_a_publisher_seen_without_its_parameters_is_asked_again_once_a_period() -> None:
    """Its bounds' writes went out before a route to the optimizer existed: ask its process."""
    network = MemoryNetwork()
    clock = ManualClock()
    transport = MemoryTransport(network, host="base", clock=clock)
    asked: list[str] = []
    transport.refresh = lambda entry: asked.append(entry.topic)  # type: ignore[method-assign]
    optimizer = OptimizerNode(transport, settings=DbmSettings(11.0, 1.0, 1.0))
    MemoryTransport(network, host="r1").graph.announce(Role.PUBLISHER, R1, Variant.FULL)
    optimizer.optimize()
    assert asked == []  # just seen: its writes may be on the way
    clock.advance(1.0)
    optimizer.optimize()
    clock.advance(0.5)
    optimizer.optimize()
    assert asked == [R1]  # once a period, not once a round
    MemoryTransport(network, host="r1").params.set(names.min_rate(R1), 1.0)
    MemoryTransport(network, host="r1").params.set(names.max_rate(R1), 16.0)
    MemoryTransport(network, host="r1").params.set(names.size(R1), 84_000)
    clock.advance(5.0)
    optimizer.optimize()
    assert asked == [R1]  # complete now: nothing to ask


def test_the_channels_tracked_are_bounded_the_known_ones_stay_and_a_flood_is_said_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Publishers announced by any peer cannot make the optimizer track (remember) more."""
    fleet = two_robots()
    fleet.watch(R1)
    optimizer = fleet.optimizer
    assert R1 in optimizer.optimize().rates_hz  # tracked before the flood
    peer = MemoryTransport(fleet.network, host="peer")
    over = 50
    # Sorted ahead of the robots' topics: only what was tracked already keeps its place.
    flood = [
        peer.graph.announce(Role.PUBLISHER, f"/a/{i:05d}", Variant.FULL)
        for i in range(MAX_CHANNELS + over)
    ]
    with caplog.at_level(logging.WARNING, logger="dbml.optimizer"):
        for _ in range(3):
            result = optimizer.optimize()
            assert len(optimizer._tracked) == MAX_CHANNELS
            assert {c.topic for c in result.channels} == {R1, R2}  # the robots' stay
            assert R1 in result.rates_hz
            assert f"{over + 2} channels ignored: more than {MAX_CHANNELS}" in result.message
            assert len(optimizer._pushed) <= MAX_CHANNELS
        for handle in flood[: over + 2]:
            handle.close()
        result = optimizer.optimize()
        assert "channels ignored" not in result.message
        # Hovering at the bound is one flood: told again only once half the bound is free.
        flood.append(peer.graph.announce(Role.PUBLISHER, "/a/late", Variant.FULL))
        assert "; 1 channels ignored" in optimizer.optimize().message
        left = flood[over + 2 :]
        closed = len(left) + 2 - (MAX_CHANNELS // 2 + 1)  # leaves one more than half the bound
        for handle in left[:closed]:
            handle.close()
        optimizer.optimize()
        assert len(optimizer._tracked) == MAX_CHANNELS // 2 + 1
        told = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(told) == 1  # the flood is not over yet
        left[closed].close()  # half the bound: the flood is over
        optimizer.optimize()
    # What the flood says (a run's earlier logging setup may let the rounds' INFO lines in too).
    messages = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert messages == [
        f"channels tracked: {MAX_CHANNELS} held, the most kept; refusing new ones "
        "(told once until half of them are gone)",
        f"channels tracked: room again; {over + 3} refused meanwhile",
    ]


# -- the round report: what the view and the monitor show --------------------------------------


def test_a_round_reports_table2_with_the_paper_s_floors() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R2, 10 / 17)  # Table 2's step 1: tc 20 s and 10 s
    report = fleet.optimizer.optimize().report()
    assert report.status is Status.OPTIMAL
    assert report.strategy is Strategy.PAPER
    assert report.budget_mbit == 11.0
    assert report.round == fleet.operator.params.get(names.ROUND)
    r1, r2 = report.channels
    assert (r1.topic, r2.topic) == (R1, R2)
    # Eq. 2: only R2 has a priority, so it weighs everything; eq. 4: its floor is its maximum.
    assert (r1.normalized_priority, r2.normalized_priority) == (0.0, 1.0)
    assert (r1.floor_hz, r2.floor_hz) == (1.0, 16.0)
    assert (round(r1.rate_hz or 0, 2), r2.rate_hz) == (12.37, 16.0)
    assert r1.share == pytest.approx((r1.rate_hz or 0) * 84_000 / 1_375_000)
    assert (r1.size_bytes, r1.min_hz, r1.max_hz, r2.priority) == (84_000, 1.0, 16.0, 10 / 17)
    assert report.allocated_mbit == pytest.approx(11.0, abs=1e-6)


def test_a_round_reports_an_unmanaged_channel_at_its_maximum_without_floor_or_share() -> None:
    fleet = two_robots()
    fleet.watch(R2)
    report = fleet.optimizer.optimize().report()
    r1 = report.channel(R1)
    assert r1 is not None
    assert (r1.managed, r1.rate_hz) == (False, 16.0)
    assert (r1.floor_hz, r1.normalized_priority, r1.share) == (None, None, None)
    assert report.allocated_mbit == pytest.approx(16 * 21_000 * 8 / 1e6)  # R2's alone


def test_a_round_without_a_budget_reports_no_floors_and_no_shares() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    fleet.operator.params.set(names.BANDWIDTH, None)
    report = fleet.optimizer.optimize().report()
    assert report.status is Status.INFEASIBLE
    assert report.budget_mbit is None
    assert all(c.floor_hz is None and c.share is None for c in report.channels)


def test_a_round_reports_what_its_links_allowed() -> None:
    """A rate an uplink held down: no allocation of the parameter values alone would show it."""
    fleet = two_robots(strategy=Strategy.LP, links=(LinkSpec("uplink-r1", 2.0, (R1,)),))
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R1, 1.0)
    report = fleet.optimizer.optimize().report()
    r1 = report.channel(R1)
    assert r1 is not None
    assert (r1.rate_hz or 0) * 84_000 * 8 / 1e6 == pytest.approx(2.0)  # not its floor, 16 Hz
    assert r1.floor_hz == 16.0
    assert report.status is Status.INFEASIBLE
    assert "uplink-r1" in report.message


def test_rounds_are_published_to_whoever_follows_them() -> None:
    fleet = two_robots()
    fleet.watch(R1)
    viewer = MemoryTransport(fleet.network, host="viewer")
    rounds = RoundFollower(viewer)
    assert rounds.latest() is None
    first = fleet.optimizer.optimize().report()
    assert rounds.latest() == first
    # A peer's malformed report is dropped where it enters: the optimizer's stands.
    rogue = viewer.declare_publisher(ROUND_TOPIC)
    rogue.put(b'{"round": -1}')
    rogue.put(b"\xff")
    assert rounds.latest() == first
    second = fleet.optimizer.optimize().report()
    assert rounds.latest() == second
    assert second.round == first.round + 1
    rounds.close()


def test_a_forged_sent_rate_is_refused_or_only_reported_never_allocated() -> None:
    """``frequency/sent_value`` from the network: out of range refused, in range only shown."""
    fleet = two_robots()
    fleet.watch(R1)
    fleet.watch(R2)
    fleet.priority(R2, 10 / 17)
    before = fleet.optimizer.optimize()
    rates = fleet.rates()
    for bad in (-1.0, 1e12, "fast", float("nan"), True):
        fleet.network.forge({names.sent(R1): bad}, writer="rogue")
        result = fleet.optimizer.optimize()
        channel = result.report().channel(R1)
        assert channel is not None
        assert channel.sent_hz is None, bad  # never taken in
    fleet.network.forge({names.sent(R1): 0.0, names.sent(R2): 1000.0}, writer="rogue")
    result = fleet.optimizer.optimize()
    assert {c.topic: c.sent_hz for c in result.report().channels} == {R1: 0.0, R2: 1000.0}
    assert fleet.rates() == rates  # the allocation reads no sent rate
    assert result.status is before.status


def test_a_first_rate_goes_whole_and_not_in_steps() -> None:
    """A channel from zero waits for its whole first rate: at a fleet's start all are first."""
    fleet, _ = six_robots_r6_rising()
    HeldAcks(fleet, "r4")
    HeldAcks(fleet, "r5")  # r3's cut alone would cover half of the newcomer's rate
    writes = rate_writes(fleet)
    fleet.publisher("/r7/camera", size_bytes=10_000)
    fleet.watch("/r7/camera")
    fleet.priority("/r7/camera", 1.0)
    fleet.optimize()
    assert [t for t, _ in writes if t == "/r7/camera"] == []
