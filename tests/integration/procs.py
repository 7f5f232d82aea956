"""Start real ``dbml`` processes for integration tests, read their output, end them by PID."""

from __future__ import annotations

import itertools
import os
import signal
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dbml.harness.processes import free_port
from dbml.harness.supervisor import ProcessChild, Supervisor
from dbml.scenarios.teleop import MAX_RATE_HZ, ROBOTS
from dbml.transports.zenoh import ZenohTransport

ROOT = Path(__file__).resolve().parents[2]
STOP_S = 10.0
"""How long a process told to end may take before it is killed."""


def start_rclpy_cameras(children: Supervisor, env: Mapping[str, str]) -> dict[str, ProcessChild]:
    """The paper's two cameras as plain rclpy drivers (``rclpy_camera``), by topic.

    Images serialising to each robot's size, at the cameras' 16 Hz maximum.
    """
    return {
        camera.topic: children.start(
            f"camera-{camera.robot}",
            [
                sys.executable,
                "-m",
                "tests.integration.rclpy_camera",
                camera.topic,
                str(MAX_RATE_HZ),
                str(camera.size_bytes),
            ],
            env=env,
            cwd=ROOT,
            stdin=False,
        )
        for camera in ROBOTS
    }


def publish_argv(topic: str, size_bytes: int, *more: str) -> list[str]:
    """``dbml publish`` of a camera-like channel, 1-16 Hz (the paper's bounds)."""
    bounds = ["--size-bytes", str(size_bytes), "--min-hz", "1", "--max-hz", "16"]
    return ["publish", topic, *bounds, *more]


class Proc:
    """One ``python -m dbml ...`` process (or ``-m module``), a child of a ``Supervisor``.

    Its stdin is /dev/null (as a command's in a shell), its stdout read line by line, its
    stderr logged; ended by its PID.
    """

    _names = itertools.count()

    def __init__(
        self,
        args: list[str],
        env: Mapping[str, str],
        *,
        module: str = "dbml",
        children: Supervisor | None = None,
    ) -> None:
        self.args = args
        self._own = children is None
        self.children = Supervisor() if children is None else children
        command = args[0] if args and "/" not in args[0] else module.rpartition(".")[2]
        name = f"{command}-{next(self._names)}"
        self.child: ProcessChild = self.children.start(
            name, [sys.executable, "-m", module, *args], env=env, cwd=ROOT, stdin=False
        )

    @property
    def pid(self) -> int:
        return self.child.pid

    def poll(self) -> int | None:
        """Its exit code, None while it runs."""
        return self.child.poll()

    def wait(self, timeout_s: float) -> int | None:
        """Its exit code, waiting up to ``timeout_s`` (None: it still runs)."""
        return self.child.wait(timeout_s)

    def next_line(self, *, timeout_s: float) -> str | None:
        """Its next line on stdout, None if none came within ``timeout_s`` (or it ended)."""
        line = self.child.next(timeout_s=timeout_s)
        return None if line is None or line.ended else line.text

    def json_lines(self, *, timeout_s: float) -> Iterator[dict[str, Any]]:
        """Its JSON lines (other lines skipped) as they come, until ``timeout_s`` passes."""
        return self.children.reports(self.child.name, timeout_s=timeout_s)

    def drain(self) -> None:
        """Forget the stdout lines printed so far: what is read next is printed from now on."""
        self.children.drop(self.child.name)

    def stderr(self) -> str:
        """What it wrote on stderr so far."""
        return self.child.log()

    @property
    def stderr_lines(self) -> list[str]:
        """``stderr()`` line by line, each with its newline."""
        return self.stderr().splitlines(keepends=True)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = STOP_S) -> int:
        """``sig``, then SIGKILL after ``timeout_s``: its exit code."""
        self.child.send_signal(sig)
        if self.child.wait(timeout_s) is None:
            self.child.force(timeout_s=timeout_s)
        code = self.child.poll()
        assert code is not None
        if self._own:
            self.children.close()
        return code


class Fleet:
    """Processes on one private loopback rendezvous, plus an in-process probe session."""

    def __init__(self) -> None:
        self.port = free_port()
        self.env = dict(os.environ, DBML_ZENOH_PORT=str(self.port))
        self.children = Supervisor()
        self._probe: ZenohTransport | None = None

    def start(self, *args: str) -> Proc:
        return Proc(list(args), self.env, children=self.children)

    @property
    def probe(self) -> ZenohTransport:
        if self._probe is None:
            self._probe = ZenohTransport(host="probe", port=self.port)
        return self._probe

    def param(self, name: str) -> object:
        return self.probe.params.get(name)

    def close(self) -> None:
        try:
            self.children.close()
        finally:
            if self._probe is not None:
                self._probe.close()


@contextmanager
def fleet() -> Iterator[Fleet]:
    made = Fleet()
    try:
        yield made
    finally:
        made.close()
