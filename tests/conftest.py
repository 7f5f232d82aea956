"""Shared test helpers: waiting on conditions (never bare sleeps)."""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from tests.ros1.rosnet import RosNet


MONITOR_JSON_KEYS = frozenset(
    {
        "topic",
        "host",
        "managed",
        "priority",
        "size_bytes",
        "allocated_hz",
        "share",
        "preference",
        "encoding",
        "quality",
        "status",
        "estimate_mbit",
        "estimator",
    }
)
"""``dbml monitor --json``: the keys of each line (a contract scripts read)."""


def require(problem: str | None, *, what: str) -> None:
    """Skip with ``problem`` when something a test needs is missing; in CI (CI=true) fail."""
    if problem is None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI must {what}: {problem}")
    pytest.skip(problem)


def wait_for(predicate: Callable[[], bool], *, timeout_s: float = 5.0, what: str = "") -> None:
    """Poll ``predicate`` until it holds; fail the test with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what or predicate}")
        time.sleep(0.005)


@pytest.fixture
def ros(tmp_path: Path) -> Iterator[RosNet]:
    """A private ROS master with its nodes; skipped without ROS 1 (a failure when CI=true)."""
    from tests.ros1.rosnet import rosnet

    with rosnet(tmp_path) as net:
        yield net


_LTTNG = "lttng-ust-wait-*"
"""What ``import rclpy`` (LTTng's tracing) leaves in /dev/shm for the user, not per process."""
_lttng_before: set[Path] = set()
_FASTDDS = ("fastdds_*", "sem.fastdds_*")
"""A Fast DDS segment's or port's files (``dbml.harness.ros2env``)."""
_fastdds_before: set[Path] = set()


def _fastdds_files() -> set[Path]:
    return {path for pattern in _FASTDDS for path in Path("/dev/shm").glob(pattern)}


def pytest_configure(config: pytest.Config) -> None:
    """Before any test module imports rclpy: what /dev/shm held of LTTng's already.

    And Ctrl-C as a terminal's foreground job has it: a shell that starts the suite in the
    background (``cmd &``) ignores SIGINT, every process a test starts inherits that, and the
    tests that press Ctrl-C on a process they started would see it ignored.
    """
    _lttng_before.update(Path("/dev/shm").glob(_LTTNG))
    _fastdds_before.update(_fastdds_files())
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_unconfigure(config: pytest.Config) -> None:
    """Remove the /dev/shm files this session created (those from before are someone else's).

    LTTng's, and the Fast DDS files of processes that ended without removing theirs (one killed,
    or one that met a killed one): only those no live process holds, a test's or another's.
    """
    for path in set(Path("/dev/shm").glob(_LTTNG)) - _lttng_before:
        path.unlink(missing_ok=True)
    if new := _fastdds_files() - _fastdds_before:
        from dbml.harness.ros2env import remove_fastdds_shm

        remove_fastdds_shm(new)


@pytest.hookimpl(tryfirst=True)  # before -m selects by marker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark ``ros1`` every test using ``ros``: it needs rospy, so it runs in .venv-ros1.

    ROS 1 and ROS 2's wheels cannot share an interpreter: ``make test`` runs ``-m "not ros1"``
    in .venv and ``-m ros1`` in .venv-ros1 (tests/ros1/conftest.py marks its whole directory).
    """
    for item in items:
        if "ros" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.ros1)


@pytest.fixture(autouse=True)
def isolated_logging() -> Iterator[None]:
    """A ``main()`` run in-process may configure the root logger: undo it after each test.

    Its handler writes to the test's captured stderr, which is closed once the test ends; left
    in place it would turn every later log line of the session into a logging error.
    """
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        yield
    finally:
        for handler in root.handlers:
            if handler not in handlers:
                root.removeHandler(handler)
        root.setLevel(level)


@pytest.fixture(scope="session", autouse=True)
def ros2_process_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """This test process's own ROS 2 settings, before any test starts an rclpy context.

    rclpy logs to ``ROS_LOG_DIR`` (else ``~/.ros/log``) and Fast DDS reads its profile once per
    process, at the first participant: both are set here, for the whole session (the 3-s lease
    and fast announcements of ``dbml.transports.rclpy.fastdds``; children get theirs from
    ``ros2_child_env``).
    """
    from dbml.transports.rclpy.fastdds import apply_discovery_profile

    log_dir = tmp_path_factory.mktemp("ros-log")
    saved = {k: os.environ.get(k) for k in ("ROS_LOG_DIR", "FASTDDS_DEFAULT_PROFILES_FILE")}
    os.environ["ROS_LOG_DIR"] = str(log_dir)
    apply_discovery_profile(log_dir)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@pytest.fixture
def ros_domain() -> Iterator[int]:
    """A ROS 2 domain this test holds alone (parallel runs never share one: see ros2env)."""
    from dbml.harness.ros2env import claim_domain

    with claim_domain() as domain:
        yield domain


@pytest.fixture
def ros_log_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A log directory for ROS 2, also ``ROS_LOG_DIR`` here, so rclpy writes nothing to ~/.ros."""
    log_dir = tmp_path / "ros-log"
    log_dir.mkdir()
    monkeypatch.setenv("ROS_LOG_DIR", str(log_dir))
    return log_dir
