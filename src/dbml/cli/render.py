"""Everything the CLI shows a person: rich tables, live views and plots.

The library returns typed results; this module is the only place that turns them into terminal
output (JSON is produced next to it, in ``dbml.cli.main``), so no library module imports rich.
"""

from __future__ import annotations

import math

from rich.table import Table

from dbml.core.allocation import Allocation, Status
from dbml.runtime.monitor import MonitorView
from dbml.scenarios.reproduce import RobotRow

__all__ = ["allocation_table", "mark", "monitor_table", "reproduce_table"]

OK_MARK = "[green]✓[/]"
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
    for name in (
        "topic",
        "host",
        "managed",
        "priority",
        "size B",
        "allocated Hz",
        "share",
        "status",
    ):
        table.add_column(name, justify="left" if name in {"topic", "host", "status"} else "right")
    for row in view.rows:
        table.add_row(
            row.topic,
            row.host,
            "yes" if row.managed else "no",
            f"{row.priority:.2f}",
            "-" if row.size_bytes is None else f"{row.size_bytes:,.0f}",
            "-" if row.allocated_hz is None else f"{row.allocated_hz:.2f}",
            "-" if row.share is None else f"{row.share:.1%}",
            row.status,
        )
    if view.status_message is not None:
        table.caption = view.status_message
    return table
