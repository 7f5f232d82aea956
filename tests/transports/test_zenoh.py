"""The zenoh transport's own bookkeeping, on loopback."""

from __future__ import annotations

import functools
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import pytest
import zenoh

from dbml.harness.processes import free_port
from dbml.protocol import keys, names
from dbml.runtime.priority import PRIORITY_INTERVAL_S, PriorityTopic
from dbml.transports import ParamValue, Role, Variant
from dbml.transports.codecs import encode_float64
from dbml.transports.zenoh.transport import (
    LEASE_MS,
    MAX_GRAPH_ENTRIES,
    NET_THREADS,
    OPEN_TIMEOUT_MS,
    RETRY_MAX_MS,
    ROUTER_RX_THREADS,
    RUNTIME_ENV,
    RX_THREADS,
    ZenohTransport,
    _config,
    _ZenohGraph,
    open_router,
    prepare_runtime,
)
from tests.conftest import wait_for


def test_closed_declarations_are_forgotten() -> None:
    with ZenohTransport(host="solo", port=free_port()) as transport:
        baseline = len(transport._declared)
        for variant in [Variant.FULL, Variant.OPTIMIZED] * 5:  # a subscriber flipping variants
            transport.subscribe("/r1/camera", lambda _s: None, variant).close()
            transport.declare_publisher("/r1/camera", variant).close()
        assert len(transport._declared) == baseline
        kept = transport.subscribe("/r1/camera", lambda _s: None)
        assert len(transport._declared) == baseline + 1
        kept.close()
        kept.close()
        assert len(transport._declared) == baseline
    assert transport._declared == set()


def mesh(port: int, *hosts: str) -> list[ZenohTransport]:
    return [ZenohTransport(host=host, port=port) for host in hosts]


def close_all(transports: list[ZenohTransport]) -> None:
    for transport in transports:
        transport.close()


def test_writes_from_callbacks_under_a_flood_never_stall() -> None:
    """Every received write is acknowledged by a write made on zenoh's callback thread.

    A blocking put there, looped back into the session's own full callback queue, once
    deadlocked a fleet of 40: this floods both ways and asserts progress to the end.
    """
    port = free_port()
    flooder, acker = sessions = mesh(port, "base", "r1")
    try:
        assert acker.wait_for_peers(10)
        assert flooder.wait_for_peers(10)
        writes = 3_000
        acked = threading.Event()

        def ack(name: str, value: ParamValue) -> None:
            if name.startswith("/flood") and name.endswith("/dbm/priority"):
                channel = name.removesuffix("/dbm/priority")
                acker.params.set(names.applied(channel), 1.0)  # on the callback thread

        last = names.applied(f"/flood{writes - 1}/c")
        acker.params.watch(ack)
        flooder.params.watch(lambda name, _v: acked.set() if name == last else None)
        for i in range(writes):
            flooder.params.set(names.priority(f"/flood{i}/c"), 0.5)
        assert acked.wait(60), "the acknowledgements stalled"
        wait_for(
            lambda: sum(n.endswith("/applied_value") for n in flooder.params.snapshot()) == writes,
            timeout_s=30,
            what="every acknowledgement",
        )
    finally:
        close_all(sessions)


MEETINGS_PER_JOIN = 8
"""The most fetches a join makes of one session. Each side meets the other when it hears its
token and again when their direct link comes up, and repeats each meeting once a second later
(a repeat pending is replaced, one that fired is not): four meetings a side at most, and a
meeting by either side makes the newcomer fetch (its own, or the pull it is sent). CI once
counted 5 at one session when the bound said 4 (the other side's repeat was left out)."""


def test_a_newcomer_costs_each_session_answers_of_its_own_values_only() -> None:
    """A join costs each session a constant: answers of its own values, never its whole cache."""
    port = free_port()
    old = mesh(port, *(f"r{i}" for i in range(5)))
    try:
        for i, transport in enumerate(old):
            for field in ("frequency/min", "frequency/max", "priority"):
                transport.params.set(f"/r{i}/camera/dbm/{field}", 1.0)
        wait_for(
            lambda: all(
                len(t.params.snapshot()) == 15 and len(t._sync._live) == 4 and settled(t)
                for t in old
            ),
            timeout_s=20,
            what="every session holding every value, done meeting the others",
        )
        answered: list[int] = []
        for transport in old:
            owned = transport._sync.keyed.owned

            def counting(
                is_live: Callable[[str], bool],
                owned: Callable[..., list[tuple[str, bytes]]] = owned,
                *,
                prefix: str = "",
            ) -> list[tuple[str, bytes]]:
                answer = owned(is_live, prefix=prefix)
                answered.append(len(answer))
                return answer

            transport._sync.keyed.owned = counting  # type: ignore[method-assign]
        with ZenohTransport(host="late", port=port) as late:
            assert late.wait_for_peers(10)
            wait_for(
                lambda: len(late.params.snapshot()) == 15,
                timeout_s=20,
                what="the newcomer holding every value",
            )
            wait_for(lambda: len(answered) >= 5, timeout_s=10, what="every session answering")
            wait_for(lambda: settled(late), timeout_s=10, what="the newcomer done meeting")
            # Each session answers with its own three values only, and a constant number of
            # times (``MEETINGS_PER_JOIN``), whatever it holds of the others'.
            assert set(answered) == {3}
            assert len(answered) <= MEETINGS_PER_JOIN * 5
    finally:
        close_all(old)


def test_a_publishing_session_hears_its_own_channels_not_the_fleets_reports() -> None:
    """``follow_all_params=False``: globals, its host's batches and its own channels' writes.

    Other channels' writes are not delivered to it: each one cost every robot of a fleet a
    callback (40 acknowledgements per rate change, to 42 sessions, at 40 x 4).
    """
    port = free_port()
    fleet = ZenohTransport(host="base", port=port)
    robot = ZenohTransport(host="r1", port=port, follow_all_params=False)
    try:
        assert robot.wait_for_peers(10)
        assert fleet.wait_for_peers(10)
        delivered: list[str] = []
        on_write = robot._sync.keyed.on_write

        def record(key: str, data: bytes) -> None:
            delivered.append(key)
            on_write(key, data)

        robot._sync.keyed.on_write = record  # type: ignore[method-assign]
        robot.params.set("/r1/cam/dbm/frequency/max", 10.0)  # now it hears /r1/cam's parameters
        wait_for(lambda: fleet.params.get("/r1/cam/dbm/frequency/max") == 10.0, timeout_s=10)
        fleet.params.set("/r2/cam/dbm/frequency/applied_value", 3.0)  # another robot's report
        fleet.params.set("/r1/cam/dbm/message_size_in_bytes", 1)  # a write over its own channel
        fleet.params.set_many({"/r1/cam/dbm/frequency/current_value": 4.0}, host="r1")
        fleet.params.set_many({"/r2/cam/dbm/frequency/current_value": 5.0}, host="r2")
        before_ns = time.time_ns()
        fleet.params.set_many({"/dbm/round": 3})  # the batch for everyone
        fleet.params.set("/dbm/max_bandwidth_in_mbit", 7.0)  # a global, sent last
        wait_for(lambda: robot.params.get("/dbm/max_bandwidth_in_mbit") == 7.0, timeout_s=10)
        wait_for(lambda: robot.params.get("/r1/cam/dbm/message_size_in_bytes") == 1, timeout_s=10)
        assert robot.params.get("/r1/cam/dbm/frequency/current_value") == 4.0  # its host's batch
        assert robot.params.get("/dbm/round") == 3
        stamp = robot.param_stamp_ns("/dbm/round")  # the writer's clock: the same host here
        assert stamp is not None
        assert before_ns <= stamp <= time.time_ns()
        assert robot.param_stamp_ns("/dbm/never_written") is None
        assert robot.params.get("/r2/cam/dbm/frequency/current_value") is None  # r2's batch
        assert "dbml/param/r2/cam/dbm/frequency/applied_value" not in delivered
        assert "dbml/param/r1/cam/dbm/message_size_in_bytes" in delivered
        # What it paid for, as the fleet bench counts it: each write delivered, and its host's
        # and everyone's batch, not r2's.
        assert robot.control_messages_received >= len(delivered) + 2
        assert robot.control_bytes_received >= robot.control_messages_received
    finally:
        close_all([robot, fleet])


def settled(session: ZenohTransport) -> bool:
    """No meeting due, none queued and no fetch waiting for its answers."""
    sync = session._sync
    with sync._lock:
        return not sync._meet_again and sync._fetching == 0 and not sync._queued


def test_a_publishing_session_fetches_its_channels_values_when_it_starts_hearing_them() -> None:
    """A write to a channel made while nobody there listened is fetched from its owner."""
    port = free_port()
    fleet = ZenohTransport(host="base", port=port)
    robot = ZenohTransport(host="r1", port=port, follow_all_params=False)
    try:
        assert robot.wait_for_peers(10)
        assert fleet.wait_for_peers(10)
        # After the meetings, their repetition and their fetches, nothing fetches everything.
        wait_for(lambda: settled(robot) and settled(fleet), timeout_s=10, what="the meetings")
        fleet.params.set("/r1/cam/dbm/priority", 0.3)
        assert fleet.params.flush(5)
        assert robot.params.get("/r1/cam/dbm/priority") is None  # not heard: not followed yet
        robot.params.set("/r1/cam/dbm/frequency/max", 10.0)
        wait_for(lambda: robot.params.get("/r1/cam/dbm/priority") == 0.3, timeout_s=10)
    finally:
        close_all([robot, fleet])


class _Token:
    def undeclare(self) -> None:
        pass


class _FakeLiveliness:
    def liveliness(self) -> _FakeLiveliness:
        return self

    def declare_token(self, _key: str) -> _Token:
        return _Token()


class _FakeTransport:
    """What the graph uses of its transport: who it is, and the fetch a new entry asks for."""

    node_id = "0123456789abcdef"
    host = "base"

    def __init__(self) -> None:
        self.session = _FakeLiveliness()
        self.fetched: list[str] = []

    def fetch_owner_of(self, uid: str, topic: str) -> None:
        self.fetched.append(uid)


@dataclass(frozen=True)
class _FakeSample:
    key_expr: str
    kind: zenoh.SampleKind


def _graph_token(i: int, *, gone: bool = False) -> zenoh.Sample:
    key = keys.graph_key(
        Role.PUBLISHER.value, "r1", f"{i:016x}.1", Variant.FULL.value, f"/r1/cam{i}"
    )
    kind = zenoh.SampleKind.DELETE if gone else zenoh.SampleKind.PUT
    return cast(zenoh.Sample, _FakeSample(key, kind))


@pytest.mark.parametrize(
    "key",
    [
        "dbml/graph/pub/r1/x.1/bogus/r1/cam",  # no such variant
        "dbml/graph/nope/r1/x.1/full/r1/cam",  # no such role
        "dbml/graph/pub/r 1/x.1/full/r1/cam",  # not a host name
        "dbml/graph/pub/r1",  # too short
    ],
)
def test_a_malformed_graph_token_is_no_entry(key: str) -> None:
    transport = _FakeTransport()
    graph = _ZenohGraph(cast(ZenohTransport, transport))
    graph.on_sample(cast(zenoh.Sample, _FakeSample(key, zenoh.SampleKind.PUT)))
    assert graph.entries() == frozenset()
    assert transport.fetched == []


def test_the_graph_read_twice_unchanged_is_one_snapshot_and_any_change_makes_a_new_one() -> None:
    """The optimizer reads the graph every round and summarizes it only when it changed."""
    graph = _ZenohGraph(cast(ZenohTransport, _FakeTransport()))
    graph.on_sample(_graph_token(1))
    first = graph.entries()
    assert graph.entries() is first
    graph.on_sample(_graph_token(2))
    second = graph.entries()
    assert second is not first
    assert {e.topic for e in second} == {"/r1/cam1", "/r1/cam2"}
    graph.on_sample(_graph_token(1, gone=True))
    assert {e.topic for e in graph.entries()} == {"/r1/cam2"}
    mine = graph.announce(Role.PUBLISHER, "/base/cam", Variant.FULL)
    assert {e.topic for e in graph.entries()} == {"/r1/cam2", "/base/cam"}
    mine.close()
    assert {e.topic for e in graph.entries()} == {"/r1/cam2"}


def test_graph_entries_from_peers_are_bounded_and_a_flood_is_logged_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    transport = _FakeTransport()
    graph = _ZenohGraph(cast(ZenohTransport, transport))
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        for i in range(MAX_GRAPH_ENTRIES + 100):
            graph.on_sample(_graph_token(i))
        assert len(graph.entries()) == MAX_GRAPH_ENTRIES
        assert len(transport.fetched) == MAX_GRAPH_ENTRIES  # a refused entry fetches nothing
        # This process's own declarations are always in its graph (its code bounds them).
        mine = graph.announce(Role.PUBLISHER, "/base/cam", Variant.FULL)
        assert any(e.topic == "/base/cam" for e in graph.entries())
        assert len(graph.entries()) == MAX_GRAPH_ENTRIES + 1
        for i in range(MAX_GRAPH_ENTRIES // 2 + 1):
            graph.on_sample(_graph_token(i, gone=True))
        mine.close()
    messages = [record.getMessage() for record in caplog.records]
    assert messages == [
        "graph entries: 16384 held, the most kept; refusing new ones "
        "(told once until half of them are gone)",
        "graph entries: room again; 100 refused meanwhile",
    ]
    assert len(graph.entries()) == MAX_GRAPH_ENTRIES // 2 - 1


def test_a_publishing_session_hears_the_graph_of_the_topics_it_reads_alone() -> None:
    """Every robot of a fleet hearing every graph token cost each one a callback per token.

    A publisher hears none (its own declarations aside); a subscriber its topics'.
    """
    port = free_port()
    fleet = ZenohTransport(host="base", port=port)
    robot = ZenohTransport(host="r1", port=port, follow_all_params=False)
    try:
        assert robot.wait_for_peers(10)
        fleet.graph.announce(Role.SUBSCRIBER, "/r2/cam", Variant.OPTIMIZED)  # another robot's
        fleet.graph.announce(Role.SUBSCRIBER, "/r1/cam", Variant.OPTIMIZED)  # before the robot
        robot.graph.announce(Role.PUBLISHER, "/r1/cam", Variant.FULL)
        woken: list[int] = []
        robot.graph.watch(lambda: woken.append(1), topic="/r1/lidar")
        fleet.graph.announce(Role.SUBSCRIBER, "/r1/lidar", Variant.OPTIMIZED)  # a watched topic
        wait_for(lambda: bool(woken), timeout_s=10, what="the watched topic's token")
        fleet.graph.announce(Role.SUBSCRIBER, "/r2/lidar", Variant.OPTIMIZED)
        wait_for(lambda: len(fleet.graph.entries()) == 5, timeout_s=10, what="the fleet's graph")
        late = fleet.graph.announce(Role.SUBSCRIBER, "/r1/lidar", Variant.FULL)  # after the rest
        wait_for(lambda: len(robot.graph.entries(topic="/r1/lidar")) == 2, timeout_s=10)
        # Its own publisher, the watched topic's two subscribers; not the operator's of /r1/cam.
        assert sorted((e.host, e.topic, e.variant.value) for e in robot.graph.entries()) == [
            ("base", "/r1/lidar", "full"),
            ("base", "/r1/lidar", "optimized"),
            ("r1", "/r1/cam", "full"),
        ]
        # Read, a topic is followed from then on, with what was declared before.
        wait_for(
            lambda: any(e.host == "base" for e in robot.graph.entries(topic="/r1/cam")),
            timeout_s=10,
            what="the operator's subscriber of /r1/cam, declared before the robot read it",
        )
        late.close()
        wait_for(lambda: len(robot.graph.entries(topic="/r1/lidar")) == 1, timeout_s=10)
    finally:
        close_all([robot, fleet])


def test_a_robot_hears_the_sessions_that_follow_everything_not_other_robots() -> None:
    """Each robot hearing every other's session token was quadratic in the fleet at its start."""
    port = free_port()
    fleet = ZenohTransport(host="base", port=port)
    robots = [ZenohTransport(host=f"r{i}", port=port, follow_all_params=False) for i in range(1, 3)]
    try:
        for robot in robots:
            assert robot.wait_for_peers(10)
        wait_for(lambda: len(fleet._sync._live) == 2, timeout_s=10, what="both robots met")
        late = ZenohTransport(host="r3", port=port, follow_all_params=False)
        robots.append(late)
        wait_for(lambda: len(fleet._sync._live) == 3, timeout_s=10, what="the third robot")
        for robot in robots:  # a token heard would be in ``_live`` (met or not)
            assert set(robot._sync._live) == {fleet._sync.node_id}, robot.host
    finally:
        close_all([*robots, fleet])


def test_a_topics_watchers_wake_for_that_topic_alone() -> None:
    """A subscriber per channel of a fleet: one change wakes one, not every subscriber."""
    graph = _ZenohGraph(cast(ZenohTransport, _FakeTransport()))
    woken: list[str] = []
    graph.watch(lambda: woken.append("all"))
    for topic in ("/r1/cam0", "/r1/cam1", "/r1/cam2"):
        graph.watch(functools.partial(woken.append, topic), topic=topic)
    graph.on_sample(_graph_token(1))
    assert woken == ["all", "/r1/cam1"]
    assert {e.topic for e in graph.entries(topic="/r1/cam1")} == {"/r1/cam1"}
    assert graph.entries(topic="/r1/cam2") == frozenset()
    woken.clear()
    mine = graph.announce(Role.SUBSCRIBER, "/r1/cam2", Variant.OPTIMIZED)
    mine.close()
    graph.on_sample(_graph_token(1, gone=True))
    assert woken == ["all", "/r1/cam2", "all", "/r1/cam2", "all", "/r1/cam1"]
    assert graph.entries() == frozenset()
    assert graph.entries(topic="/r1/cam1") == frozenset()


def test_the_receiving_runtime_gets_its_threads_unless_the_user_chose(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(RUNTIME_ENV, "")  # recorded, so the test leaves it as it found it
    monkeypatch.delenv(RUNTIME_ENV)
    prepare_runtime()
    assert os.environ[RUNTIME_ENV] == (
        f"(rx: (worker_threads: {RX_THREADS}), net: (worker_threads: {NET_THREADS}))"
    )
    monkeypatch.setenv(RUNTIME_ENV, "(app: (worker_threads: 2))")
    prepare_runtime()
    assert os.environ[RUNTIME_ENV] == "(app: (worker_threads: 2))"


def test_a_router_gets_a_receiving_thread_per_link_of_a_fleet() -> None:
    """Its first session decides: a router's process, as ``dbml router`` starts it."""
    code = (
        "import os, sys\n"
        "from dbml.transports.zenoh.transport import open_router\n"
        "open_router([sys.argv[1]]).close()\n"
        f"print(os.environ[{RUNTIME_ENV!r}])\n"
    )
    env = {k: v for k, v in os.environ.items() if k != RUNTIME_ENV}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    done = subprocess.run(
        [sys.executable, "-c", code, endpoint],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == (
        f"(rx: (worker_threads: {ROUTER_RX_THREADS}), net: (worker_threads: {NET_THREADS}))"
    )
    assert ROUTER_RX_THREADS > RX_THREADS


def test_sessions_drop_a_lost_peer_soon_and_retry_a_returning_one_often() -> None:
    config = _config(
        connect=["tcp/127.0.0.1:7000"],
        listen=[],
        config_file=None,
        shared_memory=False,
        port=1,
        host="r1",
    )
    assert json.loads(config.get_json("transport/link/tx/lease")) == LEASE_MS < 10_000
    assert json.loads(config.get_json("transport/unicast/open_timeout")) == OPEN_TIMEOUT_MS
    assert json.loads(config.get_json("connect/retry"))["period_max_ms"] == RETRY_MAX_MS


def test_a_session_declares_its_hosts_namespace_once(tmp_path: Path) -> None:
    """Its publishers share one interest, its channels' parameters one subscription.

    A router matches each declaration against every face's interests, under one lock.
    """
    aggregated = functools.partial(
        _config, connect=[], listen=[], shared_memory=False, port=1, host="r1"
    )
    config = aggregated(config_file=None)
    assert json.loads(config.get_json("aggregation/publishers")) == ["r1/**"]
    assert json.loads(config.get_json("aggregation/subscribers")) == [
        "dbml/param/r1/**",
        "r1/**/dbm/priority",
    ]
    users = tmp_path / "users.json5"
    users.write_text('{mode: "client", aggregation: {publishers: ["fleet/**"]}}')
    config = aggregated(config_file=users)
    assert json.loads(config.get_json("aggregation/publishers")) == ["fleet/**"]  # the user's
    assert json.loads(config.get_json("aggregation/subscribers")) == [
        "dbml/param/r1/**",
        "r1/**/dbm/priority",
    ]


def test_through_a_router_each_aggregated_publisher_knows_its_own_subscribers(
    tmp_path: Path,
) -> None:
    """What the aggregation must not change: which publisher has a subscriber, what is heard."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = tmp_path / "client.json5"
    client.write_text('{mode: "client"}')
    router = open_router([endpoint])
    robot = ZenohTransport(
        host="r1", connect=[endpoint], config_file=client, follow_all_params=False
    )
    operator = ZenohTransport(host="op", connect=[endpoint], config_file=client)
    try:
        heard: list[bytes] = []
        operator.subscribe("/r1/a", lambda sample: heard.append(sample.payload), Variant.FULL)
        a = robot.declare_publisher("/r1/a")
        b = robot.declare_publisher("/r1/b")
        wait_for(lambda: a.has_subscribers, what="/r1/a's subscriber")
        assert not b.has_subscribers  # the one interest brought /r1/a's subscriber only
        wait_for(lambda: (a.put(b"frame"), heard)[1] != [], what="/r1/a's frame")
        operator.subscribe("/r1/b", lambda sample: None, Variant.FULL)
        wait_for(lambda: b.has_subscribers, what="/r1/b's subscriber")
        # Parameters: the robot hears the channels it writes to, and only those.
        robot.params.set(names.max_rate("/r1/a"), 16.0)
        operator.params.set(names.current_value("/r1/c"), 3.0)
        operator.params.set(names.current_value("/r1/a"), 5.0)
        wait_for(
            lambda: robot.params.get(names.current_value("/r1/a")) == 5.0,
            what="/r1/a's rate at the robot",
        )
        assert robot.params.get(names.current_value("/r1/c")) is None
        # A priority topic's subscription, aggregated too, still gets its messages.
        priorities: list[bytes] = []
        robot.subscribe("/r1/a/dbm/priority", lambda sample: priorities.append(sample.payload))
        source = operator.declare_publisher("/r1/a/dbm/priority")
        wait_for(lambda: source.has_subscribers, what="the robot's priority subscription")
        wait_for(lambda: (source.put(b"p"), priorities)[1] != [], what="a priority message")
    finally:
        operator.close()
        robot.close()
        router.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs


def test_priority_links_of_a_client_are_said_to_be_one_link(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Zenoh's client connects to one endpoint: the second range's link is never opened."""
    client = tmp_path / "client.json5"
    client.write_text('{mode: "client"}')
    linked = functools.partial(
        _config,
        connect=["tcp/127.0.0.1:7000"],
        listen=[],
        shared_memory=False,
        port=1,
        host="r1",
        priority_links=True,
    )
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        linked(config_file=None)
        assert not caplog.records  # a peer opens a link per range
        linked(config_file=client)
    assert [r.getMessage() for r in caplog.records] == [
        "priority_links: a zenoh client opens one link, to the first router it reaches; "
        "control and data share it (a peer opens one per range)"
    ]


def test_a_cdr_float64_on_the_priority_topic_sets_the_priority_and_a_flood_keeps_the_rule(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Over zenoh a priority topic carries CDR, as rmw_zenoh's would: another session's."""
    name = names.priority("/r1/camera")
    robot, operator = sessions = mesh(free_port(), "r1", "op")
    heard = PriorityTopic(robot, "/r1/camera")  # what the channel's managed publisher runs
    writes: list[tuple[float, object]] = []
    robot.params.watch(lambda n, v: writes.append((time.monotonic(), v)) if n == name else None)
    try:
        assert operator.wait_for_peers(10)
        publisher = operator.declare_publisher("/r1/camera/dbm/priority")
        wait_for(lambda: publisher.has_subscribers, timeout_s=10, what="the robot's subscription")
        with caplog.at_level(logging.WARNING, logger="dbml.priority"):
            publisher.put(encode_float64(1.5))
            wait_for(lambda: f"{name}=1.5 must be within" in caplog.text, what="the refusal")
        publisher.put(encode_float64(0.3))
        wait_for(lambda: operator.params.get(name) == 0.3, timeout_s=10, what="0.3 everywhere")
        started = time.monotonic()
        flood = [round(0.001 * i, 3) for i in range(1, 1_000)]
        for value in flood:
            publisher.put(encode_float64(value))
        wait_for(lambda: operator.params.get(name) == flood[-1], timeout_s=10, what="the newest")
        during = [t for t, _v in writes if t >= started]
        span_s = during[-1] - during[0]
        assert len(during) <= span_s / PRIORITY_INTERVAL_S + 1, (len(during), span_s)
        assert len(during) < len(flood) / 10
    finally:
        heard.close()
        close_all(sessions)


def test_a_peer_mesh_past_the_sessions_it_completes_with_says_so_once(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The no-flags mesh names the router topology once it holds more sessions than it can."""
    import dbml.transports.zenoh.transport as transport_module

    monkeypatch.setattr(transport_module, "PEER_MESH_SESSIONS", 2)
    port = free_port()
    with caplog.at_level(logging.WARNING, logger="dbml.zenoh"):
        sessions = mesh(port, "base", "r1")
        try:
            wait_for(lambda: all(len(s._sync._live) == 1 for s in sessions), timeout_s=10)
            assert "peer mesh" not in caplog.text  # two sessions: within what it completes
            sessions += mesh(port, "r2", "r3")
            wait_for(lambda: all(len(s._sync._live) == 3 for s in sessions), timeout_s=10)
            said = [r.getMessage() for r in caplog.records if "peer mesh" in r.getMessage()]
            assert len(said) == len(sessions)  # once per session, however many it meets
            assert all("past 2" in line and "dbml router" in line for line in said)
        finally:
            close_all(sessions)
    routed = ZenohTransport(host="r9", connect=[f"tcp/127.0.0.1:{port}"])  # not a mesh member
    routed.close()
    assert routed._sync._mesh_sessions is None
