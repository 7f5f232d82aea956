"""``dbml testbed teleop``: the paper's teleoperation scenario over a real, shaped network.

Robots R1 and R2 and the operator are network namespaces; their traffic to the operator shares
one ``tc``-shaped link (and, with ``--uplink``, a robot's own slower uplink). The real runtime runs
inside: zenoh on explicit endpoints with shared memory off, the optimizer on the operator's side,
a process per robot publishing 84,000 / 21,000 byte frames on Table 2's schedule. The runner
starts them, changes the link's rate on schedule, collects every frame the operator received and
reports, per step and robot, allocated and delivered rates, latency, losses and goodput.

Every namespace and process is removed at the end, also on error, Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import contextlib
import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from dbml.core.allocation import Strategy
from dbml.harness.processes import RoleProcesses
from dbml.scenarios.teleop import ROBOTS, STEPS
from dbml.testbed.analysis import (
    Frame,
    Tick,
    analyse,
    link_at,
    parse_schedule,
    parse_uplinks,
)
from dbml.testbed.netns import Network, TestbedError, privilege_problem
from dbml.testbed.roles import ROLES, RoleSpec

__all__ = ["POLICIES", "TestbedResult", "print_result", "run_teleop_testbed"]

POLICIES = ("dbml", "static", "unmanaged")
DEFAULT_UTILIZATION = 0.92
"""dbml's budget as a share of the shaped rate: TCP/IP and Ethernet headers take ~4.3 % of the
wire (measured: raw TCP gets 95.7 % of a tbf rate), the rest is margin."""
PAPER_STATIC_UTILIZATION = 1.0
"""The paper's static baseline splits the whole 11 Mbit/s: 13.1 Hz per camera."""
READY_TIMEOUT_S = 60.0
START_MARGIN_S = 1.5
ZENOH_PORT = 7447
OPTIMIZER_PORT = 7448
HOST_OF_ROLE = {"operator": "op", "optimizer": "op", "r1": "r1", "r2": "r2"}
IDENTITY = {"operator": "operator", "optimizer": "base-station", "r1": "robot-r1", "r2": "robot-r2"}


@dataclass
class TestbedResult:
    __test__ = False  # not a pytest test class despite the name

    policy: str
    strategy: str | None
    link_mbit: float
    step_seconds: float
    utilization: float | None
    estimate: bool
    schedule: tuple[tuple[float, float], ...] = ()
    uplinks_mbit: dict[str, float] = field(default_factory=dict)
    run_id: str = ""
    steps: list[dict[str, Any]] = field(default_factory=list)
    series: list[dict[str, Any]] = field(default_factory=list)
    changes: list[dict[str, Any]] = field(default_factory=list)
    interrupted: bool = False

    def summary(self) -> dict[str, Any]:
        robots = [r for s in self.steps for r in s["robots"]]
        errors = [
            abs(r["delivered_hz"] - r["allocated_hz"]) / r["allocated_hz"]
            for r in robots
            if r["allocated_hz"]
        ]
        p95 = [r["latency_p95_ms"] for r in robots if r["latency_p95_ms"] is not None]
        p50 = [r["latency_p50_ms"] for r in robots if r["latency_p50_ms"] is not None]
        fractions = [s["goodput_mbit"] / s["link_mbit"] for s in self.steps]
        summary: dict[str, Any] = {
            "steps": len(self.steps),
            "max_rate_error": max(errors, default=None),
            "latency_p50_ms_max": max(p50, default=None),
            "latency_p95_ms_max": max(p95, default=None),
            "lost": sum(r["lost"] for r in robots),
            "goodput_mbit_mean": _mean([s["goodput_mbit"] for s in self.steps]),
            "goodput_fraction_mean": _mean(fractions),
            "goodput_fraction_min": min(fractions, default=None),
            "changes": self.changes,
        }
        for robot, capacity in sorted(self.uplinks_mbit.items()):
            used = [r["goodput_mbit"] for r in robots if r["robot"] == robot]
            summary[f"uplink_{robot}"] = {
                "capacity_mbit": capacity,
                "goodput_mbit_max": max(used, default=None),
            }
        summary["targets"] = self.targets()
        return summary

    def targets(self) -> dict[str, bool]:
        """The issue's expectations that apply to this run (policy dbml)."""
        if self.policy != "dbml" or not self.steps:
            return {}
        robots = [r for s in self.steps for r in s["robots"]]
        targets: dict[str, bool] = {}
        if not self.schedule or all(mbit == self.link_mbit for _, mbit in self.schedule):
            targets["delivered_within_5pct"] = all(
                r["allocated_hz"]
                and abs(r["delivered_hz"] - r["allocated_hz"]) <= 0.05 * r["allocated_hz"]
                for r in robots
            )
            targets["p95_under_200ms"] = all(
                r["latency_p95_ms"] is not None and r["latency_p95_ms"] < 200 for r in robots
            )
            targets["nothing_lost"] = all(r["lost"] == 0 for r in robots)
            if not self.uplinks_mbit:  # a capped uplink leaves the shared link underused
                targets["goodput_at_least_90pct"] = all(
                    s["goodput_mbit"] >= 0.9 * s["link_mbit"] for s in self.steps
                )
        for change in self.changes:
            if "recovery_s" in change:
                key = f"recovered_within_3s_after_{change['t_s']:g}s"
                targets[key] = change["recovery_s"] is not None and change["recovery_s"] <= 3.0
            elif "budget_recovery_s" in change:
                key = f"budget_back_within_10s_after_{change['t_s']:g}s"
                reached = change["budget_recovery_s"]
                targets[key] = reached is not None and reached <= 10.0
        return targets

    def as_json(self) -> dict[str, Any]:
        return {
            "policy": self.policy,
            "strategy": self.strategy,
            "link_mbit": self.link_mbit,
            "link_schedule": [list(entry) for entry in self.schedule],
            "uplinks_mbit": self.uplinks_mbit,
            "estimate": self.estimate,
            "utilization": self.utilization,
            "step_seconds": self.step_seconds,
            "run_id": self.run_id,
            "interrupted": self.interrupted,
            "steps": self.steps,
            "summary": self.summary(),
            "series": self.series,
        }


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM unwinds like Ctrl-C, so the namespaces are removed either way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(_sig: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _check(
    *,
    policy: str,
    link_mbit: float,
    step_seconds: float,
    schedule: str | None,
    estimate: bool,
    uplinks: Sequence[str],
    strategy: str | None,
    utilization: float | None,
) -> tuple[tuple[tuple[float, float], ...], dict[str, float], str | None, float | None]:
    if policy not in POLICIES:
        raise TestbedError(f"--policy={policy!r} is not one of: {', '.join(POLICIES)}")
    if not link_mbit > 0:
        raise TestbedError(f"--link-mbit={link_mbit!r} must be > 0")
    if not step_seconds >= 1.0:
        raise TestbedError(f"--step-seconds={step_seconds!r} must be >= 1")
    parsed = parse_schedule(schedule) if schedule else ()
    uplinks_mbit = parse_uplinks(uplinks, [c.robot for c in ROBOTS])
    if policy == "unmanaged":
        for flag, given in (
            ("--estimate", estimate),
            ("--strategy", strategy),
            ("--utilization", utilization),
        ):
            if given:
                raise TestbedError(f"{flag} needs an optimizer: --policy=unmanaged has none")
        return parsed, uplinks_mbit, None, None
    if policy == "static":
        if strategy not in (None, Strategy.STATIC.value):
            raise TestbedError(f"--strategy={strategy!r}: --policy=static is the static one")
        return parsed, uplinks_mbit, Strategy.STATIC.value, utilization or PAPER_STATIC_UTILIZATION
    chosen = strategy or (Strategy.LP.value if uplinks_mbit else Strategy.PAPER.value)
    if chosen not in {s.value for s in Strategy}:
        raise TestbedError(
            f"--strategy={strategy!r} is not one of: {', '.join(s.value for s in Strategy)}"
        )
    if uplinks_mbit and chosen != Strategy.LP.value:
        raise TestbedError(f"--uplink needs --strategy=lp (per-link limits), not {chosen!r}")
    util = DEFAULT_UTILIZATION if utilization is None else utilization
    if not 0 < util <= 1:
        raise TestbedError(f"--utilization={utilization!r} must be in (0, 1]")
    return parsed, uplinks_mbit, chosen, util


def run_teleop_testbed(
    *,
    policy: str = "dbml",
    link_mbit: float = 11.0,
    step_seconds: float = 6.0,
    link_schedule: str | None = None,
    estimate: bool = False,
    uplinks: Sequence[str] = (),
    strategy: str | None = None,
    utilization: float | None = None,
    console: Console | None = None,
    show_live: bool = True,
    plot: Path | None = None,
) -> TestbedResult:
    schedule, uplinks_mbit, chosen, util = _check(
        policy=policy,
        link_mbit=link_mbit,
        step_seconds=step_seconds,
        schedule=link_schedule,
        estimate=estimate,
        uplinks=uplinks,
        strategy=strategy,
        utilization=utilization,
    )
    problem = privilege_problem()
    if problem is not None:
        raise TestbedError(f"dbml testbed needs root to build network namespaces: {problem}")
    console = console or Console(stderr=True)
    first_rate = link_at(schedule, 0.0, link_mbit)
    network = Network(
        robots=("r1", "r2"),
        link_mbit=first_rate,
        uplinks_mbit={robot.lower(): mbit for robot, mbit in uplinks_mbit.items()},
    )
    result = TestbedResult(
        policy=policy,
        strategy=chosen,
        link_mbit=link_mbit,
        step_seconds=step_seconds,
        utilization=util,
        estimate=estimate,
        schedule=schedule,
        uplinks_mbit=uplinks_mbit,
        run_id=network.run_id,
    )
    frames: list[Frame] = []
    ticks: list[Tick] = []
    t0 = 0.0
    with _sigterm_as_interrupt():
        try:
            network.build()
            roles = RoleProcesses()
            try:
                t0 = _run(
                    network,
                    roles,
                    result=result,
                    frames=frames,
                    ticks=ticks,
                    console=console,
                    show_live=show_live,
                )
            finally:
                roles.close()
        except KeyboardInterrupt:
            result.interrupted = True
        finally:
            network.close()
    if t0:
        analysed = analyse(
            frames,
            ticks,
            robots=[c.robot for c in ROBOTS],
            t0=t0,
            step_s=step_seconds,
            steps=len(STEPS) if not result.interrupted else _steps_done(ticks, t0, step_seconds),
            link_mbit=link_mbit,
            schedule=schedule,
        )
        result.steps, result.series = analysed["steps"], analysed["series"]
        result.changes = analysed["changes"]
    if plot is not None and result.series:
        _plot(result, plot)
    return result


def _steps_done(ticks: Sequence[Tick], t0: float, step_s: float) -> int:
    last = max((t.t_s for t in ticks), default=t0)
    return max(0, min(len(STEPS), int((last - t0) // step_s)))


def _specs(network: Network, result: TestbedResult) -> dict[str, RoleSpec]:
    op = network.hosts["op"].address
    operator_ep = f"tcp/{op}:{ZENOH_PORT}"
    optimizer_ep = f"tcp/{op}:{OPTIMIZER_PORT}"
    managed = result.policy != "unmanaged"
    common: dict[str, Any] = {
        "policy": result.policy,
        "step_s": result.step_seconds,
        "link_mbit": result.link_mbit,
        "utilization": result.utilization or 1.0,
        "strategy": result.strategy or Strategy.PAPER.value,
        "estimate": result.estimate,
        "uplinks_mbit": result.uplinks_mbit,
    }
    specs = {
        "operator": RoleSpec(**common, host=IDENTITY["operator"], listen=[operator_ep]),
    }
    if managed:
        specs["optimizer"] = RoleSpec(
            **common, host=IDENTITY["optimizer"], listen=[optimizer_ep], connect=[operator_ep]
        )
    for role in ("r1", "r2"):
        address = network.hosts[role].address
        specs[role] = RoleSpec(
            **common,
            host=IDENTITY[role],
            listen=[f"tcp/{address}:{ZENOH_PORT}"],
            connect=[operator_ep, *([optimizer_ep] if managed else [])],
        )
    return specs


def _run(
    network: Network,
    roles: RoleProcesses,
    *,
    result: TestbedResult,
    frames: list[Frame],
    ticks: list[Tick],
    console: Console,
    show_live: bool,
) -> float:
    """Start the roles, run the schedule, collect the operator's reports; returns t0."""
    specs = _specs(network, result)
    for role in ROLES:
        if role in specs:
            argv = [sys.executable, "-m", "dbml.testbed.roles", role, specs[role].to_json()]
            roles.spawn(role, network.exec_argv(HOST_OF_ROLE[role], argv))
    try:
        ended = roles.wait_ready(set(specs), timeout_s=READY_TIMEOUT_S)
    except queue.Empty:
        raise TestbedError("testbed roles did not get ready in time") from None
    if ended is not None:
        raise _exited_early(roles, ended)
    t0 = time.time() + START_MARGIN_S
    roles.send(f"start {t0!r}")
    stop = threading.Event()
    changer = threading.Thread(
        target=_change_link, args=(network, result.schedule, t0, stop), daemon=True
    )
    changer.start()
    total = len(STEPS) * result.step_seconds
    progress = Progress(
        TextColumn("step {task.fields[step]}/10"),
        BarColumn(),
        TimeRemainingColumn(),
        console=console,
    )
    task = progress.add_task("testbed", total=total, step=0)
    try:
        with Live(
            _live_view(progress, result, frames, ticks, t0),
            console=console,
            auto_refresh=False,
            transient=True,
        ) as live:
            end = t0 + total + 30.0
            while True:
                try:
                    role, message = roles.messages.get(timeout=0.5)
                except queue.Empty:
                    if time.time() > end:
                        raise TestbedError("testbed timed out waiting for the operator") from None
                    continue
                if message is None:
                    if role == "operator":
                        break
                    if time.time() < t0 + total:
                        raise _exited_early(roles, role)
                    continue
                if message.get("type") == "done":
                    break
                if message.get("type") == "tick":
                    frames.extend(
                        Frame(
                            int(r[0]), int(r[1]), float(r[2]), float(r[3]), int(r[4]), float(r[5])
                        )
                        for r in message["frames"]
                    )
                    ticks.append(
                        Tick(
                            message["t"],
                            tuple(message["allocated_hz"]),
                            message["budget_mbit"],
                            message["estimate_mbit"],
                            message.get("estimator"),
                        )
                    )
                    elapsed = min(max(0.0, message["t"] - t0), total)
                    progress.update(
                        task,
                        completed=elapsed,
                        step=min(10, int(elapsed // result.step_seconds) + 1),
                    )
                    if show_live:
                        live.update(_live_view(progress, result, frames, ticks, t0), refresh=True)
    finally:
        stop.set()
    return t0


def _exited_early(roles: RoleProcesses, role: str) -> TestbedError:
    """One line: the role and the last lines of its log."""
    tail = " | ".join(roles.log_tail(role).strip().splitlines()[-3:])
    return TestbedError(f"testbed role {role} exited early{': ' + tail if tail else ''}")


def _change_link(
    network: Network, schedule: Sequence[tuple[float, float]], t0: float, stop: threading.Event
) -> None:
    for at, mbit in schedule:
        if at <= 0:
            continue
        if stop.wait(max(0.0, t0 + at - time.time())):
            return
        with contextlib.suppress(TestbedError):  # the network is being torn down
            network.set_link_rate(mbit)


def _live_view(
    progress: Progress,
    result: TestbedResult,
    frames: Sequence[Frame],
    ticks: Sequence[Tick],
    t0: float,
) -> Group:
    now = ticks[-1].t_s if ticks else t0
    table = Table(title=f"dbml testbed teleop — {result.policy}, live", expand=False)
    for name in ("robot", "allocated Hz", "delivered Hz", "p95 ms", "Mbit/s"):
        table.add_column(name, justify="right")
    total = 0.0
    for i, camera in enumerate(ROBOTS):
        recent = [f for f in frames[-400:] if f.robot == i and now - 1.0 <= f.arrival_s < now]
        latencies = sorted(f.arrival_s - f.sent_s for f in recent)
        p95 = latencies[int(0.95 * (len(latencies) - 1))] * 1000 if latencies else None
        mbit = sum(f.size_bytes for f in recent) * 8e-6
        total += mbit
        allocated = ticks[-1].allocated_hz[i] if ticks else None
        table.add_row(
            camera.robot,
            "-" if allocated is None else f"{allocated:.2f}",
            f"{len(recent):d}",
            "-" if p95 is None else f"{p95:.0f}",
            f"{mbit:.2f}",
        )
    link = link_at(result.schedule, now - t0, result.link_mbit)
    budget = ticks[-1].budget_mbit if ticks else None
    caption = f"received {total:.2f} Mbit/s on a {link:g} Mbit/s link"
    if budget is not None:
        caption += f", budget {budget:.2f}"
    table.caption = caption
    return Group(progress, table)


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def result_table(result: TestbedResult) -> Table:
    title = f"Teleoperation over a shaped link — policy {result.policy}"
    if result.strategy and result.policy == "dbml":
        title += f" ({result.strategy}{', estimating' if result.estimate else ''})"
    table = Table(title=title)
    for name in ("step", "robot", "alloc", "deliv", "p50", "p95", "lost", "goodput", "budget"):
        table.add_column(name, justify="right", no_wrap=True)
    table.add_column("link", justify="right", no_wrap=True)
    for step in result.steps:
        for i, robot in enumerate(step["robots"]):
            first = i == 0
            table.add_row(
                str(step["step"]) if first else "",
                robot["robot"],
                _fmt(robot["allocated_hz"], ".2f"),
                _fmt(robot["delivered_hz"], ".2f"),
                _fmt(robot["latency_p50_ms"], ".0f"),
                _fmt(robot["latency_p95_ms"], ".0f"),
                str(robot["lost"]),
                _fmt(step["goodput_mbit"], ".2f") if first else "",
                _fmt(step["budget_mbit"], ".2f") if first else "",
                f"{step['link_mbit']:g}" if first else "",
                end_section=i == len(step["robots"]) - 1,
            )
    summary = result.summary()
    lines = [
        "rates in Hz, one-way latency in ms, goodput, budget and link in Mbit/s",
        f"goodput {_fmt(summary['goodput_fraction_mean'], '.0%')} of the link on average, "
        f"p95 latency at most {_fmt(summary['latency_p95_ms_max'], '.0f')} ms, "
        f"{summary['lost']} frames lost",
    ]
    for change in result.changes:
        if "recovery_s" in change:
            lines.append(
                f"link {change['from_mbit']:g} -> {change['to_mbit']:g} Mbit/s at "
                f"{change['t_s']:g} s: latency and losses recovered after "
                f"{_fmt(change['recovery_s'], '.2f')} s, {change['lost_after']} lost"
            )
        elif "budget_recovery_s" in change:
            lines.append(
                f"link {change['from_mbit']:g} -> {change['to_mbit']:g} Mbit/s at "
                f"{change['t_s']:g} s: budget at 90 % of the link after "
                f"{_fmt(change['budget_recovery_s'], '.2f')} s"
            )
    for name, ok in summary["targets"].items():
        lines.append(f"{'[green]✓[/]' if ok else '[red]✗[/]'} {name.replace('_', ' ')}")
    table.caption = "\n".join(lines)
    return table


def print_result(result: TestbedResult, console: Console) -> None:
    console.print(result_table(result))


def _plot(result: TestbedResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (rates, latency, bandwidth) = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    times = [p["t"] for p in result.series]
    for i, camera in enumerate(ROBOTS):
        allocated = [p["robots"][i]["allocated_hz"] for p in result.series]
        delivered = [p["robots"][i]["delivered_hz"] for p in result.series]
        p95 = [p["robots"][i]["latency_p95_ms"] for p in result.series]
        if any(a is not None for a in allocated):
            rates.step(times, allocated, where="post", label=f"{camera.robot} allocated")
        rates.plot(times, delivered, ".", alpha=0.6, label=f"{camera.robot} delivered (1 s)")
        latency.plot(times, p95, label=f"{camera.robot} p95 (1 s)")
    rates.set_ylabel("rate (Hz)")
    rates.legend(loc="upper right", fontsize=8)
    latency.set_ylabel("one-way latency (ms)")
    latency.set_yscale("log")
    latency.axhline(200, color="grey", linestyle=":", linewidth=1)
    latency.legend(loc="upper right", fontsize=8)
    bandwidth.plot(times, [p["goodput_mbit"] for p in result.series], label="goodput (1 s)")
    bandwidth.step(
        times, [p["link_mbit"] for p in result.series], where="post", color="red", label="link"
    )
    budgets = [p["budget_mbit"] for p in result.series]
    if any(b is not None for b in budgets):
        label = "budget (estimate)" if result.estimate else "budget"
        bandwidth.step(times, budgets, where="post", color="green", label=label)
    for k in range(len(STEPS) + 1):
        for axis in (rates, latency, bandwidth):
            axis.axvline(k * result.step_seconds, color="grey", linewidth=0.4)
    bandwidth.set_ylim(bottom=0)
    bandwidth.set_xlabel("time since step 1 (s)")
    bandwidth.set_ylabel("Mbit/s")
    bandwidth.legend(loc="lower right", fontsize=8)
    figure.suptitle(f"dbml testbed teleop: policy {result.policy} on a tc-shaped link")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
