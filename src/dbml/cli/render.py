"""Everything the CLI shows a person: rich tables, live views and plots.

The library returns typed results; this module is the only place that turns them into terminal
output (JSON is produced next to it, in ``dbml.cli.main`` and ``dbml.cli.documents``; plots in
``dbml.cli.plots``), so no library module imports rich.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import TracebackType
from typing import TYPE_CHECKING

from rich.console import Console, Group
from rich.live import Live
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from dbml.core.allocation import Allocation, Status
from dbml.experiment.analysis import (
    BUDGET_BACK_FRACTION,
    OUTAGE_AFTER_S,
    RATE_TOLERANCE,
    RATE_TOLERANCE_HZ,
    latest,
    link_at,
)
from dbml.experiment.spec import URGENT_RATE_HZ, URGENT_SIZE_BYTES
from dbml.runtime.monitor import MONITOR_PARAMETERS, MonitorView
from dbml.scenarios.reproduce import RobotRow
from dbml.scenarios.teleop import LINK_MBIT, ROBOTS, STEPS
from dbml.testbed.options import Policy, Topology

if TYPE_CHECKING:
    from dbml.demo.photos import PhotoDemoResult
    from dbml.demo.runner import DemoResult
    from dbml.experiment.runner import Snapshot
    from dbml.testbed.result import TestbedResult

__all__ = [
    "ExperimentView",
    "allocation_table",
    "demo_table",
    "mark",
    "monitor_table",
    "photo_demo_table",
    "reproduce_table",
    "testbed_table",
]

OK_MARK = "[green]✓[/]"
URGENT_MARK = "[bold yellow]![/]"
BAD_MARK = "[bold red]✗[/]"


def mark(ok: bool) -> str:
    """A green tick or a red cross."""
    return OK_MARK if ok else BAD_MARK


def allocation_table(allocation: Allocation) -> Table:
    """``dbml allocate``: one row per channel, the status and the budget in the caption."""
    table = Table(title=f"dbml allocate — strategy {allocation.strategy.value}")
    for name in ("topic", "priority", "normalized", "floor Hz", "rate Hz", "bytes/s", "share"):
        table.add_column(name, justify="left" if name == "topic" else "right")
    for c in allocation.channels:
        table.add_row(
            c.topic,
            f"{c.priority:.2f}",
            f"{c.normalized_priority:.3f}",
            f"{c.floor_hz:.2f}",
            f"{c.rate_hz:.2f}",
            f"{c.bytes_per_s:,.0f}",
            f"{c.share:.2%}",
        )
    style = "green" if allocation.status is Status.OPTIMAL else "bold red"
    table.caption = (
        f"[{style}]{allocation.status.value}[/]: {allocation.message}; "
        f"{allocation.total_bytes_per_s:,.0f} of {allocation.budget_bytes_per_s:,.0f} B/s"
    )
    return table


def reproduce_table(steps: list[list[RobotRow]]) -> Table:
    """``dbml reproduce table2``: ours beside the paper's, a mark per cell."""
    table = Table(title="Table 2 of the paper, reproduced (strategy paper, 11 Mbit, 1-16 Hz)")
    for name in ("step", "robot", "tc s", "p", "f Hz", "paper", "BW %", "paper", "static"):
        table.add_column(name, justify="right", no_wrap=True)
    for step in steps:
        for row in step:
            tc = "∞" if math.isinf(row.tc_s) else f"{row.tc_s:g}"
            table.add_row(
                str(row.step) if row is step[0] else "",
                row.robot,
                f"{tc} {mark(row.tc_match)}",
                f"{row.priority:.2f} {mark(row.priority_match)}",
                f"{row.rate_hz:.2f} {mark(row.rate_match)}",
                f"{row.paper.rate_hz:g}",
                f"{row.share * 100:.2f} {mark(row.share_match)}",
                f"{row.paper.share_percent:.2f}",
                f"{row.static_rate_hz:.2f}",
                end_section=row is step[-1],
            )
    matched = sum(all(r.match for r in step) for step in steps)
    all_match = matched == len(steps)
    verdict = "[green]all match[/]" if all_match else "[bold red]MISMATCH[/]"
    table.caption = (
        f"{matched}/{len(steps)} steps match the paper to its printed precision: {verdict}. "
        "static: the paper's fixed baseline, Hz."
    )
    return table


def monitor_table(view: MonitorView) -> Table:
    """``dbml monitor``: every live channel, the budget and the estimator in the title."""
    title = "dbml monitor"
    if view.bandwidth_mbit is not None:
        title += f" — budget {view.bandwidth_mbit:g} Mbit/s"
    if view.estimate_mbit is not None:
        title += f", estimate {view.estimate_mbit:.2f} Mbit/s"
        if view.estimator is not None:
            title += f" ({view.estimator})"
    table = Table(title=title)
    shown = [
        (p, p.column)
        for p in MONITOR_PARAMETERS
        if p.column is not None
        and (not p.column.optional or any(row.value(p) is not None for row in view.rows))
    ]
    for name in ("topic", "host", "managed", *(c.title for _, c in shown), "share", "status"):
        table.add_column(name, justify="left" if name in {"topic", "host", "status"} else "right")
    for row in view.rows:
        table.add_row(
            row.topic,
            row.host,
            "yes" if row.managed else "no",
            *(_fmt(row.value(p), column.format) for p, column in shown),
            _fmt(row.share, ".1%"),
            row.status,
        )
    if view.status_message is not None:
        table.caption = view.status_message
    return table


def _fmt(value: float | str | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


class ExperimentView:
    """A running demo or testbed: a progress bar and a live table of what arrives.

    Redrawn at every report of the operator (``update`` is the runner's observer).

    With ``show=False`` (``--json``) it shows nothing.
    """

    def __init__(
        self,
        console: Console,
        *,
        title: str,
        step_s: float,
        link_mbit: float = LINK_MBIT,
        schedule: Sequence[tuple[float, float]] = (),
        show: bool = True,
        robots: Sequence[str] | None = None,
    ) -> None:
        self._title, self._link_mbit, self._schedule = title, link_mbit, schedule
        self._robots = [c.robot for c in ROBOTS] if robots is None else list(robots)
        self._show = show
        self._progress = Progress(
            TextColumn(f"step {{task.fields[step]}}/{len(STEPS)}"),
            BarColumn(),
            TimeRemainingColumn(),
            console=console,
        )
        self._task = self._progress.add_task("run", total=len(STEPS) * step_s, step=0)
        self._live = Live(self._progress, console=console, auto_refresh=False, transient=True)

    def __enter__(self) -> ExperimentView:
        if self._show:
            self._live.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._show:
            self._live.stop()

    def update(self, snapshot: Snapshot) -> None:
        """Show the newest reports (nothing when not shown, as under ``--json``)."""
        if not self._show:
            return
        self._progress.update(self._task, completed=snapshot.elapsed_s, step=snapshot.step)
        table = Table(title=self._title, expand=False)
        for name in ("robot", "allocated Hz", "delivered Hz", "p95 ms", "Mbit/s"):
            table.add_column(name, justify="right")
        robots = latest(snapshot.arrivals, snapshot.ticks, robots=self._robots)
        for robot in robots:
            table.add_row(
                robot.robot,
                _fmt(robot.allocated_hz, ".2f"),
                f"{robot.delivered_hz:.2f}",
                _fmt(robot.latency_p95_ms, ".0f"),
                f"{robot.goodput_mbit:.2f}",
            )
        link = link_at(self._schedule, snapshot.elapsed_s, self._link_mbit)
        caption = f"received {sum(r.goodput_mbit for r in robots):.2f} Mbit/s on a {link:g}"
        caption += " Mbit/s link"
        budget = snapshot.ticks[-1].budget_mbit if snapshot.ticks else None
        if budget is not None:
            caption += f", budget {budget:.2f}"
        table.caption = caption
        self._live.update(Group(self._progress, table), refresh=True)


def demo_table(result: DemoResult) -> Table:
    """``dbml demo teleop``: per step and robot, allocated beside Table 2 and measured."""
    table = Table(
        title=f"Teleoperation, live over {result.options.transport.name} "
        f"({result.options.step_seconds:g} s per step)"
    )
    for name in ("step", "robot", "tc s", "p", "alloc Hz", "Table 2", "measured", "Mbit/s"):
        table.add_column(name, justify="right", no_wrap=True)
    for step in result.steps:
        for i, robot in enumerate(step.robots):
            measured = robot.measured
            table.add_row(
                str(step.step.step) if i == 0 else "",
                measured.robot,
                "∞" if math.isinf(robot.tc_s) else f"{robot.tc_s:g}",
                f"{robot.priority:.2f}",
                _fmt(measured.allocated_hz, ".2f") + f" {mark(robot.matches_table2)}",
                f"{robot.table2_hz:g}",
                f"{measured.delivered_hz:.2f} {mark(robot.within_tolerance)}",
                f"{step.total_mbit:.2f}/{step.step.link_mbit:g}" if i == 0 else "",
                end_section=i == len(step.robots) - 1,
            )
    verdict = "[green]all steps match[/]" if result.ok else "[bold red]NOT all steps match[/]"
    table.caption = (
        f"{verdict}: allocated = Table 2, measured within {RATE_TOLERANCE * 100:g} % "
        f"(or {RATE_TOLERANCE_HZ:g} Hz) of allocated"
    )
    return table


def photo_demo_table(result: PhotoDemoResult) -> Table:
    """``dbml demo teleop --frames photos``: per step and robot, the ladder beside rate only."""
    table = Table(
        title=f"Real frames over {result.transport.name}, {result.step_seconds:g} s a step: "
        "the ladder, then rate only (0)"
    )
    for name in ("step", "robot", "p", "keep", "rung", "fps", "SSIM", "fps0", "SSIM0"):
        table.add_column(name, justify="right", no_wrap=True)
    table.add_column("utility", justify="right", no_wrap=True)
    rate_only = result.rate_only.steps if result.rate_only is not None else ()
    for k, step in enumerate(result.ladder.steps):
        other = rate_only[k] if k < len(rate_only) else None
        for i, robot in enumerate(step.robots):
            measured = robot.measured
            base = other.robots[i].measured if other is not None else None
            good = robot.at_least_min_fps and robot.at_max_if_prioritised
            table.add_row(
                str(step.step.step) if i == 0 else "",
                measured.robot,
                f"{robot.priority:.2f}",
                "rate" if robot.preference.value == "keep_rate" else "-",
                measured.encoding or "-",
                f"{measured.delivered_hz:.1f}{mark(good)}",
                _fmt(measured.ssim, ".3f"),
                _fmt(None if base is None else base.delivered_hz, ".1f"),
                _fmt(None if base is None else base.ssim, ".3f"),
                (
                    f"{step.utility:.2f}/{_fmt(other.utility if other else None, '.2f')}"
                    if i == 0
                    else ""
                ),
                end_section=i == len(step.robots) - 1,
            )
    checks = result.checks
    gain = result.gain
    verdict = "[green]ok[/]" if result.ok else "[bold red]NOT ok[/]"
    failed = [name.replace("_", " ") for name, held in checks.items() if not held]
    wire = result.ladder.wire
    table.caption = (
        f"{verdict}{': ' + ', '.join(failed) if failed else ''}. Utility "
        f"{result.ladder.utility:.3f} with the ladder, "
        f"{_fmt(result.rate_only.utility if result.rate_only else None, '.3f')} rate only "
        f"({_fmt(None if gain is None else gain * 100, '+.1f')} %; every camera at its maximum "
        f"rate with SSIM 1 would reach {result.ladder.ceiling:.3f}, "
        f"{_fmt(None if result.gain_ceiling is None else result.gain_ceiling * 100, '+.1f')} %); "
        "the worst 1-s window "
        f"{wire.worst_bytes:,} B against {result.ladder.limit_bytes:,.0f} B (the budget and one "
        "frame). fps and SSIM as the operator decoded them."
    )
    return table


def testbed_table(result: TestbedResult) -> Table:
    """``dbml testbed teleop``: per step and robot, the summary and targets in the caption."""
    options = result.options
    title = f"Teleoperation over a shaped link — policy {options.policy}"
    if options.strategy and options.policy is Policy.DBML:
        title += f" ({options.strategy}{', estimating' if options.estimate else ''})"
    if options.fleet or options.topology is not Topology.PEER:
        title += f", {options.robots} robots, topology {options.topology}"
    table = Table(title=title)
    expected = result.expected_hz
    photos = options.frames.value == "photos"
    columns = ["step", "robot", *(["allocate()"] if expected else []), "alloc", "deliv"]
    columns += ["SSIM", "rung"] if photos else []
    for name in (*columns, "p50", "p95", "lost", "goodput", "budget"):
        table.add_column(name, justify="right", no_wrap=True)
    table.add_column("link", justify="right", no_wrap=True)
    most_urgent = result.urgent_robots() if options.fleet else ()
    for k, step in enumerate(result.steps):
        for i, robot in enumerate(step.robots):
            first = i == 0
            table.add_row(
                str(step.step) if first else "",
                robot.robot
                + (f" {URGENT_MARK}" if most_urgent and most_urgent[k] == robot.robot else ""),
                *([f"{expected[k][i]:.2f}"] if expected else []),
                _fmt(robot.allocated_hz, ".2f"),
                _fmt(robot.delivered_hz, ".2f"),
                *([_fmt(robot.ssim, ".3f"), robot.encoding or "-"] if photos else []),
                _fmt(robot.latency_p50_ms, ".0f"),
                _fmt(robot.latency_p95_ms, ".0f"),
                str(robot.lost),
                _fmt(step.goodput_mbit, ".2f") if first else "",
                _fmt(step.budget_mbit, ".2f") if first else "",
                f"{step.link_mbit:g}" if first else "",
                end_section=i == len(step.robots) - 1,
            )
    summary = result.summary()
    lines = [
        "rates in Hz, one-way latency in ms, goodput, budget and link in Mbit/s",
        *(
            [
                f"{URGENT_MARK} the step's most urgent robot; allocate(): the optimizer's rule on "
                "the priorities the events imply"
            ]
            if expected or most_urgent
            else []
        ),
        f"goodput {_fmt(summary.goodput_fraction_mean, '.0%')} of the link on average, "
        f"p95 latency at most {_fmt(summary.latency_p95_ms_max, '.0f')} ms, "
        f"{summary.lost} frames lost",
    ]
    if result.wire is not None and result.limit_bytes is not None:
        lines.append(
            f"the worst 1-s window of what arrived: {result.wire.worst_bytes:,} B against "
            f"{result.limit_bytes:,.0f} B (the budget and one frame), "
            f"{result.wire.over_share:.1%} of windows over"
        )
    for change in result.changes:
        link = f"link {change.from_mbit:g} -> {change.to_mbit:g} Mbit/s at {change.t_s:g} s"
        share = f"goodput {_fmt(change.goodput_share_after, '.0%')} of it from 3 s on"
        if change.drop:
            cut = change.first_cut_s
            lines.append(
                f"{link}: first cut after {_fmt(None if cut is None else cut * 1000, '.0f')} ms, "
                f"peak p95 {_fmt(change.max_latency_p95_ms, '.0f')} ms, latency and losses "
                f"recovered after {_fmt(change.recovery_s, '.2f')} s, "
                f"{change.lost_after} lost, {share}"
            )
        else:
            lines.append(
                f"{link}: budget at {BUDGET_BACK_FRACTION * 100:g} % of the link after "
                f"{_fmt(change.budget_recovery_s, '.2f')} s, {share}"
            )
    if len(result.phases) > 1:
        for phase in result.phases:
            lines.append(
                f"{phase.start_s:g}-{phase.end_s:g} s at {phase.link_mbit:g} Mbit/s: "
                f"utilisation {phase.utilisation:.0%}, p95 {_fmt(phase.latency_p95_ms, '.0f')} "
                f"ms, {phase.lost} lost"
            )
    for outage in result.outages:
        lines.append(
            f"link down {outage.start_s:g}-{outage.end_s:g} s: most urgent ({outage.urgent}) "
            f"first frame {_fmt(outage.first_urgent_s, '.2f')} s after the restoration, "
            f"first fresh one {_fmt(outage.first_fresh_urgent_s, '.2f')} s; "
            f"{outage.stale} stale frames, {outage.lost} lost; worst 1-s window in the "
            f"{OUTAGE_AFTER_S:g} s after: {_fmt(outage.worst_window_mbit, '.2f')} Mbit/s, "
            f"of frames sent after it {_fmt(outage.worst_sent_after_mbit, '.2f')} "
            f"(budget {_fmt(outage.budget_mbit, '.2f')})"
        )
    for urgent in result.urgent:
        lines.append(
            f"urgent stream ({URGENT_SIZE_BYTES:,} B at {URGENT_RATE_HZ:g} Hz), {urgent.name}: "
            f"p50 {_fmt(urgent.latency_p50_ms, '.0f')} ms, "
            f"p95 {_fmt(urgent.latency_p95_ms, '.0f')} ms, "
            f"{urgent.received} received, {urgent.lost} lost"
        )
    for name, ok in summary.targets.items():
        lines.append(f"{mark(ok)} {name.replace('_', ' ')}")
    table.caption = "\n".join(lines)
    return table
