"""The demo's layouts: one per way of meeting, each starting its children as the runner expects."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from dbml.core.errors import DbmlError
from dbml.demo import layouts
from dbml.demo.layouts import LAYOUTS, layout_of
from dbml.experiment.entry import ENTRY_MODULE, Kind
from dbml.experiment.plan import Launch, Plan
from dbml.experiment.spec import HOSTS, RoleSpec
from dbml.scenarios.teleop import ROBOTS
from dbml.transports.registry import TRANSPORTS, Discovery


def _specs(transport: str) -> dict[str, RoleSpec]:
    entry = TRANSPORTS[transport]
    return {role: RoleSpec(step_s=1.0, transport=entry, host=host) for role, host in HOSTS.items()}


def _plan(transport: str) -> Plan:
    with contextlib.ExitStack() as run:
        return layout_of(TRANSPORTS[transport]).plan(_specs(transport), TRANSPORTS[transport], run)


def _kind(launch: Launch) -> tuple[Kind, list[str]]:
    """The kind a launch runs, and its arguments after the kind."""
    argv = list(launch.argv)
    assert argv[:3] == [sys.executable, "-m", ENTRY_MODULE]
    return Kind(argv[3]), argv[4:]


def test_every_way_of_meeting_has_a_layout() -> None:
    assert set(LAYOUTS) == set(Discovery)
    plain = {name for name, entry in TRANSPORTS.items() if not layout_of(entry).dbml_operator}
    assert plain == {"rclpy", "ros2"}, "their robots and operator are plain ROS 2 nodes"


def test_over_memory_the_roles_are_threads() -> None:
    plan = _plan("memory")
    assert plan.launches is None
    assert plan.helpers == ()
    assert list(plan.specs) == ["operator", "optimizer", "r1", "r2"]


def test_over_zenoh_every_role_meets_at_one_rendezvous_of_the_runs_own() -> None:
    plan = _plan("zenoh")
    assert plan.launches is not None
    ports = set()
    for role, launch in plan.launches.items():
        kind, args = _kind(launch)
        assert (kind, args[0]) == (Kind.ROLE, role)
        assert RoleSpec.from_json(args[1]) == plan.specs[role]
        assert launch.env is not None
        ports.add(launch.env["DBML_ZENOH_PORT"])
    assert len(ports) == 1
    assert plan.helpers == ()


def test_over_ros2_a_router_plain_peers_and_dbml_bridges_and_optimizer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(layouts, "free_port", lambda: 17447)
    plan = _plan("ros2")
    endpoint = "tcp/127.0.0.1:17447"
    assert {(s.connect, s.listen) for s in plan.specs.values()} == {
        ((endpoint,), (layouts.ROS2_LISTEN,))
    }
    assert plan.launches is not None
    kinds = {role: _kind(launch)[0] for role, launch in plan.launches.items()}
    assert kinds == {
        "operator": Kind.ROS2_PEER,
        "optimizer": Kind.ROLE,
        "r1": Kind.ROS2_PEER,
        "r2": Kind.ROS2_PEER,
    }
    router, *bridges = plan.helpers
    assert (router.name, router.before, router.port) == ("router", None, 17447)
    assert _kind(router.launch) == (Kind.ROUTER, ["--listen", endpoint])
    assert [b.name for b in bridges] == ["bridge-r1", "bridge-r2"]
    for bridge, camera in zip(bridges, ROBOTS, strict=True):
        kind, (spec,) = _kind(bridge.launch)
        assert kind is Kind.BRIDGE
        document = json.loads(spec)
        assert (document["topic"], document["transport"]) == (camera.topic, "ros2")
        assert (document["connect"], document["listen"]) == ([endpoint], [layouts.ROS2_LISTEN])
        assert bridge.before == "r1", "bridges before the robots they bridge"


def test_over_rclpy_plain_peers_dbml_bridges_and_optimizer_in_one_domain(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    @contextlib.contextmanager
    def domain() -> Iterator[int]:
        yield 42

    monkeypatch.setattr(layouts, "claim_domain", domain)
    monkeypatch.setattr(
        tempfile, "TemporaryDirectory", lambda prefix: contextlib.nullcontext(str(tmp_path))
    )
    plan = _plan("rclpy")
    assert {spec.domain_id for spec in plan.specs.values()} == {42}
    assert {spec.connect + spec.listen for spec in plan.specs.values()} == {()}, "DDS finds peers"
    assert plan.launches is not None
    for role, launch in plan.launches.items():
        kind, args = _kind(launch)
        assert kind is (Kind.ROLE if role == "optimizer" else Kind.RCLPY_PEER)
        assert args == [role, plan.specs[role].to_json()]
        assert launch.env is not None
        assert (launch.env["ROS_DOMAIN_ID"], launch.env["ROS_LOG_DIR"]) == ("42", str(tmp_path))
    assert [h.name for h in plan.helpers] == ["bridge-r1", "bridge-r2"]
    for helper, camera in zip(plan.helpers, ROBOTS, strict=True):
        kind, (spec,) = _kind(helper.launch)
        assert kind is Kind.BRIDGE
        document = json.loads(spec)
        assert document["topic"] == camera.topic
        assert (document["transport"], document["domain_id"]) == ("rclpy", 42)
        assert document["host"] == HOSTS[camera.robot.lower()]
        assert helper.before == "r1", "bridges before the robots they bridge"
        assert helper.launch.env is not None
        assert helper.launch.env["ROS_DOMAIN_ID"] == "42"


@pytest.mark.parametrize(
    ("transport", "missing", "named"),
    [
        ("ros1", "rospy", "needs rospy"),
        ("ros2", "zenoh_ros2_sdk", "zenoh-ros2-sdk"),
        ("rclpy", "rclpy", r"pip install 'dbml\[rclpy\]'"),
    ],
)
def test_a_layout_says_what_to_install(
    transport: str, missing: str, named: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name: None if name == missing else real(name)
    )
    with pytest.raises(DbmlError, match=named):
        layout_of(TRANSPORTS[transport]).check()
