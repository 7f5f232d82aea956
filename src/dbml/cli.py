"""The ``dbml`` command line.

Exit codes: 0 success (``optimal``); 2 bad input or an unreadable file, with one line on stderr;
3 an infeasible budget (the result is still printed); 1 a reproduction that does not match.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from rich.console import Console
from rich.table import Table

from dbml.configfile import load_config
from dbml.core.allocation import Allocation, Status, Strategy, allocate
from dbml.core.errors import DbmlError
from dbml.sim.reproduce import RobotRow, reproduce_table2

__all__ = ["main"]

EXIT_OK = 0
EXIT_MISMATCH = 1
EXIT_USAGE = 2
EXIT_INFEASIBLE = 3


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line, like every other dbml error."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def _allocation_json(allocation: Allocation) -> dict[str, Any]:
    return {
        "strategy": allocation.strategy.value,
        "status": allocation.status.value,
        "message": allocation.message,
        "budget_bytes_per_s": allocation.budget_bytes_per_s,
        "total_bytes_per_s": allocation.total_bytes_per_s,
        "channels": [
            {
                "topic": c.topic,
                "priority": c.priority,
                "normalized_priority": c.normalized_priority,
                "floor_hz": c.floor_hz,
                "rate_hz": c.rate_hz,
                "bytes_per_s": c.bytes_per_s,
                "share": c.share,
            }
            for c in allocation.channels
        ],
    }


def _allocation_table(allocation: Allocation) -> Table:
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


def _cmd_allocate(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    strategy = Strategy(args.strategy) if args.strategy else config.dbm.strategy
    allocation = allocate(config.problem(), strategy=strategy)
    if args.json:
        print(json.dumps(_allocation_json(allocation)))
    else:
        Console().print(_allocation_table(allocation))
    return EXIT_OK if allocation.status is Status.OPTIMAL else EXIT_INFEASIBLE


def _row_json(row: RobotRow) -> dict[str, Any]:
    return {
        "robot": row.robot,
        "topic": row.topic,
        "tc_s": None if math.isinf(row.tc_s) else row.tc_s,
        "priority": row.priority,
        "rate_hz": row.rate_hz,
        "share": row.share,
        "static_rate_hz": row.static_rate_hz,
        "paper": {
            "tc_s": row.paper.tc_s,
            "priority": row.paper.priority,
            "rate_hz": row.paper.rate_hz,
            "share": row.paper.share_percent / 100,
        },
        "match": row.match,
    }


def _mark(ok: bool) -> str:
    return "[green]✓[/]" if ok else "[bold red]✗[/]"


def _cmd_reproduce(args: argparse.Namespace) -> int:
    steps = reproduce_table2()
    all_match = all(row.match for step in steps for row in step)
    if args.json:
        print(
            json.dumps(
                {
                    "steps": [
                        {"step": step[0].step, "robots": [_row_json(r) for r in step]}
                        for step in steps
                    ],
                    "all_match": all_match,
                }
            )
        )
        return EXIT_OK if all_match else EXIT_MISMATCH
    table = Table(title="Table 2 of the paper, reproduced (strategy paper, 11 Mbit, 1-16 Hz)")
    for name in ("step", "robot", "tc s", "p", "f Hz", "paper", "BW %", "paper", "static"):
        table.add_column(name, justify="right", no_wrap=True)
    for step in steps:
        for row in step:
            tc = "∞" if math.isinf(row.tc_s) else f"{row.tc_s:g}"
            table.add_row(
                str(row.step) if row.robot == "R1" else "",
                row.robot,
                f"{tc} {_mark(row.tc_match)}",
                f"{row.priority:.2f} {_mark(row.priority_match)}",
                f"{row.rate_hz:.2f} {_mark(row.rate_match)}",
                f"{row.paper.rate_hz:g}",
                f"{row.share * 100:.2f} {_mark(row.share_match)}",
                f"{row.paper.share_percent:.2f}",
                f"{row.static_rate_hz:.2f}",
                end_section=row.robot == step[-1].robot,
            )
    matched = sum(all(r.match for r in step) for step in steps)
    verdict = "[green]all match[/]" if all_match else "[bold red]MISMATCH[/]"
    table.caption = (
        f"{matched}/{len(steps)} steps match the paper to its printed precision: {verdict}. "
        "static: the paper's fixed baseline, Hz."
    )
    Console().print(table)
    return EXIT_OK if all_match else EXIT_MISMATCH


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="dbml", description="Dynamic bandwidth management for multi-robot systems."
    )
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    allocate_cmd = commands.add_parser("allocate", help="allocate rates for a config file")
    allocate_cmd.add_argument("config", help="YAML config (dbm, channels, links)")
    allocate_cmd.add_argument(
        "--strategy", choices=[s.value for s in Strategy], help="override dbm.strategy"
    )
    allocate_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")
    allocate_cmd.set_defaults(handler=_cmd_allocate)

    reproduce_cmd = commands.add_parser("reproduce", help="reproduce a table of the paper")
    reproduce_cmd.add_argument("table", choices=["table2"], help="which table")
    reproduce_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")
    reproduce_cmd.set_defaults(handler=_cmd_reproduce)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        code: int = args.handler(args)
    except DbmlError as err:
        sys.stderr.write(f"dbml: error: {err}\n")
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    return code


if __name__ == "__main__":
    sys.exit(main())
