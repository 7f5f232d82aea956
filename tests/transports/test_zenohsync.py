"""The parameter sync's bookkeeping under a flood of peers, on a fake zenoh session.

The fake records what would go on the network and can hold the sync thread still (its poll
for links waits on an event), so what is queued stays queued while the test fills it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import cast

import pytest
import zenoh

from dbml.protocol import keys
from dbml.transports.worker import death_count
from dbml.transports.zenoh.params import (
    MAX_QUEUED_FETCHES,
    MAX_SESSIONS,
    ParamSync,
    _name_prefix,
)
from tests.conftest import wait_for

TIMEOUT_S = 10.0


class _Declared:
    def undeclare(self) -> None:
        pass


class _Info:
    def __init__(self, session: FakeSession) -> None:
        self._session = session

    def zid(self) -> str:
        return "f00d"

    def peers_zid(self) -> list[str]:
        session = self._session
        session.polled.set()
        assert session.running.wait(TIMEOUT_S), "the test never let the sync thread run"
        if session.fail is not None:
            fail, session.fail = session.fail, None
            raise fail
        return []


class FakeSession:
    """What ``ParamSync`` uses of a zenoh session; queries are recorded, never answered.

    The sync thread runs only while ``running`` is set; ``fail`` is raised once from its next
    poll for links.
    """

    def __init__(self) -> None:
        self.info = _Info(self)
        self.running = threading.Event()
        self.polled = threading.Event()
        self.fail: BaseException | None = None
        self.gets: list[str] = []
        self._lock = threading.Lock()

    def declare_subscriber(self, *_args: object, **_kwargs: object) -> _Declared:
        return _Declared()

    def declare_queryable(self, *_args: object, **_kwargs: object) -> _Declared:
        return _Declared()

    def declare_token(self, *_args: object, **_kwargs: object) -> _Declared:
        return _Declared()

    def liveliness(self) -> FakeSession:
        return self

    def get(self, selector: str, *_args: object, **_kwargs: object) -> None:
        with self._lock:
            self.gets.append(selector)

    def put(self, *_args: object, **_kwargs: object) -> None:
        pass


@dataclass(frozen=True)
class FakeSample:
    key_expr: str
    kind: zenoh.SampleKind


@pytest.fixture
def session() -> Iterator[FakeSession]:
    fake = FakeSession()
    yield fake
    fake.running.set()  # never leave the sync thread waiting


def sync_of(session: FakeSession, *, follow_all: bool = True) -> ParamSync:
    return ParamSync(
        cast(zenoh.Session, session),
        "0123456789abcdef",
        host="h1",
        follow_all=follow_all,
        priority=zenoh.Priority.INTERACTIVE_HIGH,
    )


def node(i: int) -> str:
    return f"{i:016x}"


def token(
    i: int, zid: str | None = None, *, gone: bool = False, follows_all: bool = True
) -> zenoh.Sample:
    kind = zenoh.SampleKind.DELETE if gone else zenoh.SampleKind.PUT
    key = keys.node_key(node(i), zid or f"{i:x}", follows_all=follows_all)
    return cast(zenoh.Sample, FakeSample(key, kind))


def told(caplog: pytest.LogCaptureFixture, text: str) -> Callable[[], int]:
    return lambda: sum(text in record.getMessage() for record in caplog.records)


def test_sessions_met_are_bounded_and_a_flood_is_logged_once(
    session: FakeSession, caplog: pytest.LogCaptureFixture
) -> None:
    sync = sync_of(session)
    try:
        with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
            for i in range(MAX_SESSIONS + 100):
                sync._on_node(token(i))
            assert len(sync._live) == MAX_SESSIONS
            assert len(sync._zids) == MAX_SESSIONS
            assert len(sync._meet_again) <= MAX_SESSIONS
            assert sync._is_live(node(0))
            assert not sync._is_live(node(MAX_SESSIONS))  # refused: served as a writer gone
            refused = told(caplog, "dbml sessions met: 4096 held, the most kept; refusing")
            assert refused() == 1
            # Half of them leave: the flood is over, said once with its count.
            for i in range(MAX_SESSIONS // 2):
                sync._on_node(token(i, gone=True))
            assert told(caplog, "dbml sessions met: room again; 100 refused meanwhile")() == 1
            assert len(sync._live) == len(sync._zids) == MAX_SESSIONS // 2
    finally:
        session.running.set()
        sync.close()


def test_two_robots_do_not_meet_but_each_meets_whoever_follows_everything(
    session: FakeSession,
) -> None:
    """A fleet's start: robots meet the optimizer, not each other.

    A robot's graph entries are nothing for another robot to fetch.
    """
    robot = sync_of(session, follow_all=False)
    try:
        assert session.polled.wait(TIMEOUT_S)  # the sync thread holds still from now on
        robot._on_node(token(1, follows_all=False))  # another robot
        robot.fetch_owner_of(f"{node(1)}.1", "/r1/camera")  # its publisher's graph entry
        assert robot._queued == {}
        assert robot._is_live(node(1))  # known alive all the same (its values are its to serve)
        robot._on_node(token(2, follows_all=True))  # the optimizer
        assert set(robot._queued) == {(node(2), True), (node(2), False)}
    finally:
        session.running.set()
        robot.close()


def test_the_side_that_follows_everything_repeats_a_meeting(session: FakeSession) -> None:
    """A meeting goes both ways: the optimizer's repeat does for the robot's too."""
    robot, optimizer = sync_of(session, follow_all=False), sync_of(session)
    try:
        assert session.polled.wait(TIMEOUT_S)  # the sync threads hold still from now on
        robot._on_node(token(2, follows_all=True))
        optimizer._on_node(token(1, follows_all=False))
        assert robot._meet_again == {}
        assert set(optimizer._meet_again) == {node(1)}
        assert (node(2), True) in robot._queued  # each still tells the other to fetch
        assert (node(1), True) in optimizer._queued
    finally:
        session.running.set()
        robot.close()
        optimizer.close()


def test_a_session_churning_its_tokens_leaves_nothing_behind(session: FakeSession) -> None:
    """A node id met under one zenoh id and withdrawn under another forgets both."""
    sync = sync_of(session)
    try:
        for i in range(3 * MAX_SESSIONS):
            sync._on_node(token(i, "aa"))
            sync._on_node(token(i, "bb"))  # the same session again: ignored
            sync._on_node(token(i, "bb", gone=True))
        assert sync._live == {}
        assert sync._zids == {}
        assert sync._meet_again == {}
    finally:
        session.running.set()
        sync.close()


def test_queued_fetches_are_bounded_and_a_flood_is_logged_once(
    session: FakeSession, caplog: pytest.LogCaptureFixture
) -> None:
    """Pulls and graph entries of made-up sessions cannot queue more than the bound."""
    sync = sync_of(session)
    try:
        with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
            assert session.polled.wait(TIMEOUT_S)  # the sync thread holds still from now on
            for i in range(MAX_QUEUED_FETCHES + 100):
                sync.fetch_owner_of(f"{node(i)}.1", "/t")
                sync.fetch_owner_of(f"{node(i)}.2", "/t")  # one fetch per session already queued
            assert len(sync._queued) == MAX_QUEUED_FETCHES
            assert sync._fetching == MAX_QUEUED_FETCHES
            refused = told(caplog, "parameter fetches queued: 8192 held, the most kept; refusing")
            assert refused() == 1
            session.running.set()
            # Two requests for each of the 100 sessions past the bound.
            over = told(caplog, "parameter fetches queued: room again; 200 refused meanwhile")
            wait_for(lambda: over() == 1, timeout_s=TIMEOUT_S, what="the queue to drain")
            wait_for(lambda: not sync._queued, timeout_s=TIMEOUT_S, what="every fetch sent")
        assert refused() == 1
        assert over() == 1
        assert len(session.gets) == MAX_QUEUED_FETCHES  # each session asked once
    finally:
        sync.close()


def test_the_sync_thread_survives_a_failure_and_reports_its_death(
    session: FakeSession, caplog: pytest.LogCaptureFixture
) -> None:
    sync = sync_of(session)
    try:
        session.fail = RuntimeError("one bad poll")
        session.running.set()
        sync.fetch_owner_of(f"{node(1)}.1", "/t")
        wait_for(lambda: not sync._queued, timeout_s=TIMEOUT_S, what="the fetch after a failure")
        assert sync.alive
        assert "parameter sync" in caplog.text
        deaths = death_count()
        session.fail = SystemExit("not an Exception: it ends the thread")
        wait_for(lambda: not sync.alive, timeout_s=TIMEOUT_S, what="the thread's death")
        assert death_count() == deaths + 1
        assert "dbml-param-sync: the thread died" in caplog.text
    finally:
        sync.close()


def test_a_channel_subscriber_declared_as_the_sync_closes_is_undeclared_outside_the_lock(
    session: FakeSession, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whoever waits for the sync's lock must not wait for a middleware call."""
    sync = ParamSync(
        cast(zenoh.Session, session),
        "0123456789abcdef",
        host="h1",
        follow_all=False,
        priority=zenoh.Priority.INTERACTIVE_HIGH,
    )
    session.running.set()
    locked_at_undeclare: list[bool] = []

    class Declared(_Declared):
        def undeclare(self) -> None:
            locked_at_undeclare.append(sync._lock.locked())

    def declare_closing(*_args: object, **_kwargs: object) -> _Declared:
        sync.close()  # while the channel's subscriber is declared: ``_follow`` holds no lock
        return Declared()

    monkeypatch.setattr(session, "declare_subscriber", declare_closing)
    sync._follow(keys.param_key("/r1/cam/dbm/min_rate"))
    assert locked_at_undeclare == [False]
    assert sync._declared == []
    assert session.gets == []  # nothing asked for a channel no longer heard


@pytest.mark.parametrize(
    ("selector", "prefix"),
    [
        ("dbml/own/n1/r1/cam/**", "/r1/cam"),  # a robot's question: its channel's values
        ("dbml/own/n1/dbm/**", "/dbm"),  # the global values
        ("dbml/own/n1/**", ""),  # everything (a session that follows everything)
        ("dbml/own/n1/r1/$*/dbm/priority", "/r1"),  # a sub-chunk wildcard
        ("dbml/own/n1/dbm/round", "/dbm/round"),  # one name
        ("dbml/own/n12/dbm/**", ""),  # another session whose id starts with this one's
        ("dbml/own/*/dbm/**", ""),  # every session's: the key expression decides alone
        ("dbml/own/n1", ""),
    ],
)
def test_a_question_encodes_only_what_its_literal_prefix_selects(
    selector: str, prefix: str
) -> None:
    assert _name_prefix(selector, keys.own_key("n1")) == prefix
