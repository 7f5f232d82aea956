"""The namespace testbed for real: reachability, tbf shaping, live rate change, cleanup, errors."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import pytest

from dbml.harness.supervisor import Supervisor
from dbml.testbed import Network, TestbedError, leftover_namespaces
from dbml.testbed import netns as netns_module

pytestmark = [pytest.mark.integration, pytest.mark.usefixtures("netns_privilege")]

PORT = 5201

# One small TCP peer run inside a namespace: "serve" receives until EOF and reports what arrived
# and over how long (first to last byte, at the receiver, so queues do not inflate the rate);
# "send" connects (retrying until its deadline while the server starts) and sends N bytes.
PEER = r"""
import json, socket, sys, time

mode, addr, port = sys.argv[1], sys.argv[2], int(sys.argv[3])
deadline = time.monotonic() + float(sys.argv[4])

def left():
    return max(0.05, deadline - time.monotonic())

if mode == "serve":
    with socket.create_server((addr, port)) as server:
        server.settimeout(left())
        conn, peer = server.accept()
        with conn:
            conn.settimeout(left())
            total = first_len = 0
            first = last = time.monotonic()
            while chunk := conn.recv(1 << 16):
                now = time.monotonic()
                if total == 0:
                    first, first_len = now, len(chunk)
                total += len(chunk)
                last = now
            conn.sendall(b"ok")
    seconds = last - first
    print(json.dumps({"peer": peer[0], "bytes": total, "first": first_len, "seconds": seconds}))
else:
    nbytes = int(sys.argv[5])
    while True:
        try:
            sock = socket.create_connection((addr, port), timeout=left())
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.01)
    with sock:
        sock.settimeout(left())
        sock.sendall(b"x" * nbytes)
        sock.shutdown(socket.SHUT_WR)
        assert sock.recv(16) == b"ok"
"""


def transfer(network: Network, src: str, dst: str, nbytes: int, timeout_s: float) -> dict[str, Any]:
    """Send ``nbytes`` over TCP from ``src`` to ``dst``; what the receiver saw."""
    address = network.hosts[dst].address
    args = [address, str(PORT), str(timeout_s)]
    with Supervisor() as children:  # ended by PID when the block leaves, however it leaves
        server = children.start(
            "serve",
            [sys.executable, "-c", PEER, "serve", *args],
            netns=network.hosts[dst].netns,
            stdin=False,
        )
        client = children.start(
            "send",
            [sys.executable, "-c", PEER, "send", *args, str(nbytes)],
            netns=network.hosts[src].netns,
            stdin=False,
        )
        assert client.wait(timeout_s + 2) == 0, f"{src}->{dst} sender failed: {client.log()}"
        assert server.wait(timeout_s + 2) == 0, f"{src}->{dst} receiver failed: {server.log()}"
        out = server.next(timeout_s=5)
    assert out is not None
    assert out.report is not None, out.text
    result: dict[str, Any] = out.report
    assert result["bytes"] == nbytes
    return result


def throughput_mbit(network: Network, src: str, dst: str, *, expect_mbit: float) -> float:
    """TCP payload rate src -> dst in Mbit/s, over a transfer sized to last about 1.5 s."""
    nbytes = int(expect_mbit * 1e6 / 8 * 1.5)
    result = transfer(network, src, dst, nbytes, timeout_s=10)
    return float((result["bytes"] - result["first"]) * 8 / result["seconds"] / 1e6)


def assert_reaches(network: Network, src: str, dst: str) -> None:
    result = transfer(network, src, dst, 4, timeout_s=5)
    assert result["peer"] == network.hosts[src].address  # routed, not translated


def root_interfaces() -> list[str]:
    """Interface names in the root namespace (``ip -o link``: ``2: name@peer: <...``)."""
    out = subprocess.run(
        ["ip", "-o", "link"], check=True, capture_output=True, text=True, timeout=10
    ).stdout
    return [line.split(":")[1].strip().split("@")[0] for line in out.splitlines() if line]


def assert_gone(run_id: str) -> None:
    assert leftover_namespaces(f"dbml-{run_id}-") == []
    assert [name for name in root_interfaces() if run_id in name] == []


@pytest.fixture
def make_network() -> Iterator[Callable[..., Network]]:
    """Build networks that are closed, and proven gone, even when the test fails."""
    networks: list[Network] = []

    def make(**kwargs: Any) -> Network:
        network = Network(**kwargs)
        networks.append(network)
        return network.build()

    yield make
    for network in networks:
        network.close()
    for network in networks:
        assert_gone(network.run_id)


def test_hosts_reach_each_other_through_the_router(make_network: Callable[..., Network]) -> None:
    network = make_network(robots=("r1", "r2", "scout3"), link_mbit=8)
    assert {name: host.address for name, host in network.hosts.items()} == {
        "r1": "10.200.1.2",
        "r2": "10.200.2.2",
        "scout3": "10.200.3.2",
        "op": "10.200.100.2",
    }
    assert sorted(network.namespaces) == leftover_namespaces(f"dbml-{network.run_id}-")
    assert [name for name in root_interfaces() if network.run_id in name] == []
    for robot in network.robots:
        assert_reaches(network, "op", robot)
        assert_reaches(network, robot, "op")
    assert_reaches(network, "r1", "r2")


def test_bottleneck_is_shaped_and_changes_live(make_network: Callable[..., Network]) -> None:
    network = make_network(link_mbit=8)
    first = throughput_mbit(network, "r1", "op", expect_mbit=8)
    assert 0.70 * 8 <= first <= 1.05 * 8
    network.set_link_rate(4)
    assert network.link_mbit == 4
    second = throughput_mbit(network, "r1", "op", expect_mbit=4)
    assert second < 0.75 * first
    assert 0.70 * 4 <= second <= 1.05 * 4
    print(f"r1->op at 8 Mbit: {first:.2f} Mbit/s; after set_link_rate(4): {second:.2f} Mbit/s")


def test_fractional_rates_shape(make_network: Callable[..., Network]) -> None:
    network = make_network(link_mbit=2.5)
    measured = throughput_mbit(network, "r2", "op", expect_mbit=2.5)
    assert 0.70 * 2.5 <= measured <= 1.05 * 2.5
    print(f"r2->op at 2.5 Mbit: {measured:.2f} Mbit/s")


def test_uplink_shapes_only_its_robot(make_network: Callable[..., Network]) -> None:
    network = make_network(link_mbit=8, uplinks_mbit={"r1": 2})
    slow = throughput_mbit(network, "r1", "op", expect_mbit=2)
    fast = throughput_mbit(network, "r2", "op", expect_mbit=8)
    assert 0.70 * 2 <= slow <= 1.05 * 2
    assert 0.70 * 8 <= fast <= 1.05 * 8
    print(f"uplink r1 2 Mbit: {slow:.2f} Mbit/s; r2 over the 8 Mbit link: {fast:.2f} Mbit/s")


# UDP probes through a saturated link, alternately marked (IP_TOS) and not: "echo" returns what
# it gets (the way back, op -> robot, is not shaped, so a round trip is the way there's queue);
# "probe" sends N of each, one every 20 ms, and reports each kind's round trips in ms.
PROBE = r"""
import json, socket, sys, time

mode, addr, port = sys.argv[1], sys.argv[2], int(sys.argv[3])
if mode == "echo":
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((addr, port))
        sock.settimeout(float(sys.argv[4]))
        try:
            while True:
                data, peer = sock.recvfrom(2048)
                sock.sendto(data, peer)
        except TimeoutError:
            pass
else:
    tos, count = int(sys.argv[4], 0), int(sys.argv[5])
    socks = {}
    for kind, value in (("marked", tos), ("unmarked", 0)):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, value)
        s.settimeout(1.0)
        socks[kind] = s
    rtts = {kind: [] for kind in socks}
    for i in range(count):
        for kind, s in socks.items():
            sent = time.monotonic()
            s.sendto(b"p" * 200, (addr, port))
            try:
                s.recvfrom(2048)
            except TimeoutError:
                continue
            rtts[kind].append((time.monotonic() - sent) * 1000)
        time.sleep(0.02)
    print(json.dumps(rtts))
"""


BULK_BYTES = 2_000_000
"""8 s at 2 Mbit/s: it outlasts 30 probes of each kind even if each waits out a full queue."""


def test_an_expedited_link_forwards_marked_packets_first(
    make_network: Callable[..., Network],
) -> None:
    """A saturating TCP transfer fills the bottleneck; EF-marked probes skip its queue."""
    tos = 0xB8
    network = make_network(link_mbit=2, expedited_tos=tos)
    op = network.hosts["op"]
    with Supervisor() as children:
        echo = [sys.executable, "-c", PROBE, "echo", op.address, str(PORT + 1), "20"]
        children.start("echo", echo, netns=op.netns, stdin=False)
        serve = [sys.executable, "-c", PEER, "serve", op.address, str(PORT), "20"]
        children.start("serve", serve, netns=op.netns, stdin=False)
        send = [sys.executable, "-c", PEER, "send", op.address, str(PORT), "20", str(BULK_BYTES)]
        children.start("send", send, netns=network.hosts["r2"].netns, stdin=False)
        probe = [sys.executable, "-c", PROBE, "probe", op.address, str(PORT + 1), str(tos), "30"]
        prober = children.start("probe", probe, netns=network.hosts["r1"].netns, stdin=False)
        assert prober.wait(20) == 0, prober.log()
        out = prober.next(timeout_s=5)
    assert out is not None
    assert out.report is not None, out.text
    rtts = {kind: sorted(values) for kind, values in out.report.items()}
    marked, unmarked = rtts["marked"], rtts["unmarked"]
    assert len(marked) >= 28, rtts
    marked_p95 = marked[int(0.95 * (len(marked) - 1))]
    unmarked_p50 = unmarked[len(unmarked) // 2]
    print(
        f"round trips beside a 2-Mbit transfer: marked p95 {marked_p95:.1f} ms, "
        f"unmarked p50 {unmarked_p50:.1f} ms"
    )
    assert marked_p95 < 40.0  # the packet on the wire and the one tbf holds: 12 ms at 2 Mbit/s
    assert unmarked_p50 > 2 * marked_p95


# A burst of UDP datagrams sent at once: what a fade finds in flight.
BURST = r"""
import socket, sys
addr, port, count = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
    for _ in range(count):
        sock.sendto(b"b" * 1000, (addr, port))
"""


def shared_link_qdiscs(network: Network) -> dict[str, dict[str, Any]]:
    """The shared link's qdiscs at the router, by kind, with their statistics (``tc -s -j``)."""
    out = subprocess.run(
        ["tc", "-n", f"dbml-{network.run_id}-rt", "-s", "-j", "qdisc", "show"],
        check=True,
        capture_output=True,
        text=True,
        timeout=10,
    ).stdout
    link = f"r{network.run_id}op"
    return {q["kind"]: q for q in json.loads(out) if q["dev"] == link}


@pytest.mark.parametrize("expedited", [False, True])
def test_a_fixed_queue_holds_what_a_fade_finds_in_flight(
    make_network: Callable[..., Network], expedited: bool
) -> None:
    """At 50 kbit/s tbf's own bound is 5,250 bytes; a radio's queue keeps its bytes."""
    tos = 0xB8 if expedited else None
    drops = {}
    for queue_bytes in (None, 120_000):
        network = make_network(link_mbit=8, queue_bytes=queue_bytes, expedited_tos=tos)
        network.set_link_rate(0.05)  # a fade
        assert network.queue_bytes == queue_bytes
        sender = [sys.executable, "-c", BURST, network.hosts["op"].address, str(PORT), "50"]
        done = subprocess.run(
            network.exec_argv("r1", sender), check=False, capture_output=True, timeout=10
        )
        assert done.returncode == 0, done.stderr
        qdiscs = shared_link_qdiscs(network)
        queue = qdiscs["bfifo" if expedited else "tbf"]
        drops[queue_bytes] = queue["drops"]
        held = queue["backlog"]
        if queue_bytes is not None:
            # 50 datagrams of 1,028 bytes on the wire: none dropped, all but the one
            # on the wire still queued at 6,250 bytes/s.
            assert drops[queue_bytes] == 0, qdiscs
            assert held > 40 * 1_000, qdiscs
        if expedited:
            assert qdiscs["bfifo"]["options"]["limit"] == (queue_bytes or 5_250)
    assert drops[None] >= 30  # of 50: the shaper's queue holds 5, its burst lets 3 pass


def test_close_removes_everything_and_twice_is_fine() -> None:
    network = Network(link_mbit=8).build()
    try:
        assert len(leftover_namespaces(f"dbml-{network.run_id}-")) == 4
    finally:
        network.close()
    assert_gone(network.run_id)
    network.close()
    assert_gone(network.run_id)


def test_with_block_cleans_up_after_an_exception() -> None:
    network = Network(robots=("a", "b", "c"), link_mbit=8)

    def use_and_fail() -> None:
        with network:
            assert len(leftover_namespaces(f"dbml-{network.run_id}-")) == 5
            raise RuntimeError("inside the block")

    with pytest.raises(RuntimeError, match="inside the block"):
        use_and_fail()
    assert_gone(network.run_id)


@pytest.mark.parametrize(
    "needle",
    ["tc -n", "ip link add d", "ip netns add dbml-"],
    ids=["shaping", "veth", "namespace"],
)
def test_failed_build_leaves_nothing_and_names_the_command(
    monkeypatch: pytest.MonkeyPatch, needle: str
) -> None:
    real_run = netns_module._run
    calls: list[str] = []

    def run(argv: Sequence[str]) -> str:
        command = " ".join(argv)
        calls.append(command)
        failing = needle in command and sum(needle in call for call in calls) == 2
        # A real command that really fails, so the real error path and message are exercised.
        return real_run([argv[0], "-bogus", *argv[1:]] if failing else argv)

    monkeypatch.setattr(netns_module, "_run", run)
    network = Network(link_mbit=8, uplinks_mbit={"r1": 2})
    try:
        with pytest.raises(TestbedError) as caught:
            network.build()
    finally:
        network.close()
    message = str(caught.value)
    program, rest = [call for call in calls if needle in call][1].split(" ", 1)
    assert f"command '{program} -bogus {rest}' failed" in message
    assert 'Option "-bogus" is unknown' in message
    assert "\n" not in message
    assert_gone(network.run_id)


def test_two_networks_at_once_are_independent(make_network: Callable[..., Network]) -> None:
    first = make_network(link_mbit=8)
    second = make_network(link_mbit=8)
    assert first.run_id != second.run_id
    for network in (first, second):
        assert_reaches(network, "r1", "op")
        assert_reaches(network, "op", "r2")
    clash = Network(link_mbit=8, run_id=first.run_id)
    with pytest.raises(TestbedError, match=f"ip netns add dbml-{first.run_id}-rt"):
        clash.build()
    second.close()
    assert_gone(second.run_id)
    assert sorted(first.namespaces) == leftover_namespaces(f"dbml-{first.run_id}-")
    assert_reaches(first, "r2", "op")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"robots": ("R1",)}, "robot name 'R1'"),
        ({"robots": ("toolong7",)}, "robot name 'toolong7'"),
        ({"robots": ("r1", "r1")}, "robot name 'r1' appears twice"),
        ({"robots": ("op",)}, "robot name 'op' is reserved"),
        ({"robots": "r1"}, "robots='r1'"),
        ({"robots": ()}, "robots=()"),
        ({"uplinks_mbit": {"r3": 2}}, "uplink 'r3' is not a robot (robots: r1, r2)"),
        ({"uplinks_mbit": {"r1": 0}}, "uplinks_mbit['r1']=0"),
        ({"link_mbit": 0}, "link_mbit=0"),
        ({"link_mbit": -1.5}, "link_mbit=-1.5"),
        ({"link_mbit": math.nan}, "link_mbit=nan"),
        ({"link_mbit": math.inf}, "link_mbit=inf"),
        ({"run_id": "ABCDEF"}, "run_id='ABCDEF'"),
        ({"expedited_tos": 0xB9}, "expedited_tos=185"),
        ({"expedited_tos": 0}, "expedited_tos=0"),
        ({"expedited_tos": True}, "expedited_tos=True"),
        ({"queue_bytes": 1_000}, "queue_bytes=1000 must be an integer in 1514.."),
        ({"queue_bytes": 2**27}, "queue_bytes=134217728"),
        ({"queue_bytes": 150_000.0}, "queue_bytes=150000.0"),
        ({"queue_bytes": True}, "queue_bytes=True"),
    ],
)
def test_bad_values_are_refused_before_anything_exists(
    kwargs: dict[str, Any], message: str
) -> None:
    before = leftover_namespaces()
    with pytest.raises(TestbedError, match=re.escape(message)) as caught:
        Network(**{"link_mbit": 8, **kwargs}).build()
    assert "\n" not in str(caught.value)
    assert leftover_namespaces() == before


def test_exec_argv_and_rate_checks_without_building() -> None:
    network = Network(link_mbit=8, run_id="abc123")
    assert network.exec_argv("op", ["true"]) == ["ip", "netns", "exec", "dbml-abc123-op", "true"]
    with pytest.raises(TestbedError, match="host 'rt' is not in the testbed"):
        network.exec_argv("rt", ["true"])
    with pytest.raises(TestbedError, match="link_mbit=0"):
        network.set_link_rate(0)
    with pytest.raises(TestbedError, match="is not built"):
        network.set_link_rate(4)
    network.close()
