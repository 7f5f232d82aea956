"""A private ROS 1 world for a test.

A real ``rosmaster`` on a free port, real node processes on their own loopback hosts (ROS_IP),
and the real ``rosparam`` / ``rostopic`` tools.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from dbml.harness.processes import foreign_interpreter_env
from dbml.harness.rosmaster import RosMaster
from dbml.harness.supervisor import Supervisor
from dbml.transports.ros1.master import MasterClient
from tests.conftest import require
from tests.integration.procs import Proc

TOOLS = ("rosmaster", "rosparam", "rostopic")


def ros1_problem() -> str | None:
    """Why ROS 1 tests cannot run here, or None."""
    if importlib.util.find_spec("rospy") is None:
        return (
            f"{sys.executable} cannot import rospy: run scripts/install-ros1; `make test` runs "
            "the ROS 1 tests (pytest -m ros1) in .venv-ros1, made from Debian's Python"
        )
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        return f"ROS 1 tools not found: {', '.join(missing)} (scripts/install-ros1)"
    return None


def require_ros1() -> None:
    require(ros1_problem(), what="run the ROS 1 tests")


class RosNet:
    def __init__(self, master: RosMaster, home: Path) -> None:
        self.master = master
        self.api = MasterClient(master.uri, caller_id="/dbml_test")
        self.env = dict(
            os.environ, ROS_MASTER_URI=master.uri, ROS_HOME=str(home), ROS_LOG_DIR=str(home)
        )
        self.procs: list[Proc] = []

    def node(
        self, *args: str, host: str, module: str = "dbml", env: dict[str, str] | None = None
    ) -> Proc:
        """A process on ROS host ``host`` (a loopback address such as 127.0.0.2)."""
        env = dict(self.env, ROS_IP=host, ROS_HOSTNAME=host, **(env or {}))
        proc = Proc(list(args), env, module=module)
        self.procs.append(proc)
        return proc

    def param(self, name: str) -> object:
        """Straight from the parameter server (XML-RPC, as rosparam does)."""
        return self.api.call("getParam", name, missing_ok=True)

    def tool(self, name: str, *args: str) -> str:
        """Run a ROS command-line tool (``rosparam``, ``rostopic``) against this master."""
        done = subprocess.run(
            [name, *args],
            env=foreign_interpreter_env(self.env),  # Debian's /usr/bin/python3 runs the tools
            capture_output=True,
            text=True,
            timeout=20,
            check=False,
        )
        assert done.returncode == 0, f"{name} {' '.join(args)}: {done.stderr}"
        return done.stdout.strip()

    def rosparam(self, *args: str) -> str:
        return self.tool("rosparam", *args)

    def rostopic(self, *args: str) -> str:
        return self.tool("rostopic", *args)

    def wait_param(
        self, name: str, predicate: object, *, timeout_s: float = 15.0, what: str = ""
    ) -> object:
        """Poll ``name`` until ``predicate(value)`` holds; the value."""
        assert callable(predicate)
        deadline = time.monotonic() + timeout_s
        value = self.param(name)
        while not predicate(value):
            if time.monotonic() > deadline:
                pytest.fail(f"{name}={value!r} after {timeout_s} s: waited for {what}")
            time.sleep(0.05)
            value = self.param(name)
        return value

    def rostopic_hz(self, topic: str, *, window: int, timeout_s: float) -> float:
        """``rostopic hz -w window``'s first average over a full window of messages."""
        rate: float | None = None
        deadline = time.monotonic() + timeout_s
        with Supervisor() as children:  # ended by SIGINT, as rostopic expects, by its PID
            hz = children.start(
                "rostopic-hz",
                ["rostopic", "hz", "-w", str(window), topic],
                env=foreign_interpreter_env(self.env),
                stdin=False,
                stop_signal=signal.SIGINT,
            )
            while (left := deadline - time.monotonic()) > 0:
                line = hz.next(timeout_s=left)
                if line is None or line.ended:
                    break
                if match := re.search(r"average rate: ([0-9.]+)", line.text):
                    rate = float(match.group(1))
                elif (
                    (match := re.search(r"window: (\d+)", line.text))
                    and rate is not None
                    and int(match.group(1)) >= window
                ):
                    return rate
        pytest.fail(f"rostopic hz {topic}: no full window of {window} in {timeout_s} s")

    def close(self) -> None:
        for proc in self.procs:
            proc.stop()
        self.api.close()
        self.master.stop()


@contextmanager
def rosnet(home: Path) -> Iterator[RosNet]:
    require_ros1()
    net = RosNet(RosMaster().start(), home)
    try:
        yield net
    finally:
        net.close()
