"""The ros1 parameter sync's pushes, delivered by the test (a fake master that pushes nothing).

The master pushes every write back, this process's own too, in the order it took them; here the
test delivers each push itself (``_param_update``, as the push endpoint does), late if it likes.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from xmlrpc.server import SimpleXMLRPCServer

import pytest

from dbml.transports.base import ParamValue
from dbml.transports.replica import Write
from dbml.transports.ros1.master import MasterClient
from dbml.transports.ros1.params import ECHO_WAIT_S, Ros1Params

TIMEOUT_S = 10.0
"""How long a test waits for the sender thread, which acts within milliseconds."""
BOUND = 8
"""The store's bound in the bound's test: a flood of a few names."""
X = "/dbm/round"
Y = "/r1/camera/dbm/priority"
ABSENT = "/dbm/status_message"
MINE = "/dbm/strategy"


class FakeMaster:
    """The calls the mirror makes: its writes are recorded and held, never pushed back."""

    def __init__(self, tree: dict[str, object]) -> None:
        self.tree = tree
        self.writes: list[tuple[str, object]] = []
        self.held: dict[str, object] = {}
        self.server = SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False, allow_none=True)
        self.uri = f"http://127.0.0.1:{self.server.server_address[1]}/"
        for name in ("subscribeParam", "unsubscribeParam", "setParam", "deleteParam"):
            self.server.register_function(getattr(self, name), name)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def subscribeParam(self, _caller: str, _api: str, _key: str) -> list[object]:  # noqa: N802
        return [1, "", self.tree]

    def unsubscribeParam(self, *_args: object) -> list[object]:  # noqa: N802
        return [1, "", 1]

    def setParam(self, _caller: str, key: str, value: object) -> list[object]:  # noqa: N802
        self.writes.append((key, value))
        self.held[key] = value
        return [1, "", 0]

    def deleteParam(self, _caller: str, key: str) -> list[object]:  # noqa: N802
        self.writes.append((key, None))
        if self.held.pop(key, None) is None:
            return [-1, f"parameter [{key}] is not set", 0]  # as rosmaster: and no push
        return [1, "", 0]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


class Clock:
    """The mirror's clock, moved by the test."""

    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


class Mirror:
    """A ``Ros1Params`` on the fake master, with what its watchers heard."""

    def __init__(self, master: FakeMaster, *, max_params: int = BOUND * 100) -> None:
        self.clock = Clock()
        self.client = MasterClient(master.uri, caller_id="/mirror_test")
        self.sync = Ros1Params(
            self.client,
            "/mirror_test",
            "127.0.0.1",
            "127.0.0.1",
            clock=self.clock,
            max_params=max_params,
        )
        self.params = self.sync.replica
        self.heard: list[tuple[str, ParamValue]] = []
        self.params.watch(lambda name, value: self.heard.append((name, value)))

    def write(self, name: str, value: ParamValue) -> None:
        """A write of this process, handed to the master."""
        self.params.set(name, value)
        assert self.params.flush(TIMEOUT_S)

    def push(self, name: str, value: object, caller: str = "/master") -> None:
        """The master's push of a write of ``name`` (``{}``: deleted)."""
        self.sync._param_update(caller, name + "/", value)


@pytest.fixture
def master() -> Iterator[FakeMaster]:
    fake = FakeMaster({"keep": 1})
    yield fake
    fake.close()


@pytest.fixture
def mirror(master: FakeMaster) -> Iterator[Mirror]:
    made = Mirror(master)
    yield made
    made.sync.close()
    made.client.close()


def test_a_late_echo_of_an_older_write_changes_nothing_and_tells_nobody(
    master: FakeMaster, mirror: Mirror
) -> None:
    mirror.write("/dbm/round", 1)
    mirror.write("/dbm/round", 2)
    mirror.write("/dbm/status", "optimal")
    mirror.write("/dbm/status", None)
    assert master.writes == [
        ("/dbm/round", 1),
        ("/dbm/round", 2),
        ("/dbm/status", "optimal"),
        ("/dbm/status", None),
    ]
    told = [("/dbm/round", 1), ("/dbm/round", 2), ("/dbm/status", "optimal"), ("/dbm/status", None)]
    assert mirror.heard == told

    mirror.push("/dbm/round", 1)  # the first write's echo, after the second was applied here
    mirror.push("/dbm/status", "optimal")
    assert mirror.params.get("/dbm/round") == 2
    assert mirror.params.get("/dbm/status") is None
    mirror.push("/dbm/round", 2)  # the newest write's own echo: no change either
    mirror.push("/dbm/status", {})
    assert mirror.params.get("/dbm/round") == 2
    assert mirror.params.get("/dbm/status") is None
    assert mirror.heard == told

    # Past its echo, the master's pushes are newer than our write: the next one applies at once.
    mirror.push("/dbm/round", 3, caller="/other")
    assert mirror.params.get("/dbm/round") == 3
    assert mirror.heard == [*told, ("/dbm/round", 3)]
    assert mirror.sync._echoes == {}  # every echo came: nothing awaited


def test_the_echoes_of_a_value_written_again_are_counted_off_in_order(mirror: Mirror) -> None:
    for value in ("optimal", "infeasible", "optimal"):
        mirror.write("/dbm/status", value)
    told = [("/dbm/status", v) for v in ("optimal", "infeasible", "optimal")]
    for value in ("optimal", "infeasible"):  # the older writes' echoes: the newest value holds
        mirror.push("/dbm/status", value)
        assert mirror.params.get("/dbm/status") == "optimal"
    mirror.push("/dbm/status", "optimal")
    assert mirror.heard == told
    assert mirror.sync._echoes == {}


def test_a_push_before_our_echo_is_older_and_after_the_wait_another_writers_applies(
    mirror: Mirror,
) -> None:
    mirror.write("/r1/camera/dbm/priority", 0.5)
    # Another writer's, taken by the master before ours (its push precedes our echo): skipped.
    mirror.push("/r1/camera/dbm/priority", 0.1, caller="/other")
    mirror.push("/r1/camera/dbm", {"priority": 0.2}, caller="/other")
    mirror.push("/r1", {}, caller="/other")
    assert mirror.params.get("/r1/camera/dbm/priority") == 0.5
    assert mirror.heard == [("/r1/camera/dbm/priority", 0.5)]

    mirror.clock.now_s += ECHO_WAIT_S  # our echo is lost: what the master pushes holds again
    mirror.push("/r1/camera/dbm/priority", 0.9, caller="/other")
    assert mirror.params.get("/r1/camera/dbm/priority") == 0.9
    assert mirror.heard == [("/r1/camera/dbm/priority", 0.5), ("/r1/camera/dbm/priority", 0.9)]


def test_the_echo_wait_starts_again_when_a_queued_write_reaches_the_master(
    master: FakeMaster, mirror: Mirror
) -> None:
    """A write held in the queue (a stalled master) longer than the wait still awaits its echo."""
    mirror.write(X, 1)
    entered, release = threading.Event(), threading.Event()
    real = mirror.sync._write

    def held(write: Write) -> None:
        entered.set()
        assert release.wait(TIMEOUT_S), "the test never released the sender"
        real(write)

    mirror.params._send = held
    mirror.params.set(X, 2)
    assert entered.wait(TIMEOUT_S)  # its send stalls; the next writes wait behind it
    mirror.params.set(Y, 0)
    mirror.params.set(X, 3)
    mirror.clock.now_s += ECHO_WAIT_S  # the queued write's wait is over before it is sent
    mirror.push(X, 1)  # the first write's echo, late: older than the writes queued
    assert mirror.params.get(X) == 3
    release.set()
    assert mirror.params.flush(TIMEOUT_S)
    assert master.writes[-3:] == [(X, 2), (Y, 0), (X, 3)]
    mirror.push(X, 2)  # the echoes, late
    assert mirror.params.get(X) == 3
    mirror.push(X, 3)
    assert mirror.heard == [(X, 1), (X, 2), (Y, 0), (X, 3)]


def test_deleting_a_name_the_master_lacks_awaits_no_echo(mirror: Mirror) -> None:
    """The master answers -1 and pushes nothing: the next push of the name is another writer's."""
    mirror.write(ABSENT, None)
    mirror.push(ABSENT, "five", caller="/other")
    assert mirror.params.get(ABSENT) == "five"
    assert mirror.heard == [(ABSENT, None), (ABSENT, "five")]


def test_the_mirror_refuses_new_names_past_its_bound_and_says_so_once_per_flood(
    master: FakeMaster, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="dbml.ros1"):
        mirror = Mirror(master, max_params=BOUND)  # the tree holds /keep
        try:
            for i in range(BOUND - 1):
                mirror.push(f"/flood/{i}", i, caller="/other")
            assert caplog.records == []
            mirror.push(f"/flood/{BOUND}", BOUND, caller="/other")  # one name too many
            mirror.push("/more", {"a": 1, "b": 2}, caller="/other")  # two more in one push
            assert mirror.params.get(f"/flood/{BOUND}") is None
            assert mirror.params.get("/more/a") is None
            assert len(mirror.params) == BOUND
            mirror.push("/keep", 2, caller="/other")  # a name held is still updated
            assert mirror.params.get("/keep") == 2
            mirror.params.set(MINE, "fair")  # and this process's own writes always taken
            assert mirror.params.get(MINE) == "fair"
            assert len(mirror.params) == BOUND + 1
            assert [r.getMessage() for r in caplog.records] == [
                f"parameter names: {BOUND} held, the most kept; refusing new ones "
                "(told once until half of them are gone)"
            ]
            assert mirror.heard == [
                *((f"/flood/{i}", i) for i in range(BOUND - 1)),
                ("/keep", 2),
                (MINE, "fair"),
            ]

            mirror.push("/flood", {}, caller="/other")  # down to half the bound: the flood is over
            assert len(mirror.params) == 2
            assert caplog.records[-1].getMessage() == (
                "parameter names: room again; 3 refused meanwhile"
            )
            mirror.push("/more", {"a": 1}, caller="/other")
            assert mirror.params.get("/more/a") == 1
        finally:
            mirror.sync.close()
            mirror.client.close()
