"""The ``dbml`` command line.

Exit codes: 0 success (``optimal``); 2 bad input or an unreadable file, with one line on stderr;
3 an infeasible budget (the result is still printed); 1 a reproduction that does not match.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from rich.console import Console
from rich.table import Table

from dbml import nodes
from dbml.configfile import load_config
from dbml.core.allocation import Allocation, Status, Strategy, allocate
from dbml.core.config import DbmSettings
from dbml.core.errors import DbmlError
from dbml.core.spec import LinkSpec
from dbml.nodes import stop_on_signals
from dbml.sim.demo import print_result, run_teleop_demo
from dbml.sim.reproduce import RobotRow, reproduce_table2
from dbml.transports.base import Transport
from dbml.transports.registry import open_transport

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


def _transport_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("network (default: processes of this machine, no flags)")
    group.add_argument(
        "--transport",
        choices=["zenoh", "ros1"],
        default="zenoh",
        help="zenoh (default) or ros1: the ROS master at $ROS_MASTER_URI, host from $ROS_IP",
    )
    group.add_argument(
        "--host",
        help="this process's host identity (default: $DBML_HOST or hostname; ros1: ROS_HOSTNAME)",
    )
    group.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to, e.g. tcp/192.168.1.2:7447 (repeatable)",
    )
    group.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    group.add_argument("--zenoh-config", metavar="FILE", help="a zenoh JSON5 config file")


def _open(args: argparse.Namespace) -> Transport:
    return open_transport(
        args.transport,
        host=args.host,
        connect=args.connect,
        listen=args.listen,
        config_file=args.zenoh_config,
    )


def _setup_logging(verbose: bool = True) -> None:
    """Log to stderr. Called after the transport opens: rospy's node start replaces the root
    handlers with ROS's own (a file under ~/.ros/log), which would hide dbml's warnings."""
    logging.basicConfig(
        force=True,
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
    )
    logging.getLogger("rospy").setLevel(logging.WARNING)  # its INFO is its own start-up chatter


def _run_node(args: argparse.Namespace, body: Callable[[Transport, threading.Event], int]) -> int:
    with stop_on_signals() as stop:
        transport = _open(args)
        _setup_logging()
        try:
            return body(transport, stop)
        finally:
            transport.close()


def _cmd_optimizer(args: argparse.Namespace) -> int:
    if args.estimate and args.transport == "ros1":
        raise DbmlError(
            "--estimate needs per-message send times and sequence numbers, which ROS 1 "
            "messages do not carry: use --transport zenoh"
        )
    settings: DbmSettings | None = None
    links: tuple[LinkSpec, ...] = ()
    if args.config:
        config = load_config(args.config, require_channels=False)
        settings, links = config.dbm, config.links
    return _run_node(
        args,
        lambda t, stop: nodes.run_optimizer(
            t,
            settings=settings,
            links=links,
            stop=stop,
            duration_s=args.duration,
            estimate=args.estimate,
            write_defaults=args.transport == "ros1",
        ),
    )


def _cmd_publish(args: argparse.Namespace) -> int:
    return _run_node(
        args,
        lambda t, stop: nodes.run_publisher(
            t,
            args.topic,
            size_bytes=args.size_bytes,
            min_rate_hz=args.min_hz,
            max_rate_hz=args.max_hz,
            priority=args.priority,
            stop=stop,
            duration_s=args.duration,
        ),
    )


def _cmd_subscribe(args: argparse.Namespace) -> int:
    return _run_node(
        args,
        lambda t, stop: nodes.run_subscriber(
            t, args.topic, as_json=args.json, stop=stop, duration_s=args.duration
        ),
    )


def _cmd_priority(args: argparse.Namespace) -> int:
    return _run_node(args, lambda t, _stop: nodes.set_priority(t, args.topic, args.value))


def _cmd_monitor(args: argparse.Namespace) -> int:
    return _run_node(
        args,
        lambda t, stop: nodes.run_monitor(
            t, as_json=args.json, stop=stop, duration_s=args.duration
        ),
    )


def _show(
    args: argparse.Namespace, console: Console, document: dict[str, Any], table: Callable[[], None]
) -> None:
    """A scenario's result: one JSON object with ``--json``, else the table (and the plot)."""
    if args.json:
        print(json.dumps(document))
        return
    table()
    if args.plot:
        console.print(f"plot written to {args.plot}")


def _cmd_demo(args: argparse.Namespace) -> int:
    console = Console(stderr=args.json)
    result = run_teleop_demo(
        step_seconds=args.step_seconds,
        transport=args.transport,
        console=Console(stderr=True),
        show_live=not args.json,
        plot=Path(args.plot) if args.plot else None,
    )
    _show(args, console, result.as_json(), lambda: print_result(result, console))
    if result.interrupted:
        return EXIT_OK
    return EXIT_OK if result.ok else EXIT_MISMATCH


def _cmd_testbed(args: argparse.Namespace) -> int:
    from dbml.testbed.teleop import print_result as print_testbed
    from dbml.testbed.teleop import run_teleop_testbed

    console = Console(stderr=args.json)
    result = run_teleop_testbed(
        policy=args.policy,
        link_mbit=args.link_mbit,
        step_seconds=args.step_seconds,
        link_schedule=args.link_schedule,
        estimate=args.estimate,
        uplinks=args.uplink,
        strategy=args.strategy,
        utilization=args.utilization,
        console=Console(stderr=True),
        show_live=not args.json,
        plot=Path(args.plot) if args.plot else None,
    )
    _show(args, console, result.as_json(), lambda: print_testbed(result, console))
    return 130 if result.interrupted else EXIT_OK


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return value


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

    optimizer_cmd = commands.add_parser("optimizer", help="run the optimizer node")
    optimizer_cmd.add_argument("--config", help="YAML config; its dbm: section is enough")
    optimizer_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    optimizer_cmd.add_argument(
        "--estimate",
        action="store_true",
        help="estimate the usable bandwidth from what subscribers receive (at most the budget)",
    )
    _transport_options(optimizer_cmd)
    optimizer_cmd.set_defaults(handler=_cmd_optimizer)

    publish_cmd = commands.add_parser("publish", help="a managed publisher of synthetic payloads")
    publish_cmd.add_argument("topic", help="e.g. /r1/camera")
    publish_cmd.add_argument("--size-bytes", type=int, required=True, help="payload size")
    publish_cmd.add_argument("--min-hz", type=_positive, required=True, help="minimum rate")
    publish_cmd.add_argument("--max-hz", type=_positive, required=True, help="maximum rate")
    publish_cmd.add_argument("--priority", type=float, help="raw priority in [0, 1]")
    publish_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(publish_cmd)
    publish_cmd.set_defaults(handler=_cmd_publish)

    subscribe_cmd = commands.add_parser("subscribe", help="a managed subscriber that reports")
    subscribe_cmd.add_argument("topic", help="e.g. /r1/camera")
    subscribe_cmd.add_argument("--json", action="store_true", help="one JSON object per line")
    subscribe_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(subscribe_cmd)
    subscribe_cmd.set_defaults(handler=_cmd_subscribe)

    priority_cmd = commands.add_parser("priority", help="set a channel's raw priority")
    priority_cmd.add_argument("topic", help="e.g. /r1/camera")
    priority_cmd.add_argument("value", type=float, help="raw priority in [0, 1]")
    _transport_options(priority_cmd)
    priority_cmd.set_defaults(handler=_cmd_priority)

    monitor_cmd = commands.add_parser("monitor", help="a live view of every channel")
    monitor_cmd.add_argument("--json", action="store_true", help="one JSON object per channel")
    monitor_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(monitor_cmd)
    monitor_cmd.set_defaults(handler=_cmd_monitor)

    demo_cmd = commands.add_parser("demo", help="live scenarios")
    demo_cmd.add_argument("scenario", choices=["teleop"], help="the paper's section 4")
    demo_cmd.add_argument("--step-seconds", type=_positive, default=3.0, help="default 3")
    demo_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")
    demo_cmd.add_argument("--plot", metavar="FILE.png", help="write a PNG of rates and bandwidth")
    demo_cmd.add_argument(
        "--transport",
        choices=["zenoh", "ros1", "memory"],
        default="zenoh",
        help="zenoh (default), ros1 (a real ROS master, started if none answers) or memory",
    )
    demo_cmd.set_defaults(handler=_cmd_demo)

    testbed_cmd = commands.add_parser(
        "testbed", help="experiments over real tc-shaped links in network namespaces (root)"
    )
    testbed_cmd.add_argument("scenario", choices=["teleop"], help="the paper's section 4")
    testbed_cmd.add_argument(
        "--policy", choices=["dbml", "static", "unmanaged"], default="dbml", help="default dbml"
    )
    testbed_cmd.add_argument("--link-mbit", type=_positive, default=11.0, help="default 11")
    testbed_cmd.add_argument("--step-seconds", type=_positive, default=6.0, help="default 6")
    testbed_cmd.add_argument(
        "--link-schedule", metavar="SPEC", help='change the link rate: "0:11,20:5,40:11" (s:Mbit)'
    )
    testbed_cmd.add_argument(
        "--estimate", action="store_true", help="estimate the bandwidth instead of assuming it"
    )
    testbed_cmd.add_argument(
        "--uplink",
        metavar="ROBOT=MBIT",
        action="append",
        default=[],
        help="shape a robot's own uplink too (e.g. R1=4); implies --strategy lp",
    )
    testbed_cmd.add_argument("--strategy", choices=[s.value for s in Strategy])
    testbed_cmd.add_argument(
        "--utilization", type=_positive, help="share of the link dbml may allocate (0.92)"
    )
    testbed_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")
    testbed_cmd.add_argument("--plot", metavar="FILE.png", help="rates, latency and budget")
    testbed_cmd.set_defaults(handler=_cmd_testbed)
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
    except BrokenPipeError:  # e.g. `dbml monitor --json | head`: the reader is gone, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
    return code


if __name__ == "__main__":
    sys.exit(main())
