"""Start real ``dbml`` processes for integration tests, read their output, end them by PID."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dbml.harness.processes import end_process, free_port
from dbml.transports.zenoh import ZenohTransport

ROOT = Path(__file__).resolve().parents[2]


def publish_argv(topic: str, size_bytes: int, *more: str) -> list[str]:
    """``dbml publish`` of a camera-like channel, 1-16 Hz (the paper's bounds)."""
    bounds = ["--size-bytes", str(size_bytes), "--min-hz", "1", "--max-hz", "16"]
    return ["publish", topic, *bounds, *more]


class Proc:
    """One ``python -m dbml ...`` process (or ``-m module``) with its output lines collected."""

    def __init__(self, args: list[str], env: dict[str, str], *, module: str = "dbml") -> None:
        self.args = args
        self.popen = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        self.stdout: queue.Queue[str] = queue.Queue()
        self.stderr_lines: list[str] = []
        self._pumps = [
            threading.Thread(target=self._pump_out, daemon=True),
            threading.Thread(target=self._pump_err, daemon=True),
        ]
        for pump in self._pumps:
            pump.start()

    def _pump_out(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.stdout.put(line)

    def _pump_err(self) -> None:
        assert self.popen.stderr is not None
        for line in self.popen.stderr:
            self.stderr_lines.append(line)

    def json_lines(self, *, timeout_s: float) -> Iterator[dict[str, Any]]:
        """Parsed stdout lines as they come, until ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.stdout.get(timeout=left)
            except queue.Empty:
                return
            try:
                yield json.loads(line)
            except ValueError:
                continue

    def drain(self) -> None:
        """Forget the stdout lines printed so far: what is read next is printed from now on."""
        while True:
            try:
                self.stdout.get_nowait()
            except queue.Empty:
                return

    def stderr(self) -> str:
        return "".join(self.stderr_lines)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        end_process(self.popen, sig=sig, timeout_s=timeout_s)
        for pump in self._pumps:
            pump.join(timeout=5)  # EOF once the process is gone
        for pipe in (self.popen.stdout, self.popen.stderr):
            if pipe is not None:
                pipe.close()
        return self.popen.returncode


class Fleet:
    """Processes on one private loopback rendezvous, plus an in-process probe session."""

    def __init__(self) -> None:
        self.port = free_port()
        self.env = dict(os.environ, DBML_ZENOH_PORT=str(self.port))
        self.procs: list[Proc] = []
        self._probe: ZenohTransport | None = None

    def start(self, *args: str) -> Proc:
        proc = Proc(list(args), self.env)
        self.procs.append(proc)
        return proc

    @property
    def probe(self) -> ZenohTransport:
        if self._probe is None:
            self._probe = ZenohTransport(host="probe", port=self.port)
        return self._probe

    def param(self, name: str) -> object:
        return self.probe.params.get(name)

    def close(self) -> None:
        for proc in self.procs:
            proc.stop()
        if self._probe is not None:
            self._probe.close()


@contextmanager
def fleet() -> Iterator[Fleet]:
    made = Fleet()
    try:
        yield made
    finally:
        made.close()
