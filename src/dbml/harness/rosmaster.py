"""A ROS master of our own, for a demo or a test, when none runs.

``RosMaster`` starts ``rosmaster --core`` (Debian's ``python3-rosmaster``) on a free loopback port
and ends it by PID; ``RosMaster.reuse_or_start()`` takes the one at ``ROS_MASTER_URI`` instead
when it answers, and leaves it running.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from typing import IO

from dbml.core.errors import TransportError
from dbml.harness.processes import end_process, foreign_interpreter_env, free_port
from dbml.transports.ros1.master import answers

__all__ = ["RosMaster"]


class RosMaster:
    """``rosmaster --core`` on a free loopback port: ``with RosMaster() as master: master.uri``.

    ``RosMaster.reuse_or_start()`` takes the master at ``ROS_MASTER_URI`` when one answers.
    """

    def __init__(self, *, port: int | None = None, ready_timeout_s: float = 15.0) -> None:
        self.port = port or free_port()
        self.uri = f"http://127.0.0.1:{self.port}/"
        self._ready_timeout_s = ready_timeout_s
        self.process: subprocess.Popen[bytes] | None = None
        self.reused = False
        self._log: IO[bytes] | None = None

    @classmethod
    def reuse_or_start(cls) -> RosMaster:
        """The running master at ``ROS_MASTER_URI`` (not ours to stop), else a new one."""
        existing = os.environ.get("ROS_MASTER_URI")
        if existing and answers(existing):
            master = cls()
            master.uri, master.reused = existing, True
            return master
        return cls().start()

    def start(self) -> RosMaster:
        """Start ``rosmaster --core`` and wait until it answers."""
        executable = shutil.which("rosmaster")
        if executable is None:
            raise TransportError(
                "rosmaster not found: install Debian's ROS 1 packages (scripts/install-ros1)"
            )
        log = self._log = tempfile.TemporaryFile()  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen(
            [executable, "--core", "-p", str(self.port)],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=foreign_interpreter_env(),  # Debian's /usr/bin/python3, not ours
        )
        deadline = time.monotonic() + self._ready_timeout_s
        while not answers(self.uri):
            if self.process.poll() is not None or time.monotonic() > deadline:
                log.seek(0)
                output = log.read()[-500:].decode(errors="replace")
                self.stop()
                raise TransportError(f"rosmaster on port {self.port} did not start: {output}")
            time.sleep(0.05)
        return self

    def stop(self) -> None:
        """End the master this object started (by PID); a reused one is left running."""
        process, self.process = self.process, None
        if process is not None:
            end_process(process)
        log, self._log = self._log, None
        if log is not None:
            log.close()

    def __enter__(self) -> RosMaster:
        return self if self.process is not None or self.reused else self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()
