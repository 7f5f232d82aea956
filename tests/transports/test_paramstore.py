"""The replicated parameter store without a network: writes and queries are plain calls."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterator

import pytest

from dbml.core.errors import TransportError
from dbml.transports.base import ParamValue
from dbml.transports.paramstore import (
    MAX_CLOCK_AHEAD_NS,
    PARAM_PREFIX,
    ReplicatedParams,
    decode_param,
    encode_param,
    param_key,
)


class Wire:
    """Every store's writes go to every other store, synchronously; fetch asks them all."""

    def __init__(self) -> None:
        self.stores: list[ReplicatedParams] = []
        self.sent: list[tuple[str, bytes]] = []
        self.clock = itertools.count(1_000)
        self.fetches: list[float] = []

    def join(self, node_id: str, *, connected: bool = True) -> ReplicatedParams:
        def publish(key: str, data: bytes) -> None:
            self.sent.append((key, data))
            for other in self.stores:
                if other is not store:
                    other.on_write(key, data)

        def fetch(timeout_s: float) -> Iterator[tuple[str, bytes]]:
            self.fetches.append(timeout_s)
            for other in self.stores:
                yield from other.replies(lambda key: key.startswith(PARAM_PREFIX + "/"))

        store = ReplicatedParams(
            node_id, publish=publish, fetch=fetch, clock_ns=lambda: next(self.clock)
        )
        if connected:
            self.stores.append(store)
        return store


def record(store: ReplicatedParams) -> list[tuple[str, ParamValue]]:
    seen: list[tuple[str, ParamValue]] = []
    store.watch(lambda name, value: seen.append((name, value)))
    return seen


def test_a_write_is_applied_sent_and_notified_here_and_there() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    seen_a, seen_b = record(a), record(b)
    a.set("/r1/camera/dbm/priority", 0.5)
    assert a.get("/r1/camera/dbm/priority") == 0.5
    assert b.get("/r1/camera/dbm/priority") == 0.5
    assert seen_a == seen_b == [("/r1/camera/dbm/priority", 0.5)]
    assert wire.sent == [
        ("dbml/param/r1/camera/dbm/priority", encode_param(0.5, 1_000, "a")),
    ]
    assert a.stamp("/r1/camera/dbm/priority") == (1_000, "a")


def test_the_newest_write_wins_by_stamp_then_writer() -> None:
    store = ReplicatedParams("me", publish=lambda _k, _d: None, fetch=lambda _t: ())
    seen = record(store)
    key = param_key("/x")
    store.on_write(key, encode_param(1, 10, "b"))
    store.on_write(key, encode_param(2, 9, "z"))  # older stamp: ignored
    store.on_write(key, encode_param(3, 10, "a"))  # same stamp, smaller writer: ignored
    assert store.get("/x") == 1
    store.on_write(key, encode_param(4, 10, "c"))  # same stamp, larger writer: wins
    assert store.get("/x") == 4
    assert seen == [("/x", 1), ("/x", 4)]


def test_its_own_write_echoed_back_is_ignored() -> None:
    store = ReplicatedParams("me", publish=lambda _k, _d: None, fetch=lambda _t: ())
    store.set("/x", 1)
    seen = record(store)
    store.on_write(param_key("/x"), encode_param(2, 2**62, "me"))
    assert store.get("/x") == 1
    assert seen == []


def test_a_malformed_write_is_logged_and_ignored(caplog: pytest.LogCaptureFixture) -> None:
    store = ReplicatedParams("me", publish=lambda _k, _d: None, fetch=lambda _t: ())
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        store.on_write(param_key("/x"), b"{not json")
        store.on_write(param_key("/y"), b'{"v": [1], "t": 1, "w": "w"}')
    assert store.snapshot() == {}
    assert "ignoring dbml/param/x: malformed parameter write" in caplog.text
    assert "ignoring dbml/param/y: malformed parameter value [1]" in caplog.text


def test_deletion_hides_a_name_from_the_snapshot_but_keeps_its_stamp() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    a.set("/dbm/strategy", "paper")
    a.set("/dbm/max_bandwidth_in_mbit", 11)
    a.set("/r1/camera/dbm/managed", True)
    b.set("/dbm/strategy", None)
    assert a.snapshot("/dbm/") == {"/dbm/max_bandwidth_in_mbit": 11}
    assert a.snapshot() == {"/dbm/max_bandwidth_in_mbit": 11, "/r1/camera/dbm/managed": True}
    assert a.get("/dbm/strategy") is None
    assert a.stamp("/dbm/strategy") == (decode_param(wire.sent[-1][1])[1], "b")  # b's delete
    assert a.stamp("/nope") is None


def test_a_late_joiner_syncs_what_the_others_hold() -> None:
    wire = Wire()
    a = wire.join("a")
    a.set("/r1/camera/dbm/frequency/min", 1.0)
    late = wire.join("late", connected=False)
    seen = record(late)
    late.sync()
    assert late.get("/r1/camera/dbm/frequency/min") == 1.0
    assert seen == [("/r1/camera/dbm/frequency/min", 1.0)]
    assert wire.fetches == [2.0]
    late.sync(0.5)  # nothing newer: no second notification
    assert seen == [("/r1/camera/dbm/frequency/min", 1.0)]
    assert wire.fetches == [2.0, 0.5]


def test_replies_hold_only_the_keys_the_query_matches() -> None:
    wire = Wire()
    a = wire.join("a")
    a.set("/dbm/strategy", "paper")
    a.set("/r1/camera/dbm/priority", 0.25)
    replies = a.replies(lambda key: key == "dbml/param/dbm/strategy")
    assert replies == [("dbml/param/dbm/strategy", encode_param("paper", 1_000, "a"))]
    assert decode_param(replies[0][1]) == ("paper", 1_000, "a")


def test_bad_values_and_names_are_rejected_before_anything_is_sent() -> None:
    wire = Wire()
    a = wire.join("a")
    with pytest.raises(TransportError, match=r"parameter value=\[1\] must be a bool"):
        a.set("/x", [1])  # type: ignore[arg-type]
    with pytest.raises(TransportError, match=r"topic='x' must look like '/robot/sensor'"):
        a.set("x", 1)
    assert wire.sent == []


def test_a_failing_watcher_does_not_stop_the_others(caplog: pytest.LogCaptureFixture) -> None:
    store = ReplicatedParams("me", publish=lambda _k, _d: None, fetch=lambda _t: ())

    def fail(_name: str, _value: ParamValue) -> None:
        raise RuntimeError("boom")

    store.watch(fail)
    seen = record(store)
    with caplog.at_level(logging.ERROR, logger="dbml.transports"):
        store.set("/x", 1)
    assert seen == [("/x", 1)]
    assert "boom" in caplog.text


def test_a_write_supersedes_one_stamped_ahead_of_the_clock() -> None:
    wire = Wire()
    a, b = wire.join("a"), wire.join("b")
    ahead = next(wire.clock) + MAX_CLOCK_AHEAD_NS // 2  # a peer whose clock runs ahead
    a.on_write(param_key("/r1/camera/dbm/priority"), encode_param(0.9, ahead, "z"))
    b.on_write(param_key("/r1/camera/dbm/priority"), encode_param(0.9, ahead, "z"))
    assert a.get("/r1/camera/dbm/priority") == 0.9
    seen = record(b)
    a.set("/r1/camera/dbm/priority", 0.1)
    assert a.get("/r1/camera/dbm/priority") == 0.1
    assert b.get("/r1/camera/dbm/priority") == 0.1  # the others take it too
    assert seen == [("/r1/camera/dbm/priority", 0.1)]
    assert decode_param(wire.sent[-1][1])[1] == ahead + 1


@pytest.mark.parametrize("ahead_ns", [MAX_CLOCK_AHEAD_NS + 10, 3600 * 10**9, 2**62])
def test_a_write_stamped_too_far_ahead_is_refused(
    ahead_ns: int, caplog: pytest.LogCaptureFixture
) -> None:
    wire = Wire()
    a = wire.join("a")
    a.set("/dbm/max_bandwidth_in_mbit", 11)
    seen = record(a)
    stamp = next(wire.clock) + ahead_ns
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        a.on_write(param_key("/dbm/max_bandwidth_in_mbit"), encode_param(100, stamp, "z"))
    assert a.get("/dbm/max_bandwidth_in_mbit") == 11  # not pinned by a future stamp
    assert seen == []
    assert "ahead of this clock" in caplog.text
    a.set("/dbm/max_bandwidth_in_mbit", 5)  # and the next honest write wins as ever
    assert a.get("/dbm/max_bandwidth_in_mbit") == 5
