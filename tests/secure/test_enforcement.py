"""What zenoh enforces with the generated configs: real sessions over TLS on loopback.

"Does not arrive" is never judged by waiting: a control write that must arrive is sent after the
forbidden ones on the same session (one transport, in order), and once it is in, the forbidden
ones would have been too.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zenoh

from dbml.harness.processes import free_port
from dbml.secure import CA_CERTIFICATE, init_fleet
from tests.conftest import wait_for
from tests.secure.conftest import NODES, small_fleet


def open_node(path: Path) -> zenoh.Session:
    config = zenoh.Config.from_file(str(path))
    config.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(config)


class Recorder:
    """Every sample a session receives on ``**``: (key, payload)."""

    def __init__(self, session: zenoh.Session) -> None:
        self._lock = threading.Lock()
        self._seen: list[tuple[str, str]] = []
        self._subscriber = session.declare_subscriber("**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._seen.append((str(sample.key_expr), sample.payload.to_bytes().decode()))

    def seen(self) -> list[tuple[str, str]]:
        with self._lock:
            return list(self._seen)


@pytest.fixture
def mesh(tmp_path: Path) -> Iterator[tuple[Path, dict[str, zenoh.Session]]]:
    """The four nodes' sessions, connected in a full mesh, from the generated configs."""
    endpoints = {name: f"tls/127.0.0.1:{free_port()}" for name in NODES}
    init_fleet(tmp_path / "fleet", small_fleet(endpoints=endpoints))
    sessions: dict[str, zenoh.Session] = {}
    try:
        for name in NODES:
            sessions[name] = open_node(tmp_path / "fleet" / f"{name}.json5")
        wait_for(
            lambda: all(len(list(s.info.peers_zid())) == 3 for s in sessions.values()),
            timeout_s=15,
            what="the full TLS mesh",
        )
        yield tmp_path / "fleet", sessions
    finally:
        for session in sessions.values():
            session.close()  # type: ignore[no-untyped-call]


def listening(recorder: Recorder, sender: zenoh.Session, probe: str) -> None:
    """Wait until ``recorder``'s subscriber is known to ``sender``: an allowed probe arrives."""

    def arrived() -> bool:
        sender.put(probe, "probe")
        return (probe, "probe") in recorder.seen()

    wait_for(arrived, timeout_s=10, what=f"{probe} to arrive")


def sent_in_order(
    sender: zenoh.Session, recorder: Recorder, keys: list[str], control: str
) -> list[str]:
    """Put every key, then the control; the keys that had arrived once the control did."""
    for key in keys:
        sender.put(key, "tried")
    sender.put(control, "control")
    wait_for(lambda: (control, "control") in recorder.seen(), timeout_s=10, what=control)
    return [key for key, payload in recorder.seen() if payload == "tried"]


ROBOT_FORBIDDEN = [
    "dbml/param/dbm/max_bandwidth_in_mbit",
    "dbml/param/r2/camera/dbm/priority",
    "dbml/param/r1/camera/dbm/frequency/current_value",  # inside r1/**: the deny rule wins
    "dbml/param/r1/camera/dbm/managed",
    "dbml/param/*/camera/dbm/priority",  # a wildcard cannot reach beyond r1's own keys
    "dbml/batch",
    "dbml/batch/r2",
    "r2/camera",
    "dbml/param/dbm/status",
    "dbm/link",
]
ROBOT_ALLOWED = [
    "r1/camera",
    "r1/camera/optimized",
    "dbml/param/r1/camera/dbm/frequency/min",
    "dbml/param/r1/camera/dbm/frequency/max",
    "dbml/param/r1/camera/dbm/message_size_in_bytes",
    "dbml/param/r1/camera/dbm/frequency/applied_value",
]


@pytest.mark.integration
def test_a_robot_writes_its_own_channels_only(mesh: tuple[Path, dict[str, zenoh.Session]]) -> None:
    _, sessions = mesh
    at_optimizer = Recorder(sessions["opt"])
    listening(at_optimizer, sessions["r1"], "r1/probe")
    control = "dbml/param/r1/camera/dbm/priority"
    arrived = sent_in_order(sessions["r1"], at_optimizer, ROBOT_FORBIDDEN + ROBOT_ALLOWED, control)
    assert arrived == ROBOT_ALLOWED


@pytest.mark.integration
def test_the_optimizer_writes_its_allocation_and_status_only(
    mesh: tuple[Path, dict[str, zenoh.Session]],
) -> None:
    """The keys refused from a robot arrive from the optimizer: the refusal is the ACL's."""
    _, sessions = mesh
    at_robot = Recorder(sessions["r1"])
    listening(at_robot, sessions["opt"], "dbml/param/dbm/round")
    optimizer_keys = [
        "dbml/batch",
        "dbml/batch/r1",
        "dbml/param/r1/camera/dbm/frequency/current_value",
        "dbml/param/r1/camera/dbm/managed",
        "dbml/param/dbm/status",
        "dbml/param/dbm/status_message",
        "dbml/param/dbm/estimated_bandwidth_in_mbit",
        "dbml/param/dbm/estimator_state",
        "dbm/link",
    ]
    forbidden = ["dbml/param/dbm/max_bandwidth_in_mbit", "dbml/param/r1/camera/dbm/priority"]
    forbidden += ["r1/camera", "dbml/param/r1/camera/dbm/frequency/min"]
    arrived = sent_in_order(
        sessions["opt"], at_robot, forbidden + optimizer_keys, "dbml/param/dbm/round"
    )
    assert arrived == optimizer_keys


@pytest.mark.integration
def test_an_operator_sets_the_budget_and_priorities_only(
    mesh: tuple[Path, dict[str, zenoh.Session]],
) -> None:
    _, sessions = mesh
    at_optimizer = Recorder(sessions["opt"])
    listening(at_optimizer, sessions["op"], "dbml/param/dbm/strategy")
    allowed = [
        "dbml/param/dbm/max_bandwidth_in_mbit",
        "dbml/param/dbm/max_bandwidth_utilization",
        "dbml/param/dbm/optimization_rate_in_seconds",
        "dbml/param/r1/camera/dbm/priority",
        "dbml/param/r2/camera/dbm/priority",
    ]
    forbidden = [
        "dbml/param/r1/camera/dbm/frequency/min",
        "dbml/param/r1/camera/dbm/frequency/current_value",
        "dbml/param/dbm/status",
        "dbml/batch",
        "dbml/batch/r1",
        "op/camera",
        "r1/camera",
    ]
    control = "dbml/param/dbm/strategy"
    arrived = sent_in_order(sessions["op"], at_optimizer, forbidden + allowed, control)
    assert arrived == allowed


@pytest.mark.integration
def test_replies_are_refused_like_puts(mesh: tuple[Path, dict[str, zenoh.Session]]) -> None:
    _, sessions = mesh
    offered = {
        "r1": [
            "dbml/own/n1/r1/camera/dbm/priority",
            "dbml/own/n1/r1/camera/dbm/frequency/current_value",
            "dbml/own/n1/r2/camera/dbm/priority",
            "dbml/own/n1/dbm/max_bandwidth_in_mbit",
        ],
        "op": [
            "dbml/own/n2/dbm/max_bandwidth_in_mbit",
            "dbml/own/n2/r2/camera/dbm/priority",
            "dbml/own/n2/r2/camera/dbm/frequency/min",
            "dbml/own/n2/dbm/status",
        ],
        "r2": [
            "dbml/own/n3/r2/camera/dbm/frequency/max",
            "dbml/own/n3/r1/camera/dbm/frequency/max",
        ],
    }
    queryables = []
    for name, keys in offered.items():

        def serve(query: zenoh.Query, keys: list[str] = keys) -> None:
            for key in keys:
                query.reply(key, "value")

        queryables.append(sessions[name].declare_queryable("dbml/own/**", serve))

    def answers() -> set[str]:
        replies = sessions["opt"].get(
            "dbml/own/**",
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=5,
        )
        return {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}

    expected = {
        "dbml/own/n1/r1/camera/dbm/priority",
        "dbml/own/n2/dbm/max_bandwidth_in_mbit",
        "dbml/own/n2/r2/camera/dbm/priority",
        "dbml/own/n3/r2/camera/dbm/frequency/max",
    }
    # a query ends when every queryable has answered: no waiting for what does not come
    wait_for(lambda: answers() == expected, timeout_s=10, what="every queryable to answer")
    assert answers() == expected
    # and what the optimizer serves (values whose writer left) reaches everyone
    queryables.append(
        sessions["opt"].declare_queryable(
            "dbml/own/**", lambda query: query.reply("dbml/own/n4/r1/camera/dbm/priority", "v")
        )
    )

    def kept() -> set[str]:
        replies = sessions["r2"].get("dbml/own/n4/**", timeout=5)
        return {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}

    wait_for(
        lambda: kept() == {"dbml/own/n4/r1/camera/dbm/priority"},
        timeout_s=10,
        what="the optimizer's reply",
    )


@pytest.mark.integration
def test_graph_tokens_carry_the_certificate_s_name(
    mesh: tuple[Path, dict[str, zenoh.Session]],
) -> None:
    _, sessions = mesh
    tokens: list[str] = []
    lock = threading.Lock()

    def on_token(sample: zenoh.Sample) -> None:
        with lock:
            tokens.append(str(sample.key_expr))

    watcher = sessions["opt"].liveliness().declare_subscriber("dbml/**", on_token, history=True)
    forbidden = [
        sessions["r1"].liveliness().declare_token("dbml/graph/pub/r2/x.1/optimized/r2/camera"),
        sessions["op"].liveliness().declare_token("dbml/graph/sub/r1/y.1/optimized/r1/camera"),
        sessions["r1"].liveliness().declare_token("dbml/elsewhere/x"),
    ]
    allowed = [
        sessions["r1"].liveliness().declare_token("dbml/node/abc/def/own"),
        sessions["op"].liveliness().declare_token("dbml/graph/sub/op/y.2/optimized/r1/camera"),
        sessions["r1"].liveliness().declare_token("dbml/graph/pub/r1/x.2/optimized/r1/camera"),
    ]
    expected = {
        "dbml/node/abc/def/own",
        "dbml/graph/sub/op/y.2/optimized/r1/camera",
        "dbml/graph/pub/r1/x.2/optimized/r1/camera",
    }

    def seen() -> set[str]:
        with lock:
            return set(tokens)

    wait_for(lambda: expected <= seen(), timeout_s=10, what="the allowed tokens")
    late = {str(r.ok.key_expr) for r in sessions["opt"].liveliness().get("dbml/**") if r.ok}
    assert seen() == expected
    assert late == expected
    del watcher, forbidden, allowed


@pytest.mark.integration
def test_processes_of_one_node_meet_directly(mesh: tuple[Path, dict[str, zenoh.Session]]) -> None:
    """A second and third operator process find the endpoint taken, and still meet each other.

    Each listens on a port of its own, learnt by the others by gossip: no process depends on
    another to forward (which would make the forwarder the subject of the access control).
    """
    directory, sessions = mesh
    second = open_node(directory / "op.json5")
    third = open_node(directory / "op.json5")
    try:
        zids = {name: str(session.info.zid()) for name, session in sessions.items()}
        zids |= {"second": str(second.info.zid()), "third": str(third.info.zid())}

        def meets_everyone(session: zenoh.Session, me: str) -> bool:
            peers = {str(zid) for zid in session.info.peers_zid()}
            return peers == {zid for name, zid in zids.items() if name != me}

        wait_for(
            lambda: meets_everyone(second, "second") and meets_everyone(third, "third"),
            timeout_s=15,
            what="the operator's processes to meet every process",
        )
        at_second = Recorder(second)
        listening(at_second, third, "dbml/param/dbm/strategy")
    finally:
        second.close()  # type: ignore[no-untyped-call]
        third.close()  # type: ignore[no-untyped-call]


def rogue_config(endpoint: str, tls: dict[str, object]) -> zenoh.Config:
    """A session that must connect to ``endpoint`` within 1 s or fail to open."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("connect/timeout_ms", "1000")
    config.insert_json5("connect/exit_on_failure", "true")
    for field, value in tls.items():
        config.insert_json5(f"transport/link/tls/{field}", json.dumps(value))
    return config


def open_each(endpoints: list[str], tls: dict[str, object]) -> list[zenoh.Session | None]:
    """One session per endpoint, opened at once; None where zenoh refused to open it.

    One endpoint each: with several, a peer's open fails when any one of them does not connect
    in time, so a failure would not say that none accepted.
    """

    def attempt(endpoint: str) -> zenoh.Session | None:
        try:
            return zenoh.open(rogue_config(endpoint, tls))
        except zenoh.ZError:
            return None

    with ThreadPoolExecutor(len(endpoints)) as pool:
        return list(pool.map(attempt, endpoints))


@pytest.mark.integration
@pytest.mark.parametrize("credentials", ["plain tcp", "no certificate", "another CA's r1"])
def test_a_session_without_a_fleet_certificate_reaches_no_node(
    mesh: tuple[Path, dict[str, zenoh.Session]], tmp_path: Path, credentials: str
) -> None:
    directory, sessions = mesh
    endpoints = [
        json.loads(
            zenoh.Config.from_file(str(directory / f"{n}.json5")).get_json("listen/endpoints")
        )[0]
        for n in NODES
    ]
    init_fleet(tmp_path / "rogue", small_fleet())
    ca = str(directory / CA_CERTIFICATE)
    tls: dict[str, object] = {"root_ca_certificate": ca}
    if credentials == "plain tcp":
        tls = {}
    elif credentials == "another CA's r1":
        tls |= {
            "connect_certificate": str(tmp_path / "rogue" / "r1.pem"),
            "connect_private_key": str(tmp_path / "rogue" / "r1.key"),
            "enable_mtls": True,
        }
    tried = (
        [e.replace("tls/", "tcp/") for e in endpoints] if credentials == "plain tcp" else endpoints
    )
    assert open_each(tried, tls) == [None] * len(NODES)
    assert all(len(list(s.info.peers_zid())) == 3 for s in sessions.values())
    # the control: the same session with the operator's certificate gets into every node
    tls = {
        "root_ca_certificate": ca,
        "connect_certificate": str(directory / "op.pem"),
        "connect_private_key": str(directory / "op.key"),
        "enable_mtls": True,
    }
    opened = open_each(endpoints, tls)
    for session in opened:
        if session is not None:
            session.close()  # type: ignore[no-untyped-call]
    assert None not in opened
