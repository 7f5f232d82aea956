from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest

from dbml.core.errors import SpecError
from dbml.protocol import names
from dbml.runtime import ManagedPublisher, MessageMeta
from dbml.runtime.qos import (
    HIGH_PRIORITY,
    SMALL_MESSAGE_BYTES,
    URGENT_PRIORITY,
    QosSwitch,
    TransportQos,
    channel_qos,
    explicit_qos,
    map_priority,
    parse_transport_priority,
)
from dbml.transports import ManualClock, MemoryNetwork, MemoryTransport, Sample, Variant
from dbml.transports.base import Publisher, TransportPriority

TOPIC = "/r1/alarm"
URGENT_SMALL = TransportQos(TransportPriority.INTERACTIVE_LOW, express=True)


@pytest.mark.parametrize(
    ("priority", "size_bytes", "expected"),
    [
        (1.0, 1_000, TransportQos(TransportPriority.INTERACTIVE_LOW, express=True)),
        (URGENT_PRIORITY, SMALL_MESSAGE_BYTES, URGENT_SMALL),
        (1.0, SMALL_MESSAGE_BYTES + 1, TransportQos(TransportPriority.DATA_HIGH, express=False)),
        (1.0, None, TransportQos(TransportPriority.DATA_HIGH, express=False)),
        (HIGH_PRIORITY, 84_000, TransportQos(TransportPriority.DATA_HIGH, express=False)),
        (HIGH_PRIORITY, 64, TransportQos(TransportPriority.DATA_HIGH, express=False)),
        (0.0, 84_000, TransportQos(TransportPriority.DATA, express=False)),
        (0.1, 64, TransportQos(TransportPriority.DATA, express=False)),  # batched: throughput
    ],
)
def test_priority_and_size_map_to_a_class(
    priority: float, size_bytes: int | None, expected: TransportQos
) -> None:
    assert map_priority(priority, size_bytes) == expected


def test_mapping_never_reaches_the_control_classes() -> None:
    reserved = {TransportPriority.REAL_TIME, TransportPriority.INTERACTIVE_HIGH}
    for priority in (0.0, 0.3, 0.8, 1.0):
        for size in (None, 1, 4_096, 84_000):
            assert map_priority(priority, size).priority not in reserved


@pytest.mark.parametrize("text", ["real_time", "REAL-TIME", " real_time "])
def test_transport_priority_names_parse(text: str) -> None:
    assert parse_transport_priority(text) is TransportPriority.REAL_TIME


def test_a_bad_transport_priority_is_named() -> None:
    with pytest.raises(SpecError, match=r"transport_priority='urgent' is not one of: real_time"):
        parse_transport_priority("urgent")


class Recording(MemoryTransport):
    """A memory transport that remembers each publisher's class and when it was closed."""

    has_priorities = True  # as zenoh's: a class is declared with the publisher

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.declared: list[tuple[Variant, TransportPriority | None, bool]] = []
        self.closed: list[int] = []

    def declare_publisher(
        self,
        topic: str,
        variant: Variant = Variant.FULL,
        *,
        priority: TransportPriority | None = None,
        express: bool = False,
    ) -> Any:
        inner = super().declare_publisher(topic, variant, priority=priority, express=express)
        self.declared.append((variant, priority, express))
        index = len(self.declared) - 1
        closed = self.closed

        class Tracked:
            topic = inner.topic
            has_subscribers = property(lambda _self: inner.has_subscribers)

            def put(self, payload: bytes, attachment: bytes | None = None) -> None:
                inner.put(payload, attachment=attachment)

            def close(self) -> None:
                closed.append(index)

        tracked: Publisher = Tracked()
        return tracked


def optimized(transport: Recording) -> list[tuple[TransportPriority | None, bool]]:
    return [(p, e) for v, p, e in transport.declared if v is Variant.OPTIMIZED]


def allocated(network: MemoryNetwork, clock: ManualClock, topic: str, rate_hz: float) -> None:
    MemoryTransport(network, host="opt", clock=clock).params.set(
        names.current_value(topic), rate_hz
    )


def test_first_message_size_moves_an_urgent_channel_to_the_interactive_class() -> None:
    clock, network = ManualClock(100.0), MemoryNetwork()
    transport = Recording(network, host="r1", clock=clock)
    publisher = ManagedPublisher(transport, TOPIC, min_rate_hz=20, max_rate_hz=20, priority=1.0)
    assert optimized(transport) == [(TransportPriority.DATA_HIGH, False)]  # size unknown: large
    publisher.publish(bytes(1_000))
    assert optimized(transport)[-1] == (TransportPriority.INTERACTIVE_LOW, True)
    assert publisher.transport_qos == TransportQos(TransportPriority.INTERACTIVE_LOW, True)
    assert transport.closed == []  # the old one is retired, not closed under a racing put
    publisher.close()
    assert sorted(transport.closed) == [0, 1, 2]  # full, first and second optimized


def test_priority_change_redeclares_and_keeps_the_numbering() -> None:
    clock, network = ManualClock(100.0), MemoryNetwork()
    transport = Recording(network, host="r1", clock=clock)
    received: list[Sample] = []
    MemoryTransport(network, host="op", clock=clock).subscribe(
        TOPIC, received.append, Variant.OPTIMIZED
    )
    publisher = ManagedPublisher(transport, TOPIC, min_rate_hz=1, max_rate_hz=20, priority=0.0)
    allocated(network, clock, TOPIC, 20.0)
    assert publisher.publish(bytes(100_000))
    assert publisher.transport_qos == TransportQos(TransportPriority.DATA, express=False)
    declared = len(transport.declared)
    transport.params.set(names.priority(TOPIC), 0.5)  # on the middleware's thread: no declare
    assert len(transport.declared) == declared
    clock.advance(1.0)
    assert publisher.publish(bytes(100_000))  # the publishing thread re-declares, then sends
    assert publisher.transport_qos == TransportQos(TransportPriority.DATA_HIGH, express=False)
    assert [MessageMeta.decode(s.attachment).seq for s in received] == [1, 2]
    before = len(transport.declared)
    transport.params.set(names.priority(TOPIC), 0.6)  # same class: nothing re-declared
    assert len(transport.declared) == before
    assert not publisher.update_transport_class()
    publisher.close()


def test_explicit_class_overrides_the_priority() -> None:
    clock, network = ManualClock(100.0), MemoryNetwork()
    transport = Recording(network, host="r1", clock=clock)
    publisher = ManagedPublisher(
        transport,
        TOPIC,
        min_rate_hz=1,
        max_rate_hz=20,
        priority=0.0,
        transport_priority=TransportPriority.REAL_TIME,
    )
    publisher.publish(bytes(64))
    transport.params.set(names.priority(TOPIC), 1.0)
    publisher.publish(bytes(64))
    assert publisher.transport_qos == TransportQos(TransportPriority.REAL_TIME, express=True)
    publisher.close()


def test_without_mapping_the_publisher_keeps_the_default_class() -> None:
    clock, network = ManualClock(100.0), MemoryNetwork()
    transport = Recording(network, host="r1", clock=clock)
    publisher = ManagedPublisher(
        transport, TOPIC, min_rate_hz=1, max_rate_hz=20, priority=1.0, map_transport_priority=False
    )
    publisher.publish(bytes(64))
    assert optimized(transport) == [(None, False)]
    assert publisher.transport_qos is None
    publisher.close()


def test_a_transport_without_classes_never_redeclares() -> None:
    """ROS 1 and memory ignore classes: a priority event must not re-declare a publisher."""
    clock, network = ManualClock(100.0), MemoryNetwork()
    transport = Recording(network, host="r1", clock=clock)
    transport.has_priorities = False
    publisher = ManagedPublisher(transport, TOPIC, min_rate_hz=1, max_rate_hz=20, priority=0.0)
    publisher.publish(bytes(64))
    transport.params.set(names.priority(TOPIC), 1.0)
    publisher.publish(bytes(64))
    assert optimized(transport) == [(None, False)]
    publisher.close()


@pytest.mark.parametrize(
    ("priority", "size_bytes", "express"),
    [
        (TransportPriority.REAL_TIME, 64, True),
        (TransportPriority.INTERACTIVE_LOW, SMALL_MESSAGE_BYTES, True),
        (TransportPriority.REAL_TIME, SMALL_MESSAGE_BYTES + 1, False),
        (TransportPriority.REAL_TIME, None, False),
        (TransportPriority.DATA, 64, False),
        (TransportPriority.BACKGROUND, 64, False),
    ],
)
def test_an_explicit_class_goes_express_only_for_latency(
    priority: TransportPriority, size_bytes: int | None, express: bool
) -> None:
    assert explicit_qos(priority, size_bytes) == TransportQos(priority, express=express)


def test_a_channels_class_is_the_explicit_one_if_given() -> None:
    assert channel_qos(1.0, 64) == URGENT_SMALL
    assert channel_qos(1.0, 64, TransportPriority.DATA) == TransportQos(
        TransportPriority.DATA, express=False
    )
    assert channel_qos(0.0, 64, TransportPriority.REAL_TIME) == TransportQos(
        TransportPriority.REAL_TIME, express=True
    )


class FakePublisher:
    """A publisher that only records its class and whether it was closed."""

    topic = TOPIC
    has_subscribers = False

    def __init__(self, qos: TransportQos | None) -> None:
        self.qos = qos
        self.closed = False

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        raise AssertionError("nothing is sent here")

    def close(self) -> None:
        self.closed = True


DATA = TransportQos(TransportPriority.DATA, express=False)
DATA_HIGH = TransportQos(TransportPriority.DATA_HIGH, express=False)


class Declarations:
    """``declare`` for a ``QosSwitch``: every publisher it made, in order."""

    def __init__(self) -> None:
        self.made: list[FakePublisher] = []
        self.during: Callable[[], None] | None = None
        """Run inside the next declaration, as a racing thread would."""

    def __call__(self, qos: TransportQos | None) -> Publisher:
        during, self.during = self.during, None
        if during is not None:
            during()
        publisher = FakePublisher(qos)
        self.made.append(publisher)
        return publisher


def test_the_switch_declares_only_for_another_class() -> None:
    declare = Declarations()
    switch = QosSwitch(declare, DATA)
    assert [p.qos for p in declare.made] == [DATA]
    assert switch.publisher is declare.made[0]
    assert not switch.switch(DATA)
    assert len(declare.made) == 1
    assert switch.switch(DATA_HIGH)
    assert switch.qos == DATA_HIGH
    assert switch.publisher is declare.made[1]


def test_a_replaced_publisher_is_retired_then_closed() -> None:
    declare = Declarations()
    switch = QosSwitch(declare, DATA)
    first = declare.made[0]
    switch.switch(DATA_HIGH)
    assert not first.closed  # a put that read it just before the swap may still use it
    switch.switch(URGENT_SMALL)
    assert first.closed
    second, third = declare.made[1:]
    assert not second.closed
    switch.close()
    assert second.closed
    assert third.closed


def test_close_retired_closes_only_the_retired_one() -> None:
    declare = Declarations()
    switch = QosSwitch(declare, None)
    switch.switch(DATA)
    switch.close_retired()
    assert [p.closed for p in declare.made] == [True, False]


def test_a_newer_change_wins_and_no_lock_is_held_while_declaring() -> None:
    declare = Declarations()
    switch = QosSwitch(declare, DATA)
    finished: list[bool] = []

    def racing_change() -> None:  # another thread, while the first declaration is under way
        thread = threading.Thread(target=lambda: finished.append(switch.switch(URGENT_SMALL)))
        thread.start()
        thread.join(timeout=5.0)
        assert not thread.is_alive(), "the switch held its lock across a declaration"

    declare.during = racing_change
    assert not switch.switch(DATA_HIGH)  # overtaken: its publisher is closed again
    assert finished == [True]
    assert switch.qos == URGENT_SMALL
    high = next(p for p in declare.made if p.qos == DATA_HIGH)
    assert high.closed
    assert switch.publisher.qos == URGENT_SMALL  # type: ignore[attr-defined]


def test_back_to_the_class_in_force_while_another_is_declared_keeps_it() -> None:
    declare = Declarations()
    switch = QosSwitch(declare, DATA)
    back: list[bool] = []
    declare.during = lambda: back.append(switch.switch(DATA))
    assert not switch.switch(DATA_HIGH)
    assert back == [False]
    assert switch.qos == DATA
    assert switch.publisher is declare.made[0]
    assert declare.made[1].closed
