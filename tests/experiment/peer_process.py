"""A child of a run's entry (``python -m dbml.experiment KIND``), as the runner starts one."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pytest

from dbml.experiment.entry import Kind, child_argv
from dbml.experiment.spec import RoleSpec
from dbml.harness.supervisor import Supervisor


class Peer:
    """One ``kind`` child: its reports in order (nothing else on stdout), its stdin, its end."""

    def __init__(
        self,
        kind: Kind,
        role: str,
        spec: RoleSpec,
        *options: str,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.role = role
        self.children = Supervisor()
        self.child = self.children.start(
            role, child_argv(kind, role, spec.to_json(), *options), env=env
        )

    def tail(self) -> str:
        """The end of what it wrote on stderr."""
        return self.child.log_tail()

    def next(self, timeout_s: float) -> dict[str, Any]:
        """Its next report; the test fails if none comes, it ended, or it wrote anything else."""
        line = self.child.next(timeout_s=timeout_s)
        if line is None or line.ended:
            how = "ended" if line is not None else f"no report within {timeout_s} s"
            pytest.fail(f"{self.role}: {how}; rc={self.child.poll()}: {self.tail()}")
        if line.report is None:
            pytest.fail(f"{self.role}: {line.text!r} on stdout is not a report")
        return line.report

    def send(self, line: str) -> None:
        """One control line; nothing if the process already ended."""
        self.child.send(line)

    def wait(self, timeout_s: float) -> int | None:
        """Its exit code, waiting up to ``timeout_s``."""
        return self.child.wait(timeout_s)

    def stop(self, timeout_s: float) -> int | None:
        """Ask it to stop (an operator that reported ``done`` ends by itself); its exit code."""
        self.send("stop")
        return self.child.wait(timeout_s)

    def close(self) -> None:
        """End the process by PID, its log with it."""
        self.children.close()
