"""The Fast DDS discovery profile, its installation and the host id of a GID, against Fast DDS."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from dbml.harness.ros2env import fastdds_shm_files, remove_fastdds_shm, ros2_child_env
from dbml.transports.rclpy.fastdds import (
    DEFAULT_PROFILES_FILE,
    LEGACY_PROFILES_FILE,
    PROFILE_NAME,
    apply_discovery_profile,
    discovery_profile_xml,
    gid_host_id,
)
from tests.conftest import wait_for
from tests.harness.children import CHILD_TIMEOUT_S, first_line, held_by_live_processes, python_child

NS = {"dds": "http://www.eprosima.com"}

_SUBSCRIBER = """
import os, sys, time
import rclpy
from rclpy.context import Context
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String
context = Context()
rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
           signal_handler_options=SignalHandlerOptions.NO)
node = rclpy.create_node("fastdds_test_peer", context=context)
node.create_subscription(String, sys.argv[1], lambda message: None, 10)
print("ready", flush=True)
if sys.argv[2] == "wait":
    sys.stdin.read()  # until the test closes stdin (or kills this process)
node.destroy_node()
rclpy.shutdown(context=context)
"""
"""A plain rclpy process with one subscription: ``TOPIC wait|exit``."""


def _seconds(element: ET.Element, name: str) -> float:
    found = element.find(f"dds:{name}", NS)
    assert found is not None, name
    sec, nanosec = found.findtext("dds:sec", "0", NS), found.findtext("dds:nanosec", "0", NS)
    return int(sec) + int(nanosec) / 1e9


def _discovery(xml: str) -> ET.Element:
    root = ET.fromstring(xml)
    participant = root.find("dds:profiles/dds:participant", NS)
    assert participant is not None
    assert participant.get("profile_name") == PROFILE_NAME
    assert participant.get("is_default_profile") == "true"
    discovery = participant.find("dds:rtps/dds:builtin/dds:discovery_config", NS)
    assert discovery is not None
    return discovery


def test_the_profile_has_a_short_lease_and_fast_announcements() -> None:
    discovery = _discovery(discovery_profile_xml())
    assert _seconds(discovery, "leaseDuration") == 3.0
    assert _seconds(discovery, "leaseAnnouncement") == 1.0
    assert discovery.findtext("dds:initialAnnouncements/dds:count", None, NS) == "10"
    initial = discovery.find("dds:initialAnnouncements", NS)
    assert initial is not None
    assert _seconds(initial, "period") == 0.1


def test_the_profile_takes_other_values() -> None:
    discovery = _discovery(
        discovery_profile_xml(lease_s=2.5, announce_period_s=0.25, initial_announcements=3)
    )
    assert _seconds(discovery, "leaseDuration") == 2.5
    assert _seconds(discovery, "leaseAnnouncement") == 0.25
    assert discovery.findtext("dds:initialAnnouncements/dds:count", None, NS) == "3"


@pytest.mark.parametrize(
    "options",
    [
        {"lease_s": 1.0, "announce_period_s": 1.0},
        {"announce_period_s": 0.0},
        {"initial_announcements": -1},
        {"initial_period_s": 0.0},
    ],
)
def test_the_profile_refuses_values_fast_dds_cannot_keep(options: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match=next(iter(options))):
        discovery_profile_xml(**options)


def test_apply_writes_the_profile_and_points_fast_dds_at_it(tmp_path: Path) -> None:
    environ: dict[str, str] = {"RMW_IMPLEMENTATION": "rmw_fastrtps_dynamic_cpp"}
    path = apply_discovery_profile(tmp_path / "profile", environ)
    assert path is not None
    assert environ[DEFAULT_PROFILES_FILE] == str(path)
    assert path.read_text(encoding="utf-8") == discovery_profile_xml()
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no partial file left


@pytest.mark.parametrize(
    "environ",
    [
        {DEFAULT_PROFILES_FILE: "/home/me/my_profile.xml"},
        {LEGACY_PROFILES_FILE: "/home/me/old_profile.xml"},
        {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"},
        {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"},
    ],
)
def test_apply_leaves_a_users_profile_and_other_rmws_alone(
    tmp_path: Path, environ: dict[str, str]
) -> None:
    before = dict(environ)
    assert apply_discovery_profile(tmp_path / "profile", environ) is None
    assert environ == before
    assert not (tmp_path / "profile").exists()


def test_apply_leaves_a_profile_in_the_working_directory_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "DEFAULT_FASTDDS_PROFILES.xml").write_text("<dds/>", encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    assert apply_discovery_profile(tmp_path / "profile", {}) is None
    # ... unless Fast DDS is told to skip that file
    assert apply_discovery_profile(tmp_path / "profile", {"SKIP_DEFAULT_XML_FILE": "1"})


def test_gid_host_id_refuses_other_vendors_and_lengths() -> None:
    fast_dds = bytes.fromhex("010f78fd2b4d437a0000000000002303")
    assert gid_host_id(fast_dds) == 0xFD78
    assert gid_host_id(list(fast_dds)) == 0xFD78
    assert gid_host_id(bytes.fromhex("0110") + fast_dds[2:]) is None  # another vendor
    assert gid_host_id(fast_dds + bytes(8)) is None  # 24 bytes: not rclpy's 16
    assert gid_host_id(fast_dds[:2]) is None
    assert gid_host_id([1, 15, 300, *fast_dds[3:]]) is None  # not bytes


@contextmanager
def _rclpy_node(domain_id: int, name: str) -> Iterator[Any]:
    """An rclpy node in a context of its own (as another process's would be)."""
    rclpy = pytest.importorskip("rclpy")
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(context=context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.usefixtures("ros_log_dir")
def test_gid_host_id_is_the_same_for_two_real_nodes_of_one_host(ros_domain: int) -> None:
    pytest.importorskip("rclpy")
    from std_msgs.msg import String

    topic = "/dbml_test_gid"
    with _rclpy_node(ros_domain, "gid_a") as a, _rclpy_node(ros_domain, "gid_b") as b:
        a.create_publisher(String, topic, 10)
        b.create_subscription(String, topic, lambda message: None, 10)
        wait_for(
            lambda: bool(a.get_subscriptions_info_by_topic(topic)),
            timeout_s=10.0,
            what="the subscription in the graph",
        )
        publisher = a.get_publishers_info_by_topic(topic)[0].endpoint_gid
        subscription = a.get_subscriptions_info_by_topic(topic)[0].endpoint_gid
    assert len(publisher) == 16
    assert publisher[8:12] != subscription[8:12]  # two participants (contexts), one process
    assert gid_host_id(publisher) is not None
    assert gid_host_id(publisher) == gid_host_id(subscription)
    assert gid_host_id([0x01, 0x10, *publisher[2:]]) is None


def _run_peer(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _SUBSCRIBER, "/dbml_test_profile", "exit"],
        env=env,
        capture_output=True,
        text=True,
        timeout=CHILD_TIMEOUT_S,
        check=False,
    )


@pytest.mark.integration
def test_fast_dds_accepts_the_profile(ros_domain: int, tmp_path: Path) -> None:
    """Fast DDS says nothing of a good profile and logs XMLPARSER errors for a bad one."""
    pytest.importorskip("rclpy")
    own = {
        k: v
        for k, v in os.environ.items()
        if k not in (DEFAULT_PROFILES_FILE, LEGACY_PROFILES_FILE)
    }
    base = ros2_child_env(domain_id=ros_domain, log_dir=tmp_path, base=own)
    assert DEFAULT_PROFILES_FILE in base
    good = _run_peer(base)
    assert good.returncode == 0, good.stderr
    assert good.stdout.split() == ["ready"]
    assert "XMLPARSER" not in good.stderr, good.stderr

    broken = tmp_path / "broken.xml"
    broken.write_text(
        discovery_profile_xml().replace("leaseAnnouncement>", "leaseAnnounce>"), encoding="utf-8"
    )
    bad = _run_peer({**base, DEFAULT_PROFILES_FILE: str(broken)})
    assert "XMLPARSER" in bad.stderr  # the check above can fail


@pytest.mark.integration
@pytest.mark.usefixtures("ros_log_dir")
def test_a_killed_peer_leaves_the_graph_within_the_short_lease(
    ros_domain: int, tmp_path: Path
) -> None:
    """Fast DDS's default lease would keep it for 20 s; the profile's lets it go after 3 s."""
    pytest.importorskip("rclpy")
    from std_msgs.msg import String

    topic = "/dbml_test_lease"
    env = ros2_child_env(domain_id=ros_domain, log_dir=tmp_path / "peer")
    with _rclpy_node(ros_domain, "lease_observer") as node:
        publisher = node.create_publisher(String, topic, 10)
        # A port of ours that the killed peer wrote to outlives our clean shutdown: see ros2env.
        # (The files of this process's other live contexts stay: they are held.)
        ours = fastdds_shm_files([os.getpid()])
        with python_child(_SUBSCRIBER, topic, "wait", env=env) as peer:
            assert first_line(peer) == "ready"
            files = fastdds_shm_files([peer.pid])
            wait_for(
                lambda: publisher.get_subscription_count() == 1,
                timeout_s=10.0,
                what="the peer's subscription",
            )
            peer.kill()
            killed = time.monotonic()
            peer.wait(CHILD_TIMEOUT_S)
            wait_for(
                lambda: publisher.get_subscription_count() == 0,
                timeout_s=10.0,
                what="the killed peer to leave the graph (Fast DDS's default lease: 20 s)",
            )
            assert time.monotonic() - killed < 10.0
    assert files, "a Fast DDS process holds shared memory"
    remove_fastdds_shm(files + ours)
    assert held_by_live_processes(files + ours)  # gone, or a name another process took over
