"""zenoh's parameter messages without a network: what is sent and served are plain calls."""

from __future__ import annotations

import itertools
import logging
import threading
import time

import pytest

from dbml.core.errors import TransportError
from dbml.protocol.keys import (
    BATCH,
    MAX_WRITE_BYTES,
    decode_batch,
    decode_param,
    encode_batch,
    encode_param,
    param_key,
)
from dbml.transports.base import ParamValue
from dbml.transports.overflow import MAX_LOGGED_KEYS
from dbml.transports.replica import MAX_PARAMS, MAX_QUEUED_WRITES
from dbml.transports.zenoh.keyed import MAX_CLOCK_AHEAD_NS, KeyedParams


class Wire:
    """Every store's writes go to every other connected store, from its sender thread."""

    def __init__(self) -> None:
        self.stores: list[KeyedParams] = []
        self.sent: list[tuple[str, bytes]] = []
        self.clock = itertools.count(1_000)
        self.gone: set[str] = set()

    def join(self, node_id: str, *, connected: bool = True) -> KeyedParams:
        def send(key: str, data: bytes) -> None:
            self.sent.append((key, data))
            for other in self.stores:
                if other is not store:
                    if key == BATCH:
                        other.on_batch(data)
                    else:
                        other.on_write(key, data)

        store = KeyedParams(node_id, send=send, clock_ns=lambda: next(self.clock))
        if connected:
            self.stores.append(store)
        return store

    def settle(self) -> None:
        """Every queued write delivered."""
        for store in self.stores:
            assert store.replica.flush(timeout_s=5.0)

    def is_live(self, node_id: str) -> bool:
        return node_id not in self.gone

    def meet(self, newcomer: KeyedParams) -> int:
        """What a session does on meeting the others: ask each for what it owns."""
        answers = 0
        for owner in self.stores:
            for name, data in owner.owned(self.is_live):
                newcomer.on_value(name, data)
                answers += 1
        return answers


def name(i: int) -> str:
    """A schema name of its own per number: one channel's priority."""
    return f"/r{i}/camera/dbm/priority"


def quiet(node_id: str = "me") -> KeyedParams:
    return KeyedParams(node_id, send=lambda _k, _d: None)


def record(store: KeyedParams) -> list[tuple[str, ParamValue]]:
    seen: list[tuple[str, ParamValue]] = []
    store.replica.watch(lambda name, value: seen.append((name, value)))
    return seen


def test_a_write_is_applied_sent_and_notified_here_and_there() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    seen_a, seen_b = record(a), record(b)
    a.replica.set("/r1/camera/dbm/priority", 0.5)
    assert a.replica.get("/r1/camera/dbm/priority") == 0.5
    wire.settle()
    assert b.replica.get("/r1/camera/dbm/priority") == 0.5
    assert seen_a == seen_b == [("/r1/camera/dbm/priority", 0.5)]
    assert wire.sent == [
        ("dbml/param/r1/camera/dbm/priority", encode_param(0.5, 1_000, "a")),
    ]
    assert a.stamp("/r1/camera/dbm/priority") == (1_000, "a")


def test_the_newest_write_wins_by_stamp_then_writer() -> None:
    store = quiet()
    seen = record(store)
    name = "/dbm/max_bandwidth_in_mbit"
    key = param_key(name)
    store.on_write(key, encode_param(1, 10, "b"))
    store.on_write(key, encode_param(2, 9, "z"))  # older stamp: ignored
    store.on_write(key, encode_param(3, 10, "a"))  # same stamp, smaller writer: ignored
    assert store.replica.get(name) == 1
    store.on_write(key, encode_param(4, 10, "c"))  # same stamp, larger writer: wins
    assert store.replica.get(name) == 4
    assert seen == [(name, 1), (name, 4)]


def test_its_own_write_echoed_back_is_ignored() -> None:
    store = quiet()
    store.replica.set("/dbm/round", 1)
    seen = record(store)
    store.on_write(param_key("/dbm/round"), encode_param(2, 2**62, "me"))
    assert store.replica.get("/dbm/round") == 1
    assert seen == []


def test_a_malformed_write_is_logged_and_ignored(caplog: pytest.LogCaptureFixture) -> None:
    store = quiet()
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        store.on_write(param_key("/x"), b"{not json")
        store.on_write(param_key("/y"), b'{"v": [1], "t": 1, "w": "w"}')
    assert store.replica.snapshot() == {}
    assert "ignoring /x: malformed parameter write" in caplog.text
    assert "ignoring /y: malformed parameter value [1]" in caplog.text


def test_deletion_hides_a_name_from_the_snapshot_but_keeps_its_stamp() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    a.replica.set("/dbm/strategy", "paper")
    a.replica.set("/dbm/max_bandwidth_in_mbit", 11)
    a.replica.set("/r1/camera/dbm/managed", True)
    b.replica.set("/dbm/strategy", None)
    wire.settle()
    assert a.replica.snapshot("/dbm/") == {"/dbm/max_bandwidth_in_mbit": 11}
    assert a.replica.snapshot() == {
        "/dbm/max_bandwidth_in_mbit": 11,
        "/r1/camera/dbm/managed": True,
    }
    assert a.replica.get("/dbm/strategy") is None
    deletes = [
        decode_param(data)
        for key, data in wire.sent
        if key == param_key("/dbm/strategy") and decode_param(data)[2] == "b"
    ]
    assert [value for value, _, _ in deletes] == [None]
    assert a.stamp("/dbm/strategy") == (deletes[0][1], "b")  # b's delete, as b stamped it
    assert a.stamp("/nope") is None


def test_a_newcomer_learns_each_value_once_from_its_owner() -> None:
    """Each value is served by its writer alone: a join costs one answer per value.

    (Every session once answered with its whole cache: replies grew with sessions x values.)
    """
    wire = Wire()
    stores = [wire.join(f"s{i}") for i in range(10)]
    for i, store in enumerate(stores):
        store.replica.set(f"/r{i}/camera/dbm/frequency/min", 1.0)
        store.replica.set(f"/r{i}/camera/dbm/frequency/max", 16.0)
    wire.settle()
    late = wire.join("late", connected=False)
    seen = record(late)
    assert wire.meet(late) == 20  # not 10 sessions x 20 values
    assert late.replica.get("/r3/camera/dbm/frequency/max") == 16.0
    assert len(seen) == 20
    assert wire.meet(late) == 20
    assert len(seen) == 20  # nothing newer: no second notification


def test_a_value_whose_writer_left_is_served_by_whoever_holds_it() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    cli = wire.join("cli")
    cli.replica.set("/dbm/max_bandwidth_in_mbit", 11.0)  # `dbml priority`, say, which then exits
    wire.settle()
    wire.stores.remove(cli)
    wire.gone.add("cli")
    late = wire.join("late", connected=False)
    assert wire.meet(late) == 2  # a and b both hold it; its writer is gone
    assert late.replica.get("/dbm/max_bandwidth_in_mbit") == 11.0
    assert late.stamp("/dbm/max_bandwidth_in_mbit") == a.stamp("/dbm/max_bandwidth_in_mbit")
    assert b.held("/dbm/max_bandwidth_in_mbit") == a.held("/dbm/max_bandwidth_in_mbit")


def test_a_batch_is_one_message_that_every_store_applies() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    seen = record(b)
    a.replica.set_many({"/r1/camera/dbm/frequency/current_value": 4.0, "/dbm/round": 7})
    wire.settle()
    assert [key for key, _ in wire.sent] == [BATCH]
    assert b.replica.get("/r1/camera/dbm/frequency/current_value") == 4.0
    assert sorted(seen) == [("/dbm/round", 7), ("/r1/camera/dbm/frequency/current_value", 4.0)]
    values, stamp, writer = decode_batch(wire.sent[0][1])
    assert (values["/dbm/round"], writer) == (7, "a")
    assert b.stamp("/dbm/round") == (stamp, "a")
    a.replica.set_many({})  # nothing to say: nothing sent
    wire.settle()
    assert len(wire.sent) == 1


@pytest.mark.parametrize(
    "data",
    [
        b"[1, 2]",
        b'{"vs": [1], "t": 1, "w": "x"}',
        b'{"vs": {"/x": {"deep": 1}}, "t": 1, "w": "x"}',
        b'{"vs": {"not a topic": 1}, "t": 1, "w": "x"}',
        b'{"vs": {"/x": 1}, "t": "soon", "w": "x"}',
        b"[" * 100_000,
    ],
)
def test_a_malformed_batch_changes_nothing(data: bytes) -> None:
    store = quiet()
    store.on_batch(data)
    assert store.replica.snapshot() == {}


def test_an_oversized_write_is_refused_unread(caplog: pytest.LogCaptureFixture) -> None:
    store = quiet()
    huge = encode_param("x" * (MAX_WRITE_BYTES + 1), 1, "w")
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        store.on_write(param_key("/x"), huge)
        store.on_write(param_key("/x"), huge)
    assert store.replica.get("/x") is None
    assert caplog.text.count("more than") == 1  # logged once per key, not per write


def test_a_write_never_waits_for_the_network() -> None:
    """``set`` may run on a middleware callback thread: it queues, the sender thread sends."""
    release = threading.Event()
    sent: list[str] = []

    def send(key: str, _data: bytes) -> None:
        release.wait(10)
        sent.append(key)

    store = KeyedParams("me", send=send)
    started = time.monotonic()
    for i in range(100):
        store.replica.set(f"/r{i}/camera/dbm/priority", i / 100)
    assert time.monotonic() - started < 1.0
    assert store.replica.get("/r99/camera/dbm/priority") == 0.99  # applied here at once
    assert not store.replica.flush(timeout_s=0.05)
    release.set()
    assert store.replica.flush(timeout_s=5.0)
    assert sent == [param_key(f"/r{i}/camera/dbm/priority") for i in range(100)]  # in order
    store.replica.close()


class Stalled:
    """A send that blocks until released (a congested network), recording what it sent."""

    def __init__(self) -> None:
        self.blocked = threading.Event()
        self.release = threading.Event()
        self.sent: list[tuple[str, bytes]] = []

    def __call__(self, key: str, data: bytes) -> None:
        self.blocked.set()
        assert self.release.wait(10), "the test never released the network"
        self.sent.append((key, data))


def test_a_stalled_network_keeps_only_a_names_newest_queued_write() -> None:
    send = Stalled()
    store = KeyedParams("me", send=send)
    store.replica.set("/dbm/round", 0)
    assert send.blocked.wait(5.0)  # the sender thread took it and blocks in send
    for value in range(1, 1_000):
        store.replica.set("/dbm/max_bandwidth_in_mbit", value)
    store.replica.set("/dbm/status_message", "last")
    assert store.replica._sender is not None
    assert len(store.replica._sender.pending()) == 3  # /held in flight, /x's newest, /y
    send.release.set()
    assert store.replica.flush(timeout_s=5.0)
    assert [(k, decode_param(d)[0]) for k, d in send.sent] == [
        (param_key("/dbm/round"), 0),
        (param_key("/dbm/max_bandwidth_in_mbit"), 999),
        (param_key("/dbm/status_message"), "last"),
    ]
    store.replica.close()


def test_a_stalled_network_drops_the_oldest_write_past_the_bound_and_says_so_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    send = Stalled()
    store = KeyedParams("me", send=send)
    over = 10
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        store.replica.set(name(0), 0)
        assert send.blocked.wait(5.0)  # in flight: the queue holds the rest
        for i in range(1, MAX_QUEUED_WRITES + 1 + over):
            store.replica.set(name(i), 1)
        assert store.replica.get(name(0)) == 0  # every write holds here, sent or not
        assert store.replica._sender is not None
        assert len(store.replica._sender.pending()) == MAX_QUEUED_WRITES + 1
        assert store.replica._sender.dropped == over
        assert "unsent items" not in caplog.text  # told by the sender's thread, not under a lock
        send.release.set()
        assert store.replica.flush(timeout_s=10.0)
        assert caplog.text.count("evicting the oldest") == 1
        assert caplog.text.count(f"room again; {over} evicted meanwhile") == 1
    names = [key for key, _ in send.sent]
    kept = [param_key(name(i)) for i in (0, *range(1 + over, MAX_QUEUED_WRITES + 1 + over))]
    assert names == kept  # the oldest queued went, in order; the newest all arrived
    store.replica.close()


def test_bad_values_and_names_are_rejected_before_anything_is_sent() -> None:
    wire = Wire()
    a = wire.join("a")
    with pytest.raises(TransportError, match=r"^/dbm/round=\[1\] is not a parameter value"):
        a.replica.set("/dbm/round", [1])  # type: ignore[arg-type]
    with pytest.raises(TransportError, match=r"^x=1: 'x' is not a parameter of dbml's schema"):
        a.replica.set("x", 1)
    with pytest.raises(TransportError, match=r"^x=1: 'x' is not a parameter of dbml's schema"):
        a.replica.set_many({"/dbm/round": 1, "x": 1})
    wire.settle()
    assert wire.sent == []
    assert a.replica.get("/dbm/round") is None


def test_a_failing_watcher_does_not_stop_the_others(caplog: pytest.LogCaptureFixture) -> None:
    store = quiet()

    def fail(_name: str, _value: ParamValue) -> None:
        raise RuntimeError("boom")

    store.replica.watch(fail)
    seen = record(store)
    with caplog.at_level(logging.ERROR, logger="dbml.transports"):
        store.replica.set("/dbm/round", 1)
    assert seen == [("/dbm/round", 1)]
    assert "boom" in caplog.text


def test_a_write_supersedes_one_stamped_ahead_of_the_clock() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    ahead = next(wire.clock) + MAX_CLOCK_AHEAD_NS // 2  # a peer whose clock runs ahead
    a.on_write(param_key("/r1/camera/dbm/priority"), encode_param(0.9, ahead, "z"))
    b.on_write(param_key("/r1/camera/dbm/priority"), encode_param(0.9, ahead, "z"))
    assert a.replica.get("/r1/camera/dbm/priority") == 0.9
    seen = record(b)
    a.replica.set("/r1/camera/dbm/priority", 0.1)
    assert a.replica.get("/r1/camera/dbm/priority") == 0.1
    wire.settle()
    assert b.replica.get("/r1/camera/dbm/priority") == 0.1  # the others take it too
    assert seen == [("/r1/camera/dbm/priority", 0.1)]
    assert decode_param(wire.sent[-1][1])[1] == ahead + 1


@pytest.mark.parametrize("ahead_ns", [MAX_CLOCK_AHEAD_NS + 10, 3600 * 10**9, 2**62])
def test_a_write_stamped_too_far_ahead_is_refused(
    ahead_ns: int, caplog: pytest.LogCaptureFixture
) -> None:
    wire = Wire()
    a = wire.join("a")
    a.replica.set("/dbm/max_bandwidth_in_mbit", 11)
    seen = record(a)
    stamp = next(wire.clock) + ahead_ns
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        a.on_write(param_key("/dbm/max_bandwidth_in_mbit"), encode_param(100, stamp, "z"))
    assert a.replica.get("/dbm/max_bandwidth_in_mbit") == 11  # not pinned by a future stamp
    assert seen == []
    assert "ahead of this clock" in caplog.text
    a.replica.set("/dbm/max_bandwidth_in_mbit", 5)  # and the next honest write wins as ever
    assert a.replica.get("/dbm/max_bandwidth_in_mbit") == 5


def flood_name(i: int) -> str:
    """A name of the schema's, of a channel nobody publishes: what a flood can make up."""
    return f"/flood{i}/camera/dbm/priority"


def test_names_from_the_network_are_bounded_and_a_flood_is_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A peer writing endless new names fills the store to its bound, no further."""
    store = quiet()
    over = 100
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        for i in range(MAX_PARAMS + over):
            store.on_write(param_key(flood_name(i)), encode_param(0.5, 10, "peer"))
        batch = {"/flood/batch/dbm/priority": 0.1, flood_name(0): 0.25}
        store.on_batch(encode_batch(batch, 11, "peer"))
        assert len(store.replica) == MAX_PARAMS
        assert store.replica.get(flood_name(MAX_PARAMS)) is None  # refused
        assert store.replica.get("/flood/batch/dbm/priority") is None  # refused, in a batch too
        assert store.replica.get(flood_name(0)) == 0.25  # a name held is still updated
        # This process's own writes are always taken: read-your-writes, served as owned.
        store.replica.set("/dbm/round", 1)
        store.replica.set_many({"/dbm/max_bandwidth_in_mbit": 2, "/r1/camera/dbm/priority": 0.3})
        mine = ("/dbm/round", "/dbm/max_bandwidth_in_mbit", "/r1/camera/dbm/priority")
        assert [store.replica.get(n) for n in mine] == [1, 2, 0.3]
        assert ("/dbm/round", store.held("/dbm/round")) in store.owned(lambda _writer: True)
        # A question about one channel: only its values are encoded and served.
        assert [name for name, _ in store.owned(lambda _w: True, prefix="/r1/camera")] == [
            "/r1/camera/dbm/priority"
        ]
    full = [r.getMessage() for r in caplog.records if "parameter names" in r.getMessage()]
    assert full == [
        "parameter names: 65536 held, the most kept; refusing new ones "
        "(told once until half of them are gone)"
    ]
    assert store.replica.refused == over + 1
    store.replica.close()


def test_a_flood_gives_way_to_a_live_channel_and_names_outside_the_schema_take_no_room(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A full store gives up a flood's oldest name for a channel someone publishes.

    Refused for good, a new robot's bounds would never reach the optimizer: the channel would
    never be allocated for the life of the process.
    """
    store = quiet()
    live = {"/r9/camera"}
    store.replica.keep = lambda name: name.startswith(tuple(f"{t}/" for t in live))
    told: list[tuple[str, object]] = []
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        for i in range(1000):
            store.on_write(param_key(f"/made/up/{i}"), encode_param(1, 10, "peer"))
        assert len(store.replica) == 0  # outside the schema: nothing held
        for i in range(MAX_PARAMS):
            store.on_write(param_key(flood_name(i)), encode_param(0.5, 10, "peer"))
        store.replica.watch(lambda name, value: told.append((name, value)))
        store.on_write(param_key("/r9/camera/dbm/frequency/max"), encode_param(16.0, 12, "r9"))
        store.on_write(param_key(flood_name(MAX_PARAMS)), encode_param(0.5, 12, "peer"))
    assert store.replica.get("/r9/camera/dbm/frequency/max") == 16.0
    assert store.replica.get(flood_name(0)) is None  # the oldest of the flood's gave way
    assert store.replica.get(flood_name(1)) is None  # and the next, for the next new name
    assert store.replica.get(flood_name(MAX_PARAMS)) == 0.5
    assert len(store.replica) == MAX_PARAMS
    assert told[:2] == [(flood_name(0), None), ("/r9/camera/dbm/frequency/max", 16.0)]
    unknown = [r.getMessage() for r in caplog.records if "outside the schema" in r.getMessage()]
    assert unknown == ["ignoring /made/up/0 and other names outside the schema"]
    store.replica.close()


def test_malformed_keys_are_logged_for_a_bounded_number_of_keys(
    caplog: pytest.LogCaptureFixture,
) -> None:
    store = quiet()
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        for i in range(MAX_LOGGED_KEYS + 50):
            store.on_write(param_key(f"/bad/{i}"), b"{not json")
            store.on_write(param_key(f"/bad/{i}"), b"{not json")  # the same key: once
    messages = [r.getMessage() for r in caplog.records]
    assert sum(m.startswith("ignoring /bad/") for m in messages) == MAX_LOGGED_KEYS
    assert messages[-1] == f"{MAX_LOGGED_KEYS} distinct bad keys logged: no more are logged"
    assert len(messages) == MAX_LOGGED_KEYS + 1
    store.replica.close()
