"""The typed parameters: one validation of every value, the last good value stands.

And what that means to the optimizer and the publisher when a peer writes garbage.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping

import pytest

from dbml.cli.commands import set_priority
from dbml.core import DbmSettings, Strategy, TransportError
from dbml.protocol import names, schema
from dbml.protocol.schema import Parameter
from dbml.runtime import ManagedPublisher, ManagedSubscriber, OptimizerNode
from dbml.runtime.params import MAX_PROBLEMS, MAX_VALUES, DbmParams, ParamView, read_snapshot
from dbml.runtime.priority import collision_priority_source
from dbml.transports import MemoryNetwork, MemoryTransport
from dbml.transports.base import Closer, Handle, ParamValue
from tests.conftest import wait_for

CAMERA = "/r1/camera"


def camera_on(network: MemoryNetwork) -> ManagedPublisher:
    """R1's 84,000-byte camera (1-16 Hz) on its own host, its size already known."""
    camera = ManagedPublisher(
        MemoryTransport(network, host="r1"), CAMERA, min_rate_hz=1, max_rate_hz=16
    )
    camera.publish(bytes(84_000))
    return camera


def managed_fleet(network: MemoryNetwork) -> tuple[ManagedPublisher, OptimizerNode]:
    """The camera, a remote subscriber (so it is managed) and an optimizer with 4 Mbit/s."""
    camera = camera_on(network)
    ManagedSubscriber(MemoryTransport(network, host="op"), CAMERA, lambda s: None)
    optimizer = OptimizerNode(
        MemoryTransport(network, host="base"), settings=DbmSettings(4.0, 1.0, 1.0, Strategy.PAPER)
    )
    return camera, optimizer


def test_the_one_budget_rule() -> None:
    assert DbmParams(bandwidth_mbit=10, utilization=0.9).budget_mbit == pytest.approx(9.0)
    assert DbmParams(bandwidth_mbit=10, utilization=0.9, estimate_mbit=4).budget_mbit == 4
    assert DbmParams(bandwidth_mbit=10, utilization=0.9, estimate_mbit=4).configured_mbit == 9.0
    assert DbmParams(bandwidth_mbit=10, utilization=0.9, estimate_mbit=20).budget_mbit == 9.0
    assert DbmParams(estimate_mbit=4).budget_mbit is None  # an estimate needs a configured cap
    assert DbmParams().budget_mbit is None


def test_the_view_keeps_the_last_good_value_and_reports_the_bad_one_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    network = MemoryNetwork()
    writer = MemoryTransport(network, host="peer")
    writer.params.set(names.BANDWIDTH, 11)
    changes: list[tuple[str, ParamValue]] = []
    view = ParamView.of(MemoryTransport(network, host="me").params)
    view.watch(lambda *c: changes.append(c))
    assert view.dbm().bandwidth_mbit == 11.0
    with caplog.at_level(logging.WARNING, logger="dbml.params"):
        for _ in range(3):
            network.forge({names.BANDWIDTH: math.inf})  # a peer's bad value
    assert view.dbm().bandwidth_mbit == 11.0
    assert view.problems() == ("/dbm/max_bandwidth_in_mbit=inf is not finite",)
    assert caplog.text.count("max_bandwidth_in_mbit=inf") == 1
    assert changes == []  # a bad value is no change
    writer.params.set(names.BANDWIDTH, 5)
    assert view.dbm().bandwidth_mbit == 5.0
    assert view.problems() == ()
    assert changes == [(names.BANDWIDTH, 5.0)]
    snapshot = read_snapshot({names.BANDWIDTH: "x", names.UTILIZATION: 0.5})
    assert snapshot.globals == {schema.UTILIZATION: 0.5}


def test_bad_writes_never_widen_the_budget_nor_drop_a_live_channel() -> None:
    network = MemoryNetwork()
    _camera, optimizer = managed_fleet(network)
    assert optimizer.optimize().rates_hz[CAMERA] == pytest.approx(500_000 / 84_000)
    peer = MemoryTransport(network, host="hostile")
    writes: list[tuple[str, ParamValue]] = [  # what a hostile peer can put on the network
        (names.BANDWIDTH, 1e300),
        (names.max_rate(CAMERA), "x"),
        (names.max_rate(CAMERA), -1),
        (names.size(CAMERA), 1e15),
        (names.priority(CAMERA), math.nan),
        (names.PERIOD, math.inf),
    ]
    for name, value in writes:
        network.forge({name: value}, writer="hostile")
    result = optimizer.optimize()
    assert [c.topic for c in result.channels] == [CAMERA]  # still allocated, not dropped
    assert result.rates_hz[CAMERA] == pytest.approx(500_000 / 84_000)
    assert "ignored: /dbm/max_bandwidth_in_mbit=1e+300 must be within" in result.message
    status = peer.params.get(names.STATUS_MESSAGE)
    assert isinstance(status, str)
    assert "/r1/camera/dbm/frequency/max=-1 must be within" in status
    assert optimizer.period_s() == 1.0


def test_a_publisher_ignores_a_bad_push_and_clamps_to_its_maximum() -> None:
    network = MemoryNetwork()
    camera = ManagedPublisher(
        MemoryTransport(network, host="r1"), CAMERA, min_rate_hz=1, max_rate_hz=16
    )
    peer = MemoryTransport(network, host="hostile")
    peer.params.set(names.current_value(CAMERA), 8.0)
    assert camera.current_rate_hz() == 8.0
    network.forge({names.current_value(CAMERA): math.nan})  # once crashed the publisher
    network.forge({names.current_value(CAMERA): 1e12})
    assert camera.current_rate_hz() == 8.0
    network.forge({names.current_value(CAMERA): 59.0})  # above its maximum
    assert camera.current_rate_hz() == 16.0  # its own maximum: it is the authority on it
    assert peer.params.get(names.applied(CAMERA)) == 16.0


def test_an_optimizer_thread_survives_an_absurd_period() -> None:
    network = MemoryNetwork()
    camera, optimizer = managed_fleet(network)
    peer = MemoryTransport(network, host="hostile")
    optimizer.start()
    try:
        network.forge({names.PERIOD: math.inf})
        network.forge({names.PERIOD: 10**400})
        network.forge({names.priority(CAMERA): 10**400})
        peer.params.set(names.BANDWIDTH, 8.0)  # a good change afterwards is still acted on
        wait_for(
            lambda: camera.current_rate_hz() == pytest.approx(1_000_000 / 84_000),
            what="the new budget applied by a live optimizer",
        )
    finally:
        optimizer.stop()


def test_an_estimate_written_by_a_peer_is_not_the_optimizers_budget() -> None:
    network = MemoryNetwork()
    camera, optimizer = managed_fleet(network)
    MemoryTransport(network, host="hostile").params.set(names.ESTIMATE, 1e5)
    assert optimizer.optimize().budget_mbit == 4.0
    assert camera.current_rate_hz() == pytest.approx(500_000 / 84_000)


def test_one_view_per_store_and_a_write_during_the_first_read_is_not_lost() -> None:
    network = MemoryNetwork()
    store = MemoryTransport(network, host="me").params
    assert ParamView.of(store) is ParamView.of(store)

    class Racing:
        """A store whose snapshot is taken before a write that is notified during the read."""

        def __init__(self) -> None:
            self.watchers: list[Callable[[str, ParamValue], None]] = []

        def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
            self.watchers.append(callback)
            return Closer(lambda: None)

        def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
            old: dict[str, ParamValue] = {names.BANDWIDTH: 11.0}
            for callback in self.watchers:
                callback(names.BANDWIDTH, 5.0)  # newer, pushed while the snapshot travels
            return old

        def set(self, name: str, value: ParamValue) -> None:
            raise AssertionError("not written")

        def set_many(self, values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
            raise AssertionError("not written")

        def get(self, name: str) -> ParamValue:
            raise AssertionError("not read")

    view = ParamView(Racing())
    assert view.dbm().bandwidth_mbit == 5.0


@pytest.mark.parametrize(
    "topic", ["/r1/camera/optimized", "/dbm/priority", "/r1/camera/dbm/x", "/dbm"]
)
def test_reserved_names_are_not_channels(topic: str) -> None:
    transport = MemoryTransport()
    with pytest.raises(TransportError, match=rf"^topic='{topic}' is reserved"):
        ManagedPublisher(transport, topic, min_rate_hz=1, max_rate_hz=2)
    with pytest.raises(TransportError, match="is reserved"):
        ManagedSubscriber(transport, topic, lambda s: None)
    with pytest.raises(TransportError, match="is reserved"):
        set_priority(transport, topic, 0.5)
    assert transport.graph.entries() == frozenset()  # nothing was declared


def test_a_publisher_reasserts_its_real_size() -> None:
    network = MemoryNetwork()
    camera = camera_on(network)
    peer = MemoryTransport(network, host="hostile")
    peer.params.set(names.size(CAMERA), 1)  # once gave 1.64 x the budget while it stood
    assert peer.params.get(names.size(CAMERA)) == 1
    camera.publish(bytes(84_000))
    assert peer.params.get(names.size(CAMERA)) == 84_000


def test_a_channel_watcher_hears_its_own_channel_only_by_field() -> None:
    network = MemoryNetwork()
    writer = MemoryTransport(network, host="peer").params
    view = ParamView.of(MemoryTransport(network, host="me").params)
    camera: list[tuple[str, ParamValue]] = []
    other: list[tuple[str, ParamValue]] = []
    global_: list[tuple[str, ParamValue]] = []
    view.watch_channel(CAMERA, lambda *c: camera.append(c))
    view.watch_channel("/r2/camera", lambda *c: other.append(c))
    view.watch_dbm(lambda *c: global_.append(c))
    writer.set(names.current_value(CAMERA), 8)
    network.forge({names.priority(CAMERA): math.nan})  # a bad value calls nothing
    writer.set(names.PERIOD, 0.5)
    writer.set(names.size(CAMERA), None)
    assert camera == [(names.CURRENT_FIELD, 8.0), (names.SIZE_FIELD, None)]
    assert other == []
    assert global_ == [(names.PERIOD, 0.5)]


def test_a_closed_channel_watcher_hears_nothing_and_the_others_go_on() -> None:
    network = MemoryNetwork()
    writer = MemoryTransport(network, host="peer").params
    view = ParamView.of(MemoryTransport(network, host="me").params)
    first: list[ParamValue] = []
    second: list[ParamValue] = []
    closing = view.watch_channel(CAMERA, lambda _f, v: first.append(v))
    view.watch_channel(CAMERA, lambda _f, v: second.append(v))
    writer.set(names.priority(CAMERA), 0.5)
    closing.close()
    writer.set(names.priority(CAMERA), 0.25)
    assert first == [0.5]
    assert second == [0.5, 0.25]
    last = view.watch_channel("/r3/camera", lambda _f, v: first.append(v))
    last.close()  # its topic's last watcher: gone, and a new one starts afresh
    again: list[ParamValue] = []
    view.watch_channel("/r3/camera", lambda _f, v: again.append(v))
    writer.set(names.priority("/r3/camera"), 1.0)
    assert first == [0.5]
    assert again == [1.0]


def test_typed_reads_do_not_copy_every_value(monkeypatch: pytest.MonkeyPatch) -> None:
    network = MemoryNetwork()
    writer = MemoryTransport(network, host="peer").params
    for k in range(50):  # a fleet's worth of other channels
        writer.set(names.size(f"/r{k}/camera"), 84_000)
    writer.set(names.priority(CAMERA), 0.5)
    writer.set(names.PERIOD, 0.5)
    view = ParamView.of(MemoryTransport(network, host="me").params)

    def copied() -> Mapping[str, ParamValue]:
        raise AssertionError("a typed read copied every value")

    monkeypatch.setattr(view, "values", copied)
    assert view.channel(CAMERA).priority == 0.5
    assert view.channel("/r7/camera").size_bytes == 84_000.0
    assert view.dbm().period_s == 0.5


def test_a_view_keeps_a_bounded_number_of_names_and_says_so_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Fed by a store that bounds nothing (ROS 1's mirror), the view bounds itself."""
    view = ParamView.of(MemoryTransport(MemoryNetwork(), host="me").params)
    heard: list[str] = []
    view.watch(lambda name, _value: heard.append(name))
    over = 100
    with caplog.at_level(logging.WARNING, logger="dbml.params"):
        for i in range(MAX_VALUES + over):
            view._take(f"/flood/{i}", i)  # what the store notifies, called directly
        assert len(view.values()) == MAX_VALUES
        assert view.get(f"/flood/{MAX_VALUES}") is None  # refused: kept nowhere, told to nobody
        assert len(heard) == MAX_VALUES
        view._take("/flood/0", -1)  # a name held is still updated
        assert view.get("/flood/0") == -1
        for i in range(MAX_VALUES // 2):
            view._take(f"/flood/{i}", None)  # deletions make room
        assert len(view.values()) == MAX_VALUES // 2
    messages = [r.getMessage() for r in caplog.records]
    assert messages == [
        f"parameter names viewed: {MAX_VALUES} held, the most kept; refusing new ones "
        "(told once until half of them are gone)",
        f"parameter names viewed: room again; {over} refused meanwhile",
    ]


def test_a_flood_of_bad_values_lists_a_bounded_number_and_logs_the_rest_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Problems end up in the status message: a flood of bad names must not make it huge."""
    view = ParamView.of(MemoryTransport(MemoryNetwork(), host="me").params)
    over = 10
    with caplog.at_level(logging.WARNING, logger="dbml.params"):
        for _ in range(2):  # the same bad values again: nothing more logged
            for i in range(MAX_PROBLEMS + over):
                view._take(names.priority(f"/r{i}/camera"), "high")
        problems = view.problems()
        assert len(problems) == MAX_PROBLEMS + 1
        assert problems[-1] == f"more than {MAX_PROBLEMS} bad values: the others are not listed"
        assert len(view._problems) == MAX_PROBLEMS
        for i in range(MAX_PROBLEMS // 2):
            view._take(names.priority(f"/r{i}/camera"), 0.5)  # good values end problems
        assert len(view.problems()) == MAX_PROBLEMS // 2  # and the flood
    messages = [r.getMessage() for r in caplog.records]
    assert sum("is not a number" in m or "high" in m for m in messages) == MAX_PROBLEMS
    assert messages[MAX_PROBLEMS:] == [
        f"bad parameter values: {MAX_PROBLEMS} held, the most kept; refusing new ones "
        "(told once until half of them are gone)",
        f"bad parameter values: room again; {2 * over} refused meanwhile",
    ]


def test_a_priority_is_parsed_once_per_process_where_it_enters(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The view parses a name once; the optimizer and the publishers get it parsed."""
    network = MemoryNetwork()
    _camera, optimizer = managed_fleet(network)
    optimizer.optimize()
    parses: list[str] = []
    split = schema.split_channel_name

    def counted(name: str) -> tuple[str, str] | None:
        parses.append(name)
        return split(name)

    monkeypatch.setattr(schema, "split_channel_name", counted)
    monkeypatch.setattr(names, "topic_of", counted)
    source = collision_priority_source(MemoryTransport(network, host="r1-events"), CAMERA)
    source.set(0.5)
    # One parse in each process: the event source's store checks the name against the schema
    # as it takes the write, the robot's and the optimizer's views as it enters; none by the
    # optimizer's reaction, none again in a view (it parsed 5 times in the two views and the
    # optimizer alone).
    assert parses.count(names.priority(CAMERA)) == 3
    parses.clear()
    optimizer.optimize()
    written = {n for n in parses if not n.endswith(("/current_value", "/managed"))}
    assert written <= {names.ROUND, names.STATUS, names.STATUS_MESSAGE}, written


def test_the_view_keeps_values_by_channel_and_parameter() -> None:
    network = MemoryNetwork()
    camera, optimizer = managed_fleet(network)
    optimizer.optimize()
    view = ParamView.of(MemoryTransport(network, host="viewer").params)
    heard: list[tuple[Parameter, str | None, ParamValue]] = []
    view.watch_params(lambda p, t, v: heard.append((p, t, v)))
    assert view.topics() == [CAMERA]
    channel = view.channels([CAMERA, "/r9/none"])
    assert channel[CAMERA].size_bytes == 84_000
    assert channel[CAMERA].current_rate_hz == pytest.approx(4e6 / 8 / 84_000)
    assert channel["/r9/none"].bounded is False
    MemoryTransport(network, host="op").params.set(names.priority(CAMERA), 0.25)
    assert (schema.PRIORITY, CAMERA, 0.25) in heard
    assert view.channel(CAMERA).priority == 0.25
    MemoryTransport(network, host="op").params.set(names.priority(CAMERA), None)
    assert view.channel(CAMERA).priority == 0.0
    assert view.dbm().bandwidth_mbit == 4.0
    camera.close()


def test_a_channel_read_again_is_rebuilt_only_once_one_of_its_values_changed() -> None:
    network = MemoryNetwork()
    writer = MemoryTransport(network, host="peer").params
    other = "/r2/camera"
    for topic in (CAMERA, other):
        writer.set(names.size(topic), 84_000)
        writer.set(names.priority(topic), 0.5)
    view = ParamView.of(MemoryTransport(network, host="me").params)
    first = view.channels([CAMERA, other])
    again = view.channels([CAMERA, other])
    assert again[CAMERA] is first[CAMERA]  # nothing changed: the round's read builds nothing
    assert first[CAMERA].spec() is None  # no bounds yet: no spec
    writer.set(names.priority(CAMERA), 0.75)
    after = view.channels([CAMERA, other])
    assert after[CAMERA].priority == 0.75
    assert after[other] is first[other]  # another channel's write rebuilds only that one
    network.forge({names.priority(CAMERA): 1.5})  # a peer's bad value: the last good one stands
    assert view.channel(CAMERA) is after[CAMERA]
    writer.set(names.size(CAMERA), None)
    assert view.channel(CAMERA).size_bytes is None
    writer.set(names.priority(CAMERA), None)
    assert view.channel(CAMERA) == view.channel(CAMERA)  # no value left: read as unset
    assert view.channel(CAMERA).priority == 0.0


def test_the_global_parameters_are_read_again_once_one_changes() -> None:
    network = MemoryNetwork()
    writer = MemoryTransport(network, host="peer").params
    writer.set(names.BANDWIDTH, 11.0)
    view = ParamView.of(MemoryTransport(network, host="me").params)
    first = view.dbm()
    assert view.dbm() is first
    writer.set(names.PERIOD, 0.5)
    assert view.dbm().period_s == 0.5
    assert view.dbm().bandwidth_mbit == 11.0
    writer.set(names.BANDWIDTH, None)
    assert view.dbm().bandwidth_mbit is None


def test_a_channels_spec_follows_its_values_and_is_checked_once_per_value() -> None:
    network = MemoryNetwork()
    camera = camera_on(network)
    view = ParamView.of(MemoryTransport(network, host="me").params)
    spec = view.channel(CAMERA).spec()
    assert spec is not None
    assert (spec.min_rate_hz, spec.max_rate_hz, spec.size_bytes) == (1.0, 16.0, 84_000.0)
    MemoryTransport(network, host="op").params.set(names.priority(CAMERA), 0.25)
    moved = view.channel(CAMERA).spec()
    assert moved is not None
    assert moved.priority == 0.25
    MemoryTransport(network, host="op").params.set(names.priority(CAMERA), 0.0)
    assert view.channel(CAMERA).spec() is spec  # the same values: the spec built for them
    camera.close()
