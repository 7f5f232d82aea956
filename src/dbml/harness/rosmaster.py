"""A ROS master of our own, for a demo or a test, when none runs.

``RosMaster`` starts ``rosmaster --core`` (Debian's ``python3-rosmaster``) on a free loopback port
and ends it by PID; ``RosMaster.reuse_or_start()`` takes the one at ``ROS_MASTER_URI`` instead
when it answers, and leaves it running.
"""

from __future__ import annotations

import os
import shutil
import signal

from dbml.core.errors import TransportError
from dbml.harness.processes import foreign_interpreter_env, free_port
from dbml.harness.supervisor import ChildExitedError, ProcessChild, Supervisor
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
        self._children: Supervisor | None = None
        self.reused = False

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
        children = self._children = Supervisor()
        child = children.start(
            "rosmaster",
            [executable, "--core", "-p", str(self.port)],
            env=foreign_interpreter_env(),  # Debian's /usr/bin/python3, not ours
            stdin=False,
            read_stdout=False,
            stop_signal=signal.SIGTERM,
        )
        try:
            children.wait_until(
                lambda: answers(self.uri),
                timeout_s=self._ready_timeout_s,
                watch=["rosmaster"],
                what="rosmaster to answer",
            )
        except (ChildExitedError, TimeoutError):
            output = child.log_tail(500)
            self.stop()
            raise TransportError(f"rosmaster on port {self.port} did not start: {output}") from None
        return self

    @property
    def process(self) -> ProcessChild | None:
        """The master's process, while this object runs one."""
        return None if self._children is None else self._children.process("rosmaster")

    def stop(self) -> None:
        """End the master this object started (by PID); a reused one is left running."""
        children, self._children = self._children, None
        if children is not None:
            children.close()

    def __enter__(self) -> RosMaster:
        return self if self._children is not None or self.reused else self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()
