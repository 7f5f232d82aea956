"""The replica every store is built on, without a network: its sync is a plain function here.

zenoh's messages over it are ``test_keyed.py``'s; these are the rules every store shares and
the ones the stores ordered by arrival (ROS 1's master, rclpy's nodes) rely on.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dbml.core.errors import TransportError
from dbml.protocol.schema import ParamError, ParamValue
from dbml.transports.replica import MAX_QUEUED_WRITES, Replica, Write, check_write

log = logging.getLogger("dbml.test")
TIMEOUT_S = 10.0
PRIORITY = "/r1/camera/dbm/priority"
ROUND = "/dbm/round"


class Gate:
    """A send that blocks until opened (a stalled network), recording what it was handed."""

    def __init__(self, *, opened: bool = True) -> None:
        self.open = threading.Event()
        if opened:
            self.open.set()
        self.entered = threading.Event()
        self.sent: list[Write] = []

    def __call__(self, write: Write) -> None:
        self.entered.set()
        assert self.open.wait(TIMEOUT_S), "the test never opened the gate"
        self.sent.append(write)


def replica(send: Callable[[Write], None] | None = None, **options: object) -> Replica:
    clock = itertools.count(1_000)
    return Replica(
        "me",
        send=send or Gate(),
        log=log,
        clock_ns=lambda: next(clock),
        **options,  # type: ignore[arg-type]
    )


def record(store: Replica) -> list[tuple[str, ParamValue]]:
    seen: list[tuple[str, ParamValue]] = []
    store.watch(lambda name, value: seen.append((name, value)))
    return seen


# -- what set() refuses ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "value", "error", "message"),
    [
        (PRIORITY, [0.5], TransportError, r"^/r1/camera/dbm/priority=\[0.5\] is not a parameter"),
        (PRIORITY, {"a": 1}, TransportError, r"^/r1/camera/dbm/priority=\{'a': 1\} is not a"),
        ("/x", 1, TransportError, r"^/x=1: '/x' is not a parameter of dbml's schema"),
        ("/r1/camera/dbm/nope", 1, TransportError, r"^/r1/camera/dbm/nope=1: '/r1/camera/dbm"),
        ("r1/camera/dbm/priority", 0.5, TransportError, r"^r1/camera/dbm/priority=0.5: 'r1/"),
        ("/r1//c/dbm/priority", 0.5, TransportError, r"^/r1//c/dbm/priority=0.5: '/r1//c/"),
        (PRIORITY, 1.5, ParamError, r"^/r1/camera/dbm/priority=1.5 must be within \[0, 1\]"),
        ("/dbm/strategy", "best", ParamError, r"^/dbm/strategy='best' is not valid"),
        ("/r1/camera/dbm/managed", 1, ParamError, r"^/r1/camera/dbm/managed=1 is not valid"),
    ],
)
def test_set_refuses_a_bad_value_or_name_naming_both(
    name: str, value: object, error: type[Exception], message: str
) -> None:
    store = replica()
    with pytest.raises(error, match=message):
        check_write(name, value)
    with pytest.raises(error, match=message):
        store.set(name, value)  # type: ignore[arg-type]
    with pytest.raises(error, match=message):
        store.set_many({ROUND: 1, name: value})  # type: ignore[dict-item]
    assert store.snapshot() == {}
    assert store.unsent() == 0


def test_a_deletion_and_every_schema_value_are_taken() -> None:
    store = replica()
    store.set(PRIORITY, 0.5)
    store.set(PRIORITY, None)
    store.set_many({ROUND: 3, "/dbm/strategy": "fair", "/r1/camera/dbm/managed": False})
    assert store.snapshot() == {ROUND: 3, "/dbm/strategy": "fair", "/r1/camera/dbm/managed": False}
    with pytest.raises(TransportError, match=r"^host='a b' must be letters"):
        store.set_many({ROUND: 4}, host="a b")
    assert store.get(ROUND) == 3
    assert store.close()


def test_a_middlewares_own_name_rule_is_added() -> None:
    def no_dots(name: str) -> None:
        if "." in name:
            raise TransportError(f"{name} has a dot")

    store = replica(check_name=no_dots)
    with pytest.raises(TransportError, match=r"^/r1/cam\.front/dbm/priority has a dot"):
        store.set("/r1/cam.front/dbm/priority", 0.5)
    assert store.get("/r1/cam.front/dbm/priority") is None


def test_new_names_past_the_bound_are_refused_and_a_network_flood_never_refuses_ours() -> None:
    store = replica(max_params=3)
    for i in range(3):  # the network fills the store
        assert store.merge(f"/r{i}/c/dbm/priority", 0.1, stamp=1, writer="peer")
    assert not store.merge("/r9/c/dbm/priority", 0.1, stamp=1, writer="peer")
    assert store.refused == 1
    store.set_many({ROUND: 1, "/dbm/strategy": "fair", PRIORITY: 0.5})  # ours: counted apart
    with pytest.raises(TransportError, match=r"^/dbm/status='optimal': this process wrote 3"):
        store.set("/dbm/status", "optimal")
    with pytest.raises(TransportError, match=r"^/dbm/status=None: this process wrote 3"):
        store.set_many({ROUND: 2, "/dbm/status": None})
    assert store.get(ROUND) == 1  # nothing of a refused batch was taken
    store.set(ROUND, 5)  # a name it wrote is always written again
    assert store.get(ROUND) == 5
    assert store.close()


# -- writing never waits ------------------------------------------------------------------------


def test_a_write_is_held_and_told_before_it_is_sent_and_pending_until_then() -> None:
    gate = Gate(opened=False)
    store = replica(gate)
    seen = record(store)
    store.set(PRIORITY, 0.5)
    assert store.get(PRIORITY) == 0.5
    assert seen == [(PRIORITY, 0.5)]
    assert gate.entered.wait(TIMEOUT_S)
    assert store.pending(PRIORITY)
    assert store.wrote(PRIORITY)
    gate.open.set()
    assert store.flush(TIMEOUT_S)
    assert not store.pending(PRIORITY)
    assert [w.values for w in gate.sent] == [{PRIORITY: 0.5}]
    assert gate.sent[0].writer == "me"
    assert not gate.sent[0].batch
    assert store.close()


def test_a_failed_send_leaves_nothing_pending() -> None:
    def fail(_write: Write) -> None:
        raise TransportError("the network is gone")

    store = replica(fail)
    store.set(PRIORITY, 0.5)
    assert store.flush(TIMEOUT_S)
    assert not store.pending(PRIORITY)
    assert store.alive
    assert store.close()


def test_a_write_dropped_from_a_full_queue_is_pending_no_more() -> None:
    gate = Gate(opened=False)
    store = replica(gate)
    store.set(ROUND, 0)
    assert gate.entered.wait(TIMEOUT_S)  # in flight: the rest wait in the queue
    names = [f"/r{i}/camera/dbm/priority" for i in range(MAX_QUEUED_WRITES + 1)]
    for name in names:
        store.set(name, 0.5)
    assert not store.pending(names[0])  # dropped: the network will never have it
    assert store.arrived(names[0], 0.25, writer="master")  # so what arrives applies
    assert store.pending(names[-1])
    gate.open.set()
    assert store.close(TIMEOUT_S)


def test_a_batch_is_one_write_or_one_per_name_each_in_its_slot() -> None:
    gate = Gate(opened=False)
    batched = replica(gate)
    batched.set_many({ROUND: 1, PRIORITY: 0.5}, host="r1")
    gate.open.set()
    assert batched.flush(TIMEOUT_S)
    assert [(w.values, w.host, w.batch) for w in gate.sent] == [
        ({ROUND: 1, PRIORITY: 0.5}, "r1", True)
    ]
    assert batched.close()

    gate = Gate(opened=False)
    split = replica(gate, batches=False)
    split.set(ROUND, 0)
    assert gate.entered.wait(TIMEOUT_S)
    for value in range(1, 50):
        split.set_many({ROUND: value, PRIORITY: value / 100})
    gate.open.set()
    assert split.flush(TIMEOUT_S)
    assert [w.values for w in gate.sent] == [{ROUND: 0}, {ROUND: 49}, {PRIORITY: 0.49}]
    assert split.close()


def test_unthreaded_the_send_runs_on_the_writers_thread_after_the_watchers() -> None:
    order: list[str] = []

    def send(write: Write) -> None:
        order.append(f"sent on {threading.current_thread().name}")

    store = replica(send, threaded=False)
    store.watch(lambda name, _value: order.append(f"told {name}"))
    store.set(ROUND, 1)
    assert order == [f"told {ROUND}", f"sent on {threading.current_thread().name}"]
    assert not store.pending(ROUND)


def test_a_watcher_may_write_and_read_the_store_it_is_told_by() -> None:
    """Watchers run outside the lock: one that writes back does not deadlock."""
    store = replica()

    def write_back(name: str, _value: ParamValue) -> None:
        if name == PRIORITY:
            store.set(ROUND, 7)

    def read(_name: str, _value: ParamValue) -> None:
        store.snapshot()

    store.watch(write_back)
    store.watch(read)
    store.set(PRIORITY, 0.5)
    assert store.get(ROUND) == 7
    assert store.close()


def test_current_is_what_of_a_write_nothing_newer_replaced() -> None:
    seen: list[dict[str, ParamValue]] = []

    def send(write: Write) -> None:
        seen.append(store.current(write))

    store = replica(send)
    store.set(ROUND, 0)
    store.set_many({PRIORITY: 0.5, "/dbm/strategy": "fair"})
    assert store.flush(TIMEOUT_S)
    assert seen[-1] == {PRIORITY: 0.5, "/dbm/strategy": "fair"}
    write = Write({PRIORITY: 0.5, "/dbm/strategy": "fair"}, 1_001, "me", batch=True)
    store.arrived(PRIORITY, 0.9, writer="node", supersede=True)  # the network took a newer one
    assert store.current(write) == {"/dbm/strategy": "fair"}
    assert store.close()


# -- what arrives, by stamp and by arrival ------------------------------------------------------


def test_by_stamp_the_newest_stamp_then_writer_wins_and_ours_are_skipped() -> None:
    store = replica()
    seen = record(store)
    assert store.merge(PRIORITY, 0.1, stamp=5_000, writer="b")
    assert not store.merge(PRIORITY, 0.2, stamp=4_999, writer="z")
    assert not store.merge(PRIORITY, 0.3, stamp=5_000, writer="a")
    assert store.merge(PRIORITY, 0.4, stamp=5_000, writer="c")
    assert not store.merge(PRIORITY, 0.5, stamp=2**62, writer="me")
    assert store.merge(PRIORITY, None, stamp=5_001, writer="c")  # a deletion is held, by stamp
    assert store.entry(PRIORITY) is not None
    assert store.get(PRIORITY) is None
    assert seen == [(PRIORITY, 0.1), (PRIORITY, 0.4), (PRIORITY, None)]
    store.set(PRIORITY, 0.6)  # ours supersedes whatever stamp is held
    entry = store.entry(PRIORITY)
    assert entry is not None
    assert (entry.value, entry.stamp, entry.writer) == (0.6, 5_002, "me")


def test_by_arrival_a_push_applies_unless_our_write_of_it_is_pending() -> None:
    gate = Gate(opened=False)
    store = replica(gate)
    seen = record(store)
    assert store.arrived(ROUND, 1, writer="master")
    assert not store.arrived(ROUND, 1, writer="master")  # no change: not told again
    assert store.arrived(ROUND, True, writer="master")  # True is not 1: a change
    store.set(PRIORITY, 0.5)
    assert gate.entered.wait(TIMEOUT_S)
    assert not store.arrived(PRIORITY, 0.1, writer="master")  # older than ours, unsent
    assert not store.arrived(PRIORITY, None, writer="master")
    assert store.get(PRIORITY) == 0.5
    gate.open.set()
    assert store.flush(TIMEOUT_S)
    assert store.arrived(PRIORITY, 0.2, writer="master")  # the network has ours: newer
    assert store.arrived(PRIORITY, None, writer="master")  # a deletion forgets the name
    assert store.entry(PRIORITY) is None
    assert seen == [(ROUND, 1), (ROUND, True), (PRIORITY, 0.5), (PRIORITY, 0.2), (PRIORITY, None)]
    assert store.close()


def test_an_answer_is_older_than_what_was_written_or_heard_since_the_question() -> None:
    store = replica()
    store.arrived(ROUND, 1, writer="node")
    asked = store.mark()
    assert store.arrived(ROUND, 2, writer="node", asked_at=asked)  # nothing newer: taken
    asked = store.mark()
    store.arrived(ROUND, 3, writer="node")  # an event after the question
    assert not store.arrived(ROUND, 2, writer="node", asked_at=asked)
    store.set(PRIORITY, 0.5)
    assert store.flush(TIMEOUT_S)
    assert not store.arrived(PRIORITY, 0.1, writer="node", asked_at=asked)  # ours is newer
    assert store.get(ROUND) == 3
    assert store.get(PRIORITY) == 0.5
    assert store.close()


def test_superseding_takes_the_networks_value_over_our_pending_write() -> None:
    gate = Gate(opened=False)
    store = replica(gate)
    store.set(PRIORITY, 0.5)
    assert gate.entered.wait(TIMEOUT_S)
    assert store.arrived(PRIORITY, 0.9, writer="operator", supersede=True)
    assert not store.pending(PRIORITY)
    assert store.get(PRIORITY) == 0.9
    gate.open.set()
    assert store.close(TIMEOUT_S)


def test_forgetting_a_departed_source_keeps_what_this_process_wrote() -> None:
    store = replica()
    store.arrived("/r1/camera/dbm/frequency/min", 1.0, writer="node")
    store.arrived("/r1/camera/dbm/frequency/max", 9.0, writer="node")
    store.arrived("/r2/camera/dbm/frequency/max", 9.0, writer="node")
    store.set(PRIORITY, 0.5)
    seen = record(store)
    assert store.forget("/r1/camera/") == [
        "/r1/camera/dbm/frequency/min",
        "/r1/camera/dbm/frequency/max",
    ]
    assert store.snapshot() == {PRIORITY: 0.5, "/r2/camera/dbm/frequency/max": 9.0}
    assert seen == [("/r1/camera/dbm/frequency/min", None), ("/r1/camera/dbm/frequency/max", None)]
    assert store.close()


def test_names_from_the_network_are_bounded_by_arrival_too_and_room_ends_a_flood(
    caplog: pytest.LogCaptureFixture,
) -> None:
    store = replica(max_params=4)
    with caplog.at_level(logging.WARNING, logger="dbml.test"):
        for i in range(6):
            store.arrived(f"/flood/{i}", i, writer="master")
        assert len(store) == 4
        assert store.arrived("/flood/0", -1, writer="master")  # a name held: updated
        for i in range(3):
            store.arrived(f"/flood/{i}", None, writer="master")
    assert [r.getMessage() for r in caplog.records] == [
        "parameter names: 4 held, the most kept; refusing new ones "
        "(told once until half of them are gone)",
        "parameter names: room again; 2 refused meanwhile",
    ]


@given(st.lists(st.tuples(st.sampled_from([ROUND, PRIORITY]), st.booleans()), max_size=30))
def test_stamps_only_grow_and_a_mark_is_newer_than_every_write_before_it(
    steps: list[tuple[str, bool]],
) -> None:
    store = Replica("me", send=lambda _w: None, log=log, clock_ns=lambda: 5, threaded=False)
    last = 0
    for name, ours in steps:
        if ours:
            store.set(name, 1)
        else:
            store.arrived(name, 2 if store.get(name) == 1 else 1, writer="node")
        entry = store.entry(name)
        assert entry is not None
        assert entry.stamp > last
        last = entry.stamp
        assert store.mark() > last
        last = store.mark()


def test_watchers_hear_changes_in_the_order_they_were_made_whoever_tells_them() -> None:
    """A network merge told while a local write lands: the write is heard after, never before.

    Two threads that each told their own change could tell them in the other order than made,
    and a reader (``ParamView``) would keep the older value for good.
    """
    store = replica()
    seen: list[ParamValue] = []
    when_written: list[ParamValue] = []

    def watcher(name: str, value: ParamValue) -> None:
        seen.append(value)
        if value == 0.2:  # while the merge of 0.2 is being told, another thread writes 0.9
            thread = threading.Thread(target=store.set, args=(PRIORITY, 0.9))
            thread.start()
            thread.join(TIMEOUT_S)
            when_written.extend(seen)

    store.watch(watcher)
    assert store.merge(PRIORITY, 0.2, stamp=1, writer="peer")
    assert when_written == [0.2]  # the write's change waited for this one to be told
    assert seen == [0.2, 0.9]
    assert store.get(PRIORITY) == 0.9


def test_a_write_made_by_a_watcher_is_heard_after_the_change_it_answers() -> None:
    store = replica()
    heard: list[tuple[str, ParamValue]] = []

    def answer(name: str, value: ParamValue) -> None:
        heard.append((name, value))
        if name == PRIORITY:
            store.set(ROUND, 1)  # as a publisher acknowledges an allocation from its callback

    store.watch(answer)
    store.watch(lambda name, value: heard.append(("second", value)))
    store.set(PRIORITY, 0.5)
    assert heard == [(PRIORITY, 0.5), ("second", 0.5), (ROUND, 1), ("second", 1)]


# -- reading by prefix ----------------------------------------------------------------------------

_NAMES = [f"/r{r}/c{c}/dbm/priority" for r in (1, 2, 12) for c in (0, 1)] + [ROUND]
_OPS = st.lists(
    st.tuples(
        st.sampled_from(["set", "merge", "arrived", "forget", "evict"]),
        st.sampled_from(_NAMES),
        st.sampled_from([None, 0.25, 0.5]),
    ),
    max_size=60,
)


@given(_OPS, st.sampled_from(["", "/", "/r1", "/r1/", "/r1/c1", "/r12/c0/dbm/", "/dbm/", "/x"]))
def test_a_prefix_reads_what_a_look_at_every_name_finds(
    ops: list[tuple[str, str, float | None]], prefix: str
) -> None:
    # The store's sorted index against a brute-force filter of everything it holds, after any
    # mix of writes, network writes, deletions, departures and evictions (3 names at most).
    store = replica(max_params=3)
    store.keep = lambda _name: False  # a full store gives up its oldest network name
    candidates = set(_NAMES)
    for stamp, (op, name, value) in enumerate(ops, start=1):
        if op == "set" and value is not None:
            with contextlib.suppress(TransportError):
                store.set(name, value)
        elif op == "merge":
            store.merge(name, value, stamp=stamp, writer="peer")
        elif op == "arrived":
            store.arrived(name, value, writer="peer")
        elif op == "forget":
            store.forget(name.rsplit("/", 3)[0])
        else:
            candidates.add(f"/r9/c{stamp}/dbm/priority")
            store.merge(f"/r9/c{stamp}/dbm/priority", 0.5, stamp=stamp, writer="peer")
    held = {name: entry for name in candidates if (entry := store.entry(name)) is not None}
    assert store.entries(prefix) == sorted(
        (name, entry) for name, entry in held.items() if name.startswith(prefix)
    )
    assert store.snapshot(prefix or "/") == {
        name: entry.value
        for name, entry in held.items()
        if name.startswith(prefix or "/") and entry.value is not None
    }
