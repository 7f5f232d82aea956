"""ROS 2 hygiene: domains claimed alone, a child's environment, Fast DDS's shared memory."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from dbml.core.errors import DbmlError
from dbml.harness import ros2env
from dbml.harness.ros2env import (
    claim_domain,
    fastdds_shm_files,
    remove_fastdds_shm,
    ros2_child_env,
)
from dbml.transports.rclpy.fastdds import DEFAULT_PROFILES_FILE, PROFILE_FILE_NAME
from tests.harness.children import (
    CHILD_TIMEOUT_S,
    first_line,
    held_by_live_processes,
    python_child,
)

_CLAIMER = """
import sys
from pathlib import Path
from dbml.harness.ros2env import claim_domain
with claim_domain(Path(sys.argv[1])) as domain:
    print(domain, flush=True)
    sys.stdin.read()  # holds the claim until the test closes stdin (or kills this process)
"""

_LOCKER = """
import fcntl, os, sys
fds = [os.open(path, os.O_RDONLY) for path in sys.argv[1:]]
for fd in fds:
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
print("ready", flush=True)
sys.stdin.read()
"""
"""Holds ``flock`` on each file named, as a Fast DDS process holds its ``_el`` files."""

_RCLPY_PEER = """
import os, sys
import rclpy
from rclpy.context import Context
from rclpy.signals import SignalHandlerOptions
context = Context()
rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
           signal_handler_options=SignalHandlerOptions.NO)
node = rclpy.create_node("shm_test_peer", context=context)
print("ready", flush=True)
sys.stdin.read()
"""


def test_concurrent_claims_never_share_a_domain(tmp_path: Path) -> None:
    claimers = 8
    all_in = threading.Barrier(claimers + 1, timeout=CHILD_TIMEOUT_S)
    domains: list[int] = []
    errors: list[BaseException] = []

    def claim() -> None:
        try:
            with claim_domain(tmp_path) as domain:
                domains.append(domain)
                all_in.wait()  # every claim held at once
                all_in.wait()
        except BaseException as error:  # reported below, as the test's failure
            errors.append(error)
            all_in.abort()

    threads = [threading.Thread(target=claim) for _ in range(claimers)]
    for thread in threads:
        thread.start()
    all_in.wait()
    assert len(set(domains)) == claimers
    assert all(domain in ros2env.DOMAIN_IDS for domain in domains)
    all_in.wait()
    for thread in threads:
        thread.join(CHILD_TIMEOUT_S)
    assert not errors


def test_a_claim_is_released_when_its_block_ends(tmp_path: Path) -> None:
    with claim_domain(tmp_path) as first:
        pass
    seen: list[int] = []

    def fail_inside() -> None:
        with claim_domain(tmp_path) as second:
            seen.append(second)
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        fail_inside()
    assert seen == [first]
    with claim_domain(tmp_path) as third:
        assert third == first


def test_a_claim_is_released_when_its_process_ends(tmp_path: Path) -> None:
    with python_child(_CLAIMER, str(tmp_path)) as other:
        theirs = int(first_line(other))
        with claim_domain(tmp_path) as mine:
            assert mine != theirs
        other.kill()  # no clean exit: the kernel releases the lock
        other.wait(CHILD_TIMEOUT_S)
    with claim_domain(tmp_path) as again:
        assert again == theirs


def test_no_free_domain_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ros2env, "DOMAIN_IDS", range(1, 3))
    with (
        claim_domain(tmp_path),
        claim_domain(tmp_path),
        pytest.raises(DbmlError, match=r"1\.\.2 is claimed"),
        claim_domain(tmp_path),
    ):
        pass


def test_a_child_env_has_its_domain_logs_and_the_discovery_profile(tmp_path: Path) -> None:
    base = {"PATH": "/usr/bin", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "0"}
    env = ros2_child_env(domain_id=42, log_dir=tmp_path / "logs", base=base)
    assert env["ROS_DOMAIN_ID"] == "42"
    assert env["ROS_LOG_DIR"] == str(tmp_path / "logs")
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env["PATH"] == "/usr/bin"
    assert Path(env[DEFAULT_PROFILES_FILE]) == (tmp_path / "logs" / PROFILE_FILE_NAME).resolve()
    assert Path(env[DEFAULT_PROFILES_FILE]).is_file()
    assert base["ROS_DOMAIN_ID"] == "0"  # the base itself is left as it was


def test_a_child_env_keeps_the_users_profile(tmp_path: Path) -> None:
    base = {DEFAULT_PROFILES_FILE: "/etc/my_fastdds.xml"}
    env = ros2_child_env(domain_id=3, log_dir=tmp_path, base=base)
    assert env[DEFAULT_PROFILES_FILE] == "/etc/my_fastdds.xml"
    assert not (tmp_path / PROFILE_FILE_NAME).exists()


def _fake_group(shm: Path, base: str, *, port: bool) -> list[Path]:
    """A Fast DDS segment's or port's files, as a process leaves them in /dev/shm."""
    files = [shm / base, shm / f"{base}_el"]
    if port:
        files.append(shm / f"sem.{base}_mutex")
    for path in files:
        path.write_bytes(b"")
    return sorted(files)


def test_shm_cleanup_removes_only_the_listed_processes_files(tmp_path: Path) -> None:
    mine = _fake_group(tmp_path, "fastdds_0123456789abcdef", port=False)
    mine += _fake_group(tmp_path, "fastdds_port7411", port=True)
    theirs = _fake_group(tmp_path, "fastdds_fedcba9876543210", port=False)
    theirs += _fake_group(tmp_path, "fastdds_port7413", port=True)
    nobodys = _fake_group(tmp_path, "fastdds_00000000aaaaaaaa", port=False)  # a zombie of others
    lttng = tmp_path / "lttng-ust-wait-6"
    lttng.write_bytes(b"")
    locks = [str(path) for path in mine if path.name.endswith("_el")]
    their_locks = [str(path) for path in theirs if path.name.endswith("_el")]
    with python_child(_LOCKER, *locks) as owner, python_child(_LOCKER, *their_locks) as other:
        assert first_line(owner) == "ready"
        assert first_line(other) == "ready"
        files = fastdds_shm_files([owner.pid], shm_dir=tmp_path)
        assert files == sorted(mine)
        assert fastdds_shm_files([owner.pid, other.pid], shm_dir=tmp_path) == sorted(mine + theirs)
        assert remove_fastdds_shm(files) == []  # its owner still runs
        assert all(path.exists() for path in files)

        owner.kill()
        owner.wait(CHILD_TIMEOUT_S)
        assert fastdds_shm_files([owner.pid], shm_dir=tmp_path) == []  # a dead process owns none
        assert sorted(remove_fastdds_shm(files + theirs)) == sorted(mine)
    assert not [path for path in mine if path.exists()]
    assert all(path.exists() for path in theirs + nobodys + [lttng])


def test_shm_cleanup_takes_a_port_left_without_its_lock(tmp_path: Path) -> None:
    """A cleanly ended owner whose port a killed peer still counted on leaves it lock-less."""
    segment, mutex = tmp_path / "fastdds_port7415", tmp_path / "sem.fastdds_port7415_mutex"
    for path in (segment, mutex):
        path.write_bytes(b"")
    assert sorted(remove_fastdds_shm([segment, mutex])) == sorted([segment, mutex])
    assert list(tmp_path.iterdir()) == []  # the lock it took for the removal went too
    assert remove_fastdds_shm([segment, mutex]) == []


def test_shm_cleanup_touches_nothing_but_fast_dds_files(tmp_path: Path) -> None:
    others = [tmp_path / "lttng-ust-wait-6", tmp_path / "notes.txt", tmp_path / "fastdds_x"]
    for path in others:
        path.write_bytes(b"")
    assert remove_fastdds_shm(others) == []
    assert sorted(tmp_path.iterdir()) == sorted(others)  # no lock file made either


@pytest.mark.integration
def test_a_killed_rclpy_process_leaves_no_shared_memory(ros_domain: int, tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    env = ros2_child_env(domain_id=ros_domain, log_dir=tmp_path)
    with python_child(_RCLPY_PEER, env=env) as peer:
        assert first_line(peer) == "ready"
        files = fastdds_shm_files([peer.pid])
        assert files
        assert all(path.parent == ros2env.SHM_DIR for path in files)
        assert any(path.name.startswith("fastdds_port") for path in files)
        peer.kill()
        peer.wait(CHILD_TIMEOUT_S)
    remove_fastdds_shm(files)
    # A port's name may have been taken over meanwhile by a new process of this host
    assert held_by_live_processes(files)
    assert [path for path in tmp_path.iterdir() if path.name.startswith("python")]  # its log
