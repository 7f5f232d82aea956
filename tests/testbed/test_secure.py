"""``dbml secure init`` across network namespaces, driven through the real ``dbml`` command line.

Each robot and the operator side have a namespace of their own (``dbml.testbed.Network``); the
fleet's endpoints are their addresses. A session of the optimizer's node (in the operator's
namespace) prints every parameter change it accepts, and the claims are read from it:

- a session without a fleet certificate reaches no node;
- a robot's write of the budget, or of another robot's priority, never arrives, while its own
  channel's priority does, and the refused values stay what they were;
- an operator's budget and priorities arrive.

A refusal is judged by a control write that must arrive after it: in the same session, or by a
process started after the refused one ended.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from dbml.harness.supervisor import Supervisor
from dbml.testbed import Network, leftover_namespaces
from tests.conftest import wait_for

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
BUDGET = "/dbm/max_bandwidth_in_mbit"
R1_PRIORITY = "/r1/camera/dbm/priority"
R2_PRIORITY = "/r2/camera/dbm/priority"

READER = """
import json, sys
from dbml.transports.zenoh import ZenohTransport
transport = ZenohTransport(config_file=sys.argv[1], host=sys.argv[2])
show = lambda name, value: print(json.dumps({"name": name, "value": value}), flush=True)
transport.params.watch(show)
print(json.dumps({"ready": True}), flush=True)
sys.stdin.read()
transport.close()
"""
"""A session that prints every parameter change it accepts, until its stdin closes."""

WRITER = """
import json, sys
from dbml.transports.zenoh import ZenohTransport
config, host, writes = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
transport = ZenohTransport(config_file=config, host=host)
try:
    peers = transport.wait_for_peers(5.0)
    for name, value in writes:
        transport.params.set(name, value)
    held = transport.confirm_param(writes[-1][0], timeout_s=5.0) if peers else False
    print(json.dumps({"peers": peers, "held": held}), flush=True)
finally:
    transport.close()
"""
"""Writes in order on one session (no ``dbml`` command writes the budget); reports whether it
reached a peer and whether a peer holds the last write."""


@dataclass
class Reader:
    """The optimizer node's session (a child of ``children``): what it accepted, in order."""

    children: Supervisor
    name: str
    changes: list[tuple[str, object]] = field(default_factory=list)

    def _take(self) -> None:
        """What it reported since the last look."""
        for line in self.children.take_all(lambda ln: ln.child == self.name):
            if line.report is not None and "name" in line.report:
                self.changes.append((line.report["name"], line.report["value"]))

    def wait_ready(self, timeout_s: float) -> bool:
        line = self.children.take(
            lambda ln: ln.child == self.name and (ln.ended or bool((ln.report or {}).get("ready"))),
            timeout_s=timeout_s,
        )
        return line is not None and not line.ended

    def values(self, name: str) -> list[object]:
        self._take()
        return [value for changed, value in self.changes if changed == name]

    def current(self, name: str) -> object:
        values = self.values(name)
        return values[-1] if values else None

    def wait(self, name: str, value: object, what: str) -> None:
        wait_for(lambda: self.current(name) == value, timeout_s=30, what=what)


@dataclass
class Fleet:
    network: Network
    directory: Path
    reader: Reader

    def run(self, host: str, argv: list[str]) -> subprocess.CompletedProcess[str]:
        """Run ``argv`` (after ``python``) in ``host``'s namespace to its end."""
        return subprocess.run(
            self.network.exec_argv(host, [sys.executable, *argv]),
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )

    def dbml(self, host: str, *args: str) -> subprocess.CompletedProcess[str]:
        done = self.run(host, ["-m", "dbml", *args])
        assert done.returncode == 0, done.stderr
        return done

    def as_node(self, name: str) -> list[str]:
        return ["--zenoh-config", str(self.directory / f"{name}.json5"), "--host", name]

    def write(
        self, host: str, config: Path, name: str, writes: list[list[object]]
    ) -> dict[str, bool]:
        done = self.run(host, ["-c", WRITER, str(config), name, json.dumps(writes)])
        assert done.returncode == 0, done.stderr
        result: dict[str, bool] = json.loads(done.stdout.splitlines()[-1])
        return result


def endpoints(network: Network) -> list[str]:
    """Where each node listens: the optimizer and the operator share the operator's side."""
    op = network.hosts["op"].address
    flags = [f"opt=tls/{op}:7447", f"op=tls/{op}:7448"]
    flags += [f"{robot}=tls/{network.hosts[robot].address}:7447" for robot in ("r1", "r2")]
    return [item for flag in flags for item in ("--endpoint", flag)]


@pytest.fixture(scope="module")
def fleet(netns_privilege: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    directory = tmp_path_factory.mktemp("secure") / "fleet"
    with Network(robots=("r1", "r2"), link_mbit=100) as network:
        init = [sys.executable, "-m", "dbml", "secure", "init", str(directory)]
        init += ["--optimizer", "opt", "--robots", "r1,r2", "--operators", "op"]
        done = subprocess.run(
            [*init, *endpoints(network)], capture_output=True, text=True, timeout=60, check=False
        )
        assert done.returncode == 0, done.stderr
        argv = [sys.executable, "-c", READER, str(directory / "opt.json5"), "opt"]
        with Supervisor() as children:  # stdin closed, then SIGTERM and SIGKILL, by its PID
            children.start("reader", argv, netns=network.hosts["op"].netns, cwd=ROOT)
            reader = Reader(children, "reader")
            assert reader.wait_ready(30), "the optimizer's session did not start"
            yield Fleet(network, directory, reader)
    assert leftover_namespaces(f"dbml-{network.run_id}-") == []


def test_an_operator_sets_the_budget_and_a_robot_s_priority(fleet: Fleet) -> None:
    result = fleet.write("op", fleet.directory / "op.json5", "op", [[BUDGET, 11.0]])
    assert result == {"peers": True, "held": True}
    fleet.reader.wait(BUDGET, 11.0, "the operator's budget")
    fleet.dbml("op", "priority", "/r1/camera", "0.5", *fleet.as_node("op"))
    fleet.reader.wait(R1_PRIORITY, 0.5, "the operator's priority of /r1/camera")


def test_a_robot_sets_its_own_priority_only(fleet: Fleet) -> None:
    fleet.write("op", fleet.directory / "op.json5", "op", [[BUDGET, 11.0]])
    fleet.reader.wait(BUDGET, 11.0, "the operator's budget")
    fleet.dbml("r2", "priority", "/r2/camera", "0.2", *fleet.as_node("r2"))
    fleet.reader.wait(R2_PRIORITY, 0.2, "r2's own priority")
    # the command line: the refused process ends before the control one starts
    fleet.dbml("r1", "priority", "/r2/camera", "0.95", *fleet.as_node("r1"))
    fleet.dbml("r1", "priority", "/r1/camera", "0.6", *fleet.as_node("r1"))
    fleet.reader.wait(R1_PRIORITY, 0.6, "r1's own priority")
    # one session: the budget and r2's priority, then the control, in order
    writes: list[list[object]] = [[BUDGET, 1.0], [R2_PRIORITY, 0.9], [R1_PRIORITY, 0.7]]
    result = fleet.write("r1", fleet.directory / "r1.json5", "r1", writes)
    assert result["peers"] is True
    fleet.reader.wait(R1_PRIORITY, 0.7, "r1's own priority, after the refused writes")
    assert fleet.reader.current(BUDGET) == 11.0
    assert fleet.reader.current(R2_PRIORITY) == 0.2
    assert 1.0 not in fleet.reader.values(BUDGET)
    assert not {0.9, 0.95} & set(fleet.reader.values(R2_PRIORITY))


@pytest.mark.parametrize("connect", ["tls", "tcp"])
def test_a_session_without_a_fleet_certificate_reaches_no_node(fleet: Fleet, connect: str) -> None:
    optimizer = f"{connect}/{fleet.network.hosts['op'].address}:7447"
    fleet.dbml("r1", "priority", "/r1/camera", "0.11", "--connect", optimizer, "--host", "r1")
    fleet.dbml("r1", "priority", "/r1/camera", "0.66", *fleet.as_node("r1"))  # the control
    fleet.reader.wait(R1_PRIORITY, 0.66, "the control write")
    assert 0.11 not in fleet.reader.values(R1_PRIORITY)


def test_a_certificate_from_another_ca_reaches_no_node(fleet: Fleet, tmp_path: Path) -> None:
    """An impostor with a certificate named r1, from a CA of its own, at the fleet's addresses."""
    init = [sys.executable, "-m", "dbml", "secure", "init", str(tmp_path / "impostor")]
    init += ["--optimizer", "opt", "--robots", "r1,r2", "--operators", "op"]
    done = subprocess.run(
        [*init, *endpoints(fleet.network)], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
    result = fleet.write("r1", tmp_path / "impostor" / "r1.json5", "r1", [[R1_PRIORITY, 0.12]])
    assert result == {"peers": False, "held": False}
    fleet.dbml("r1", "priority", "/r1/camera", "0.67", *fleet.as_node("r1"))  # the control
    fleet.reader.wait(R1_PRIORITY, 0.67, "the control write")
    assert 0.12 not in fleet.reader.values(R1_PRIORITY)
