"""A fleet of 20 robots x 4 channels joining at once, on the memory transport.

Traced at 80 x 4 over zenoh: some robots' first allocation never arrived (a route not yet up),
and nothing pushed it again; their publishers, hearing the optimizer's rounds but no rate, took
the wait for a lost optimizer and went to their fail-safe. Here the first push to every eighth
channel is lost on the way: every channel must still be allocated, and none may ever be in
fail-safe while the optimizer's rounds arrive. The rule does not depend on the fleet's size:
80 x 4 (53 s here, every value reaching every host of the in-memory network) is
``bench/fleet.py``'s, over zenoh.
"""

from __future__ import annotations

from collections.abc import Callable

from dbml.core import DbmSettings, Strategy
from dbml.protocol import names
from dbml.runtime import ManagedPublisher, ManagedSubscriber, OptimizerNode
from dbml.transports import Handle, ManualClock, MemoryNetwork, MemoryTransport, ParamValue

ROBOTS, CHANNELS = 20, 4
SIZES_BYTES = (84_000, 21_000, 8_000, 1_000)
MIN_HZ, MAX_HZ = 1.0, 16.0
PERIOD_S = 1.0
ROUNDS = 8
LOSSY_EVERY = 8
"""Every eighth channel loses the first push of its rate."""


def lose_first_push(transport: MemoryTransport, topic: str) -> list[ParamValue]:
    """Make ``transport``'s watchers miss the first write of ``topic``'s allocation."""
    lost: list[ParamValue] = []
    params = transport.params
    watch = params.watch

    def lossy_watch(callback: Callable[[str, ParamValue], None]) -> Handle:
        def deliver(name: str, value: ParamValue) -> None:
            if name == names.current_value(topic) and not lost:
                lost.append(value)
                return
            callback(name, value)

        return watch(deliver)

    params.watch = lossy_watch  # type: ignore[method-assign]
    return lost


def test_every_channel_of_a_fleet_joining_at_once_is_allocated_and_none_fails_safe() -> None:
    network, clock = MemoryNetwork(), ManualClock(1000.0)
    topics = [f"/r{r}/ch{c}" for r in range(1, ROBOTS + 1) for c in range(CHANNELS)]
    sizes = {t: SIZES_BYTES[i % CHANNELS] for i, t in enumerate(topics)}
    budget_mbit = 0.6 * sum(MAX_HZ * s for s in sizes.values()) * 8 / 1e6
    operator = MemoryTransport(network, host="operator", clock=clock)
    for topic in topics:
        ManagedSubscriber(operator, topic, lambda _sample: None)
    optimizer = OptimizerNode(
        MemoryTransport(network, host="base", clock=clock),
        settings=DbmSettings(budget_mbit, 1.0, PERIOD_S, Strategy.PAPER),
    )
    publishers: dict[str, ManagedPublisher] = {}
    losses: dict[str, list[ParamValue]] = {}
    for r in range(1, ROBOTS + 1):
        robot = MemoryTransport(network, host=f"r{r}", clock=clock)
        for c in range(CHANNELS):
            topic = f"/r{r}/ch{c}"
            if topics.index(topic) % LOSSY_EVERY == 0:
                losses[topic] = lose_first_push(robot, topic)
            publishers[topic] = ManagedPublisher(
                robot, topic, min_rate_hz=MIN_HZ, max_rate_hz=MAX_HZ
            )
    for topic, publisher in publishers.items():  # all at once: every size known together
        publisher.publish(bytes(sizes[topic]))
    for _ in range(ROUNDS):
        optimizer.optimize()
        for topic, publisher in publishers.items():
            publisher.publish(bytes(sizes[topic]))
            assert not publisher.failsafe, topic
        clock.advance(PERIOD_S)
    rates = optimizer.last_round.rates_hz if optimizer.last_round else {}
    assert set(rates) == set(topics)
    assert all(lost for lost in losses.values())  # each lossy channel did lose a push
    unallocated = [t for t, p in publishers.items() if p.current_rate_hz() != rates[t]]
    assert unallocated == []
    assert all(operator.params.get(names.applied(t)) == rates[t] for t in topics)
    optimizer.stop()
