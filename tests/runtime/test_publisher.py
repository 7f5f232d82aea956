import logging
from typing import Any

import pytest

from dbml.core.errors import SpecError
from dbml.protocol import names
from dbml.runtime import ManagedPublisher, MessageMeta, ParamView
from dbml.transports import (
    ManualClock,
    MemoryNetwork,
    MemoryTransport,
    ParamStore,
    Sample,
    Variant,
)
from dbml.transports.base import Handle


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(100.0)


@pytest.fixture
def network() -> MemoryNetwork:
    return MemoryNetwork()


def robot(network: MemoryNetwork, clock: ManualClock, **kwargs: float) -> ManagedPublisher:
    transport = MemoryTransport(network, host="r1", clock=clock)
    options: dict[str, Any] = {"min_rate_hz": 1.0, "max_rate_hz": 16.0}
    options.update(kwargs)
    return ManagedPublisher(transport, "/r1/camera", **options)


def remote_reader(
    network: MemoryNetwork, clock: ManualClock
) -> tuple[MemoryTransport, list[Sample]]:
    """An operator's transport and what it receives of ``/r1/camera/optimized``."""
    operator = MemoryTransport(network, host="op", clock=clock)
    remote: list[Sample] = []
    operator.subscribe("/r1/camera", remote.append, Variant.OPTIMIZED)
    return operator, remote


def test_declares_its_parameters_and_starts_at_minimum(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock, priority=0.25)
    params = MemoryTransport(network, host="op").params
    assert params.get(names.min_rate("/r1/camera")) == 1.0
    assert params.get(names.max_rate("/r1/camera")) == 16.0
    assert params.get(names.priority("/r1/camera")) == 0.25
    assert publisher.current_rate_hz() == 1.0


def test_without_a_priority_declares_none(network: MemoryNetwork, clock: ManualClock) -> None:
    robot(network, clock)
    assert MemoryTransport(network, host="op").params.get(names.priority("/r1/camera")) is None


def test_keeps_a_priority_someone_already_set(network: MemoryNetwork, clock: ManualClock) -> None:
    MemoryTransport(network, host="cli").params.set(names.priority("/r1/camera"), 0.9)
    robot(network, clock)
    assert MemoryTransport(network, host="op").params.get(names.priority("/r1/camera")) == 0.9


def test_rejects_bad_bounds(network: MemoryNetwork, clock: ManualClock) -> None:
    with pytest.raises(SpecError, match=r"frequency.min=30.0 exceeds frequency.max=16.0"):
        robot(network, clock, min_rate_hz=30.0)


def test_applies_and_acknowledges_pushed_rates(network: MemoryNetwork, clock: ManualClock) -> None:
    publisher = robot(network, clock)
    optimizer = MemoryTransport(network, host="op", clock=clock)
    optimizer.params.set(names.current_value("/r1/camera"), 12.5)
    assert publisher.current_rate_hz() == 12.5
    assert optimizer.params.get(names.applied("/r1/camera")) == 12.5


def test_throttles_the_optimized_copy_and_numbers_each_variant(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock)
    operator, remote = remote_reader(network, clock)
    local: list[Sample] = []
    MemoryTransport(network, host="r1", clock=clock).subscribe("/r1/camera", local.append)
    for i in range(160):  # 10 s of a 16 Hz sensor, with the optimizer's push every second
        if i % 16 == 0:
            operator.params.set(names.current_value("/r1/camera"), 4.0)
        publisher.publish(b"x" * 1000)
        clock.advance(1 / 16)
    assert len(local) == 160
    assert abs(len(remote) - 40) <= 1
    assert [MessageMeta.decode(s.attachment).seq for s in remote] == list(range(1, len(remote) + 1))
    assert [MessageMeta.decode(s.attachment).seq for s in local] == list(range(1, 161))
    assert MessageMeta.decode(remote[-1].attachment).rate_hz == 4.0


def test_no_full_rate_copy_without_a_local_reader(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock)
    MemoryTransport(network, host="op").params.set(names.current_value("/r1/camera"), 5.0)
    assert publisher._full is not None
    assert not publisher._full.has_subscribers  # nothing would be sent on [topic]
    assert publisher.publish(b"x")


def test_size_is_measured_and_updated_on_material_change(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock)
    observer = MemoryTransport(network, host="op", clock=clock)
    writes: list[object] = []
    observer.params.watch(lambda n, v: writes.append(v) if n == names.size("/r1/camera") else None)
    assert observer.params.get(names.size("/r1/camera")) is None  # unknown before the first message
    publisher.publish(b"x" * 84_000)
    publisher.publish(b"x" * 88_000)  # +4.8 %: not worth a re-optimisation
    publisher.publish(b"x" * 100_000)  # +19 %
    assert writes == [84_000, 100_000]


def test_failsafe_after_three_silent_periods_and_recovery(
    network: MemoryNetwork, clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    publisher = robot(network, clock)
    optimizer = MemoryTransport(network, host="op", clock=clock)
    optimizer.params.set(names.PERIOD, 0.5)
    optimizer.params.set(names.current_value("/r1/camera"), 12.0)
    clock.advance(1.4)
    assert publisher.current_rate_hz() == 12.0
    assert not publisher.failsafe
    with caplog.at_level(logging.WARNING, logger="dbml.publisher"):
        clock.advance(0.2)  # 1.6 s > 3 periods of 0.5 s
        assert publisher.current_rate_hz() == 1.0
        assert publisher.failsafe
        assert "fail-safe" in caplog.text
        optimizer.params.set(names.current_value("/r1/camera"), 9.0)  # an optimizer is back
        assert publisher.current_rate_hz() == 9.0
        assert not publisher.failsafe
        assert "allocation heard again" in caplog.text


def test_without_any_allocation_it_says_so_after_three_periods(
    network: MemoryNetwork, clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    publisher = robot(network, clock)
    clock.advance(2.9)
    assert not publisher.failsafe
    with caplog.at_level(logging.WARNING, logger="dbml.publisher"):
        clock.advance(0.2)  # 3.1 s > 3 periods of the default 1 s
        assert publisher.current_rate_hz() == 1.0
        assert publisher.failsafe
    assert "fail-safe: minimum 1.000 Hz" in caplog.text


def test_the_optimizers_heartbeat_keeps_an_unchanged_allocation(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """An unchanged rate is not pushed again: the round counter alone says it still stands."""
    publisher = robot(network, clock)
    optimizer = MemoryTransport(network, host="op", clock=clock)
    optimizer.params.set(names.current_value("/r1/camera"), 12.0)
    for round_ in range(1, 11):  # ten periods of 1 s, the rate never rewritten
        clock.advance(1.0)
        optimizer.params.set(names.ROUND, round_)
    assert publisher.current_rate_hz() == 12.0
    assert not publisher.failsafe
    clock.advance(3.1)  # the optimizer gone: no heartbeat
    assert publisher.current_rate_hz() == 1.0
    optimizer.params.set(names.ROUND, 11)  # back, its allocation unchanged
    assert publisher.current_rate_hz() == 12.0


def test_a_heartbeat_alone_allocates_nothing_but_the_wait_goes_on(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock)
    optimizer = MemoryTransport(network, host="op", clock=clock)
    _operator, remote = remote_reader(network, clock)
    for round_ in range(1, 10):
        clock.advance(1.0)
        optimizer.params.set(names.ROUND, round_)
        publisher.publish(b"x")
    assert publisher.current_rate_hz() == 1.0  # still waiting for a first allocation
    assert not publisher.failsafe  # the optimizer runs: a wait, not a lost optimizer
    assert remote == []  # and nothing unbudgeted crossed the network meanwhile
    clock.advance(3.5)  # then silence: the fail-safe
    assert publisher.failsafe


def test_a_pushed_rate_above_the_maximum_is_clamped(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock)
    operator, remote = remote_reader(network, clock)
    operator.params.set(names.current_value("/r1/camera"), 1e6)
    for _ in range(1000):  # one second of a 1 kHz source
        publisher.publish(b"x")
        clock.advance(0.001)
    assert publisher.current_rate_hz() == 16.0
    assert len(remote) <= 16 + 1


def test_a_new_channel_sends_nothing_remote_until_allocated(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """Frames nobody allocated would break the budget on the wire while the others run full."""
    publisher = robot(network, clock)
    operator, remote = remote_reader(network, clock)
    for _ in range(32):  # two seconds of a 16 Hz sensor, no allocation yet
        assert not publisher.publish(b"x" * 1000)
        clock.advance(1 / 16)
    assert remote == []
    assert operator.params.get(names.size("/r1/camera")) == 1000  # but its size is known
    operator.params.set(names.current_value("/r1/camera"), 4.0)
    assert publisher.publish(b"x" * 1000)
    assert len(remote) == 1


def test_without_any_optimizer_a_new_channel_runs_at_its_minimum_after_the_deadline(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    publisher = robot(network, clock)
    sent = []
    for i in range(16 * 6):  # six seconds of a 16 Hz sensor
        if publisher.publish(b"x"):
            sent.append(i / 16)
        clock.advance(1 / 16)
    assert sent[0] >= 3.0  # silent for three periods, waiting for an allocation
    assert len(sent) == pytest.approx(3, abs=1)  # then 1 Hz


def test_a_publisher_hears_its_own_channel_not_every_write(
    network: MemoryNetwork, clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A process with many publishers must not have each of them filter every write."""

    def every_write(_view: ParamView, _callback: object) -> Handle:
        raise AssertionError("a publisher watched every parameter write")

    monkeypatch.setattr(ParamView, "watch", every_write)
    publisher = robot(network, clock)
    optimizer = MemoryTransport(network, host="op", clock=clock)
    optimizer.params.set(names.current_value("/r1/camera"), 4.0)
    optimizer.params.set(names.current_value("/r2/camera"), 9.0)
    assert publisher.current_rate_hz() == 4.0
    clock.advance(2.0)
    optimizer.params.set(names.ROUND, 1)  # the heartbeat, a global name, still reaches it
    clock.advance(2.0)
    assert publisher.current_rate_hz() == 4.0


def sent_rates(
    network: MemoryNetwork, clock: ManualClock
) -> tuple[ManagedPublisher, ParamStore, list[float]]:
    """A robot's publisher at 10 Hz, the optimizer's store, and every sent rate it writes."""
    publisher = robot(network, clock)
    optimizer = MemoryTransport(network, host="base", clock=clock).params
    params = MemoryTransport(network, host="op").params
    optimizer.set(names.current_value("/r1/camera"), 10.0)
    written: list[float] = []
    params.watch(
        lambda name, value: (
            written.append(value)  # type: ignore[arg-type]
            if name == names.sent("/r1/camera")
            else None
        )
    )
    return publisher, optimizer, written


def test_a_slow_rate_between_two_frames_is_not_said_as_a_stop(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """A cut to 0.6 Hz (an infeasible budget) leaves 1-s spans without a frame: not a stop."""
    publisher, optimizer, written = sent_rates(network, clock)
    for beat in range(8):  # a 10-Hz source, a heartbeat a second
        if beat == 2:
            optimizer.set(names.current_value("/r1/camera"), 0.6)
        for _ in range(10):
            clock.advance(0.1)
            publisher.publish(b"x")
        optimizer.set(names.ROUND, float(beat))
    assert written[0] == pytest.approx(10.0)
    assert 0.0 not in written
    assert written[-1] == pytest.approx(0.6, abs=0.2)


def test_a_steady_rate_is_not_said_again_wherever_the_heartbeat_falls_between_frames(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """4 Hz with heartbeats a second apart, each just after or just before a frame.

    A span then holds 3 to 5 frames by phase alone; a fleet would rewrite every rate each period.
    """
    publisher, optimizer, written = sent_rates(network, clock)
    optimizer.set(names.current_value("/r1/camera"), 4.0)
    start = clock()
    beats = [1.001, 1.999, 3.001, 3.999, 5.001, 5.999, 7.001]  # after, before, after, ...
    frame = 0
    for k, beat in enumerate(beats):
        while start + 0.25 * (frame + 1) <= start + beat:
            frame += 1
            clock.advance(start + 0.25 * frame - clock())
            assert publisher.publish(b"x")
        clock.advance(start + beat - clock())
        optimizer.set(names.ROUND, float(k))
    assert written == [pytest.approx(4.0)]  # said once, at the second heartbeat


def test_says_the_rate_it_sent_when_it_moves_or_stops(
    network: MemoryNetwork, clock: ManualClock
) -> None:
    """Between two heartbeats of the optimizer: steady writes nothing, a stop is said."""
    publisher, optimizer, written = sent_rates(network, clock)

    def period(frames: int, heartbeat: float, seconds: float = 1.0) -> None:
        for _ in range(frames):  # ``frames`` sent over ``seconds``, then a heartbeat
            clock.advance(seconds / frames)
            assert publisher.publish(b"x")
        if not frames:
            clock.advance(seconds)
        optimizer.set(names.ROUND, float(heartbeat))

    period(10, 1)  # the first heartbeat only marks
    assert written == []
    period(10, 2)
    assert written == [pytest.approx(10.0)]
    period(10, 3)  # steady: nothing written
    period(10, 4, seconds=1.05)  # 9.5 Hz, within a tenth: nothing written
    assert written == [pytest.approx(10.0)]
    period(5, 5)
    assert written == [pytest.approx(10.0), pytest.approx(5.0)]
    period(0, 6)  # the driver died
    assert written[-1] == 0.0
    period(10, 7)
    period(10, 8)
    assert written[-1] == pytest.approx(10.0)
    clock.advance(0.02)  # an extra round, 20 ms after the last: too short to measure
    optimizer.set(names.ROUND, 8.5)
    assert written[-1] == pytest.approx(10.0)
    optimizer.set(names.current_value("/r1/camera"), 1.0)  # a cut: fewer frames, not a stop
    clock.advance(0.5)
    optimizer.set(names.ROUND, 8.7)
    assert written[-1] == pytest.approx(10.0)
    optimizer.set(names.current_value("/r1/camera"), 10.0)
    period(10, 8.8)
    assert written[-1] > 0
    for _ in range(4):  # it dies 0.6 s before the heartbeat: stopped, not 4 Hz
        clock.advance(0.1)
        assert publisher.publish(b"x")
    clock.advance(0.6)
    optimizer.set(names.ROUND, 9.0)
    assert written[-1] == 0.0
    assert optimizer.get(names.sent("/r1/camera")) == 0.0  # as every other session holds it
