"""A bench's ``python -m dbml`` nodes: started, watched and ended by PID through one supervisor.

The reaction and budget-integrity benches run an optimizer, publishers and subscribers as
``dbml`` commands on a transport of the run's own; each node's stderr is ``workdir/<name>.log``,
read to judge the run (a fail-safe, a refusal) and shown when it fails.
"""

from __future__ import annotations

import sys
from pathlib import Path

from dbml.harness.supervisor import ProcessChild, Supervisor

__all__ = ["STOP_S", "Nodes"]

STOP_S = 10.0
"""How long a node told to end (SIGTERM: it closes its session) may take before SIGKILL."""


class Nodes:
    """The ``python -m dbml`` processes of one run, each ended by its PID."""

    def __init__(self, env: dict[str, str], transport_args: list[str], workdir: Path) -> None:
        self._env = env
        self._transport_args = transport_args
        self._children = Supervisor(logs=workdir)
        self._ended: set[str] = set()

    @property
    def pids(self) -> list[int]:
        """Every node started, running or not."""
        return self._children.pids()

    def live_pids(self) -> list[int]:
        """The nodes that still run."""
        return [
            child.pid
            for child in self._children.children.values()
            if isinstance(child, ProcessChild) and child.poll() is None
        ]

    def start(self, name: str, command: str, *args: str) -> None:
        """``python -m dbml COMMAND`` on the run's transport, as node ``name``."""
        self._children.start(
            name,
            [sys.executable, "-m", "dbml", command, *self._transport_args, *args],
            env=self._env,
            stdin=False,  # a command: asked to end by SIGTERM
        )

    def end(self, name: str) -> None:
        """End one node on purpose (a leave)."""
        self._ended.add(name)
        self._children.end(name, ask_s=STOP_S)

    def exited(self) -> list[str]:
        """Nodes that exited without being asked to."""
        return [
            f"{name} (exit {code})"
            for name, child in self._children.children.items()
            if name not in self._ended and (code := child.poll()) is not None
        ]

    def logged(self, text: str) -> list[str]:
        """The nodes whose log holds ``text``."""
        return [name for name, child in self._children.children.items() if text in child.log()]

    def count(self, name: str, text: str) -> int:
        """Lines of node ``name``'s log that hold ``text``."""
        return sum(text in line for line in self._children[name].log().splitlines())

    def logs(self, lines: int = 12) -> str:
        """The end of every node's log."""
        parts = []
        for name, child in self._children.children.items():
            tail = child.log().splitlines()[-lines:]
            parts.append(f"--- {name} ---\n" + "\n".join(tail))
        return "\n".join(parts)

    def stop(self) -> None:
        """SIGTERM every node (it closes its session), then SIGKILL what still runs."""
        self._children.close()
