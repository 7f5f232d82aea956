"""``dbml demo teleop``: run the live scenario, show it, check it against Table 2.

The parent starts the roles (OS processes over zenoh and ROS 1, threads over memory), gives them
one start time, renders the operator's reports live and, per step and robot, prints tc, priority,
allocated and measured Hz, and the total Mbit/s against the budget. Over ROS 1 it uses the master
at ``ROS_MASTER_URI`` when one answers and otherwise starts ``rosmaster`` for the run; each role is
a node with its own ROS_IP on loopback (127.0.0.x), so R1, R2 and the operator are different ROS
hosts. Every process it started is ended by PID on the way out, also on error and Ctrl-C.
"""

from __future__ import annotations

import importlib.util
import os
import queue
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from dbml.core.errors import DbmlError
from dbml.demo.roles import ROLES, run_role
from dbml.harness.processes import RoleProcesses, free_port
from dbml.scenarios.reproduce import reproduce_table2
from dbml.harness.rosmaster import RosMaster
from dbml.scenarios.teleop import LINK_MBIT, ROBOTS, STEPS
from dbml.transports.memory import MemoryNetwork, MemoryTransport

__all__ = ["DemoResult", "run_teleop_demo"]

HOSTS = {"optimizer": "base-station", "r1": "robot-r1", "r2": "robot-r2", "operator": "operator"}
ROS1_HOSTS = {
    "optimizer": "127.0.0.1",
    "r1": "127.0.0.2",
    "r2": "127.0.0.3",
    "operator": "127.0.0.4",
}
"""ROS_IP per role: loopback addresses, so the master sees four hosts on one machine."""
TRANSPORTS = ("zenoh", "ros1", "memory")
RATE_TOLERANCE = 0.05
RATE_TOLERANCE_HZ = 0.3
READY_TIMEOUT_S = 60.0
START_MARGIN_S = 1.5


@dataclass
class DemoResult:
    step_seconds: float
    transport: str
    steps: list[dict[str, Any]] = field(default_factory=list)
    series: list[dict[str, Any]] = field(default_factory=list)
    interrupted: bool = False

    def evaluate(self) -> None:
        """Add the checks: measured within 5 % (or 0.3 Hz) of allocated; allocated = Table 2."""
        table2 = reproduce_table2()
        for step in self.steps:
            total = 0.0
            for robot, paper in zip(step["robots"], table2[step["step"] - 1], strict=True):
                allocated, measured = robot["allocated_hz"], robot["measured_hz"]
                robot["within_tolerance"] = (
                    allocated is not None
                    and measured is not None
                    and abs(measured - allocated)
                    <= max(RATE_TOLERANCE * allocated, RATE_TOLERANCE_HZ)
                )
                robot["table2_hz"] = round(paper.paper.rate_hz, 2)
                robot["matches_table2"] = (
                    allocated is not None and round(allocated, 2) == paper.paper.rate_hz
                )
                size = next(c.size_bytes for c in ROBOTS if c.topic == robot["topic"])
                total += (measured or 0.0) * size * 8 / 1e6
            step["total_mbit"] = total
            step["budget_mbit"] = LINK_MBIT

    @property
    def ok(self) -> bool:
        robots = [r for s in self.steps for r in s["robots"]]
        return (
            not self.interrupted
            and len(self.steps) == len(STEPS)
            and all(r["within_tolerance"] and r["matches_table2"] for r in robots)
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "scenario": "teleop",
            "transport": self.transport,
            "step_seconds": self.step_seconds,
            "budget_mbit": LINK_MBIT,
            "steps": self.steps,
            "ok": self.ok,
            "interrupted": self.interrupted,
        }


def _spawn(processes: RoleProcesses, step_s: float, master: RosMaster | None) -> None:
    """Start every role: over zenoh on a private rendezvous port (a mesh of its own), over ROS 1
    as nodes of ``master``, each on its own loopback address."""
    zenoh_port = str(free_port())
    for role in ROLES:
        argv = [sys.executable, "-m", "dbml.demo.roles", role, "--step-seconds", str(step_s)]
        if master is None:
            env = dict(os.environ, DBML_ZENOH_PORT=zenoh_port)
            processes.spawn(role, [*argv, "--host", HOSTS[role]], env=env)
        else:
            host = ROS1_HOSTS[role]
            env = dict(os.environ, ROS_MASTER_URI=master.uri, ROS_IP=host, ROS_HOSTNAME=host)
            processes.spawn(role, [*argv, "--transport", "ros1"], env=env)


class _Threads:
    """The same roles as threads sharing one in-process memory network."""

    def __init__(self, step_s: float) -> None:
        self.messages: queue.Queue[tuple[str, dict[str, Any] | None]] = queue.Queue()
        self.network = MemoryNetwork()
        self.stop = threading.Event()
        self.step_s = step_s
        self.threads: list[threading.Thread] = []

    def start(self, t0: float) -> None:
        for role in ROLES:
            transport = MemoryTransport(self.network, host=HOSTS[role])

            def body(role: str = role, transport: MemoryTransport = transport) -> None:
                def emit(message: dict[str, Any]) -> None:
                    self.messages.put((role, message))

                try:
                    run_role(role, transport, t0=t0, step_s=self.step_s, stop=self.stop, emit=emit)
                finally:
                    transport.close()
                    self.messages.put((role, None))

            thread = threading.Thread(target=body, name=f"demo-{role}", daemon=True)
            thread.start()
            self.threads.append(thread)

    def close(self) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(timeout=5.0)


def _live_view(progress: Progress, status: dict[str, Any] | None) -> Group:
    table = Table(title="dbml demo teleop — live", expand=False)
    for name in ("robot", "allocated Hz", "received Hz", "Mbit/s"):
        table.add_column(name, justify="right")
    total = 0.0
    for robot in (status or {}).get("robots", []):
        mbit = robot["bytes_per_s"] * 8 / 1e6
        total += mbit
        allocated = robot["allocated_hz"]
        table.add_row(
            robot["robot"],
            "-" if allocated is None else f"{allocated:.2f}",
            f"{robot['measured_hz']:.2f}",
            f"{mbit:.2f}",
        )
    table.caption = f"total {total:.2f} of {LINK_MBIT:g} Mbit/s"
    return Group(progress, table)


def _result_table(result: DemoResult) -> Table:
    table = Table(
        title=f"Teleoperation, live over {result.transport} ({result.step_seconds:g} s per step)"
    )
    for name in ("step", "robot", "tc s", "p", "alloc Hz", "Table 2", "measured", "Mbit/s"):
        table.add_column(name, justify="right", no_wrap=True)
    for step in result.steps:
        for i, robot in enumerate(step["robots"]):
            tc = "∞" if robot["tc_s"] is None else f"{robot['tc_s']:g}"
            allocated, measured = robot["allocated_hz"], robot["measured_hz"]
            alloc_mark = "[green]✓[/]" if robot["matches_table2"] else "[red]✗[/]"
            meas_mark = "[green]✓[/]" if robot["within_tolerance"] else "[red]✗[/]"
            table.add_row(
                str(step["step"]) if i == 0 else "",
                robot["robot"],
                tc,
                f"{robot['priority']:.2f}",
                "-" if allocated is None else f"{allocated:.2f} {alloc_mark}",
                f"{robot['table2_hz']:g}",
                "-" if measured is None else f"{measured:.2f} {meas_mark}",
                f"{step['total_mbit']:.2f}/{step['budget_mbit']:g}" if i == 0 else "",
                end_section=i == len(step["robots"]) - 1,
            )
    verdict = "[green]all steps match[/]" if result.ok else "[bold red]NOT all steps match[/]"
    table.caption = f"{verdict}: allocated = Table 2, measured within 5 % (or 0.3 Hz) of allocated"
    return table


def _plot(result: DemoResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (rates, bandwidth) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    times = [s["t"] for s in result.series]
    for i, camera in enumerate(ROBOTS):
        allocated = [s["robots"][i]["allocated_hz"] for s in result.series]
        measured = [s["robots"][i]["measured_hz"] for s in result.series]
        rates.step(times, allocated, where="post", label=f"{camera.robot} allocated")
        rates.plot(times, measured, ".", alpha=0.6, label=f"{camera.robot} received")
    rates.set_ylabel("rate (Hz)")
    rates.legend(loc="upper right", fontsize=8)
    total = [sum(r["bytes_per_s"] for r in s["robots"]) * 8 / 1e6 for s in result.series]
    bandwidth.plot(times, total, label="received Mbit/s")
    bandwidth.axhline(LINK_MBIT, color="red", linestyle="--", label="budget")
    for k in range(len(STEPS) + 1):
        for axis in (rates, bandwidth):
            axis.axvline(k * result.step_seconds, color="grey", linewidth=0.5)
    bandwidth.set_xlabel("time since step 1 (s)")
    bandwidth.set_ylabel("Mbit/s")
    bandwidth.legend(loc="lower right", fontsize=8)
    figure.suptitle(f"dbml teleoperation demo over {result.transport}")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def run_teleop_demo(
    *,
    step_seconds: float = 3.0,
    transport: str = "zenoh",
    console: Console | None = None,
    show_live: bool = True,
    plot: Path | None = None,
) -> DemoResult:
    if step_seconds < 1.0:
        raise DbmlError(f"--step-seconds={step_seconds!r} must be >= 1 (rates down to 1.48 Hz)")
    if transport not in TRANSPORTS:
        raise DbmlError(f"--transport={transport!r} is not one of: {', '.join(TRANSPORTS)}")
    console = console or Console(stderr=True)
    result = DemoResult(step_seconds, transport)
    if transport == "ros1" and importlib.util.find_spec("rospy") is None:
        raise DbmlError(
            f"--transport ros1 needs rospy, which {sys.executable} cannot import: run "
            "`make run-ros1` (Debian's ROS packages and a venv of Debian's Python)"
        )
    master = RosMaster.reuse_or_start() if transport == "ros1" else None
    runner: RoleProcesses | _Threads
    runner = _Threads(step_seconds) if transport == "memory" else RoleProcesses()
    progress = Progress(
        TextColumn("step {task.fields[step]}/10"),
        BarColumn(),
        TimeRemainingColumn(),
        console=console,
    )
    task = progress.add_task("demo", total=len(STEPS) * step_seconds, step=0)
    try:
        if isinstance(runner, RoleProcesses):
            _spawn(runner, step_seconds, master)
            ended = runner.wait_ready(set(ROLES), timeout_s=READY_TIMEOUT_S)
            if ended is not None:
                raise DbmlError(f"demo role {ended} exited early:\n{runner.log_tail(ended)}")
            t0 = time.time() + START_MARGIN_S
            runner.send(f"start {t0!r}")
        else:
            t0 = time.time() + 0.5
            runner.start(t0)
        status: dict[str, Any] | None = None
        end = t0 + len(STEPS) * step_seconds + 30.0
        with Live(
            _live_view(progress, None), console=console, auto_refresh=False, transient=True
        ) as live:
            while True:
                try:
                    role, message = runner.messages.get(timeout=0.5)
                except queue.Empty:
                    if time.time() > end:
                        raise DbmlError("demo timed out waiting for the operator") from None
                    continue
                if message is None:
                    if role == "operator":
                        break
                    continue
                kind = message.get("type")
                if kind == "status":
                    status = message
                    result.series.append(message)
                    progress.update(
                        task,
                        completed=min(message["t"], len(STEPS) * step_seconds),
                        step=message["step"],
                    )
                elif kind == "step":
                    result.steps.append({"step": message["step"], "robots": message["robots"]})
                elif kind == "done":
                    break
                if show_live:
                    live.update(_live_view(progress, status), refresh=True)
    except KeyboardInterrupt:
        result.interrupted = True
    except queue.Empty:
        raise DbmlError("demo roles did not get ready in time") from None
    finally:
        runner.close()
        if master is not None:
            master.stop()
    result.evaluate()
    if plot is not None and result.series:
        _plot(result, plot)
    return result


def print_result(result: DemoResult, console: Console) -> None:
    console.print(_result_table(result))
