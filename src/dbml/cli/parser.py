"""The ``dbml`` argument parser: every command, flag and default in one place."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from dbml.core.allocation import Strategy
from dbml.core.errors import SpecError
from dbml.core.spec import check_number
from dbml.estimator.designs import DEFAULT_DESIGN, Design
from dbml.runtime.qos import parse_transport_priority
from dbml.secure import DEFAULT_BASE_PORT, DEFAULT_DAYS
from dbml.testbed.options import POLICIES, TOPOLOGIES
from dbml.testbed.options import TRANSPORTS as TESTBED_TRANSPORTS
from dbml.transports.base import DEFAULT_ROUTER_ENDPOINT, TransportPriority
from dbml.transports.registry import DEFAULT_TRANSPORT, TRANSPORTS

__all__ = ["DEFAULT_ROUTER_ENDPOINT", "EXIT_USAGE", "build_parser"]

EXIT_USAGE = 2
"""Bad input: one line on stderr naming the field and the value."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line, like every other dbml error."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(EXIT_USAGE)


def _design_option(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--estimator-design",
        choices=[d.value for d in Design],
        default=DEFAULT_DESIGN.value,
        help=f"how --estimate reads overuse (default {DEFAULT_DESIGN.value}; docs/estimator.md)",
    )


def _transport_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("network (default: processes of this machine, no flags)")
    group.add_argument(
        "--transport",
        choices=[name for name, entry in TRANSPORTS.items() if entry.spans_processes],
        default=DEFAULT_TRANSPORT,
        help="; ".join(
            f"{name}: {entry.summary}"
            for name, entry in TRANSPORTS.items()
            if entry.spans_processes
        ),
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
    group.add_argument(
        "--priority-links",
        action="store_true",
        help="zenoh/ros2 peers: one TCP link per range of priorities to each --connect endpoint, "
        "so urgent channels never wait behind queued frames (the listening side needs it too; "
        "a zenoh client opens one link whatever this asks)",
    )
    group.add_argument(
        "--domain-id",
        type=int,
        metavar="N",
        help="ros2, rclpy: the ROS 2 domain, 0-232 (default: $ROS_DOMAIN_ID, else 0)",
    )
    group.add_argument(
        "--ros-distro",
        metavar="NAME",
        help="ros2: the distro whose message types (and hashes) to use: jazzy (default), "
        "kilted, lyrical",
    )
    group.add_argument(
        "--msg-path",
        action="append",
        default=[],
        metavar="DIR",
        help="ros2: a directory of <package>/msg/<Name>.msg files for custom types (repeatable)",
    )


def _view_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("live view (pip install 'dbml[viz]')")
    group.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        help="serve the live view to Foxglove or Lichtblick over WebSocket (host default "
        "127.0.0.1): allocation, budget, rates, log, and the budget and priorities to set",
    )
    group.add_argument(
        "--record", metavar="FILE.mcap", help="record the live view's channels to an MCAP file"
    )


def _positive(text: str) -> float:
    """A finite number > 0 (argparse reports a text that is no number)."""
    try:
        return check_number(float(text), field="value", minimum=0, exclusive_minimum=True)
    except SpecError:
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0") from None


def _transport_priority(text: str) -> TransportPriority:
    """A transport class by name (argparse reports a bad one in one line, exit 2)."""
    try:
        return parse_transport_priority(text)
    except SpecError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def build_parser() -> argparse.ArgumentParser:
    """The ``dbml`` parser; each subcommand's name is ``args.command``."""
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

    reproduce_cmd = commands.add_parser("reproduce", help="reproduce a table of the paper")
    reproduce_cmd.add_argument("table", choices=["table2"], help="which table")
    reproduce_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")

    optimizer_cmd = commands.add_parser("optimizer", help="run the optimizer node")
    optimizer_cmd.add_argument("--config", help="YAML config; its dbm: section is enough")
    optimizer_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    optimizer_cmd.add_argument(
        "--estimate",
        action="store_true",
        help="estimate the usable bandwidth from what subscribers receive (at most the budget)",
    )
    optimizer_cmd.add_argument(
        "--lifecycle",
        action="store_true",
        help="a ROS 2 managed node (rclpy): start unconfigured, allocate only while active",
    )
    _design_option(optimizer_cmd)
    _transport_options(optimizer_cmd)
    _view_options(optimizer_cmd)

    publish_cmd = commands.add_parser("publish", help="a managed publisher of synthetic payloads")
    publish_cmd.add_argument("topic", help="e.g. /r1/camera")
    publish_cmd.add_argument("--size-bytes", type=int, required=True, help="payload size")
    publish_cmd.add_argument("--min-hz", type=_positive, required=True, help="minimum rate")
    publish_cmd.add_argument("--max-hz", type=_positive, required=True, help="maximum rate")
    publish_cmd.add_argument("--priority", type=float, help="raw priority in [0, 1]")
    publish_cmd.add_argument(
        "--transport-priority",
        type=_transport_priority,
        metavar="CLASS",
        help="the middleware class of its messages, instead of the one --priority maps to: "
        + "|".join(p.value for p in TransportPriority),
    )
    publish_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(publish_cmd)

    subscribe_cmd = commands.add_parser("subscribe", help="a managed subscriber that reports")
    subscribe_cmd.add_argument("topic", help="e.g. /r1/camera")
    subscribe_cmd.add_argument("--json", action="store_true", help="one JSON object per line")
    subscribe_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(subscribe_cmd)

    priority_cmd = commands.add_parser("priority", help="set a channel's raw priority")
    priority_cmd.add_argument("topic", help="e.g. /r1/camera")
    priority_cmd.add_argument("value", type=float, help="raw priority in [0, 1]")
    _transport_options(priority_cmd)

    budget_cmd = commands.add_parser("budget", help="set the link's bandwidth (the budget)")
    budget_cmd.add_argument("mbit", type=float, help="/dbm/max_bandwidth_in_mbit, e.g. 11")
    budget_cmd.add_argument(
        "--utilization", type=float, help="/dbm/max_bandwidth_utilization, in (0, 1]"
    )
    _transport_options(budget_cmd)

    monitor_cmd = commands.add_parser("monitor", help="a live view of every channel")
    monitor_cmd.add_argument("--json", action="store_true", help="one JSON object per channel")
    monitor_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(monitor_cmd)
    _view_options(monitor_cmd)

    bridge_cmd = commands.add_parser(
        "bridge", help="put an existing topic under management, its publisher untouched"
    )
    bridge_cmd.add_argument("topic", nargs="?", help="e.g. /r1/camera (or --config)")
    bridge_cmd.add_argument("--min-hz", type=_positive, help="minimum rate")
    bridge_cmd.add_argument("--max-hz", type=_positive, help="maximum rate")
    bridge_cmd.add_argument("--priority", type=float, help="raw priority in [0, 1]")
    bridge_cmd.add_argument(
        "--type", metavar="PKG/msg/NAME", help="message type (default: as the graph shows it)"
    )
    bridge_cmd.add_argument(
        "--ladder",
        action="store_true",
        help="a camera (sensor_msgs/msg/Image): send its frames as CompressedImage on "
        "[topic]/optimized/compressed, rate and JPEG quality chosen together (the quality extra)",
    )
    bridge_cmd.add_argument("--config", metavar="FILE", help="YAML whose channels: are bridged")
    bridge_cmd.add_argument(
        "--wait",
        type=_positive,
        default=10.0,
        metavar="S",
        help="how long each topic has to deliver its first message (default 10)",
    )
    bridge_cmd.add_argument("--duration", type=_positive, help="stop after S seconds")
    _transport_options(bridge_cmd)

    router_cmd = commands.add_parser(
        "router", help="a zenoh router, for machines without ROS 2's rmw_zenohd"
    )
    router_cmd.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"where it listens (repeatable; default {DEFAULT_ROUTER_ENDPOINT})",
    )

    from dbml.transports.registry import TRANSPORTS

    demo_cmd = commands.add_parser("demo", help="live scenarios")
    demo_cmd.add_argument("scenario", choices=["teleop"], help="the paper's section 4")
    demo_cmd.add_argument("--step-seconds", type=_positive, default=3.0, help="default 3")
    demo_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")
    demo_cmd.add_argument("--plot", metavar="FILE.png", help="write a PNG of rates and bandwidth")
    demo_cmd.add_argument(
        "--frames",
        choices=["synthetic", "photos"],
        default="synthetic",
        help="synthetic (default): frames of the paper's sizes, judged against Table 2; photos: "
        "cameras moving over real photographs, sent as JPEG with rate and quality chosen "
        "together, then again at one quality (rate only), compared (the quality extra)",
    )
    demo_cmd.add_argument(
        "--transport",
        choices=list(TRANSPORTS),
        default=DEFAULT_TRANSPORT,
        help=f"default {DEFAULT_TRANSPORT}; ros1 uses the master at $ROS_MASTER_URI or starts one; "
        + "; ".join(f"{name}: {entry.summary}" for name, entry in TRANSPORTS.items()),
    )
    _view_options(demo_cmd)

    testbed_cmd = commands.add_parser(
        "testbed", help="experiments over real tc-shaped links in network namespaces (root)"
    )
    testbed_cmd.add_argument("scenario", choices=["teleop"], help="the paper's section 4")
    testbed_cmd.add_argument("--policy", choices=POLICIES, default=POLICIES[0], help="default dbml")
    testbed_cmd.add_argument("--link-mbit", type=_positive, default=11.0, help="default 11")
    testbed_cmd.add_argument("--step-seconds", type=_positive, default=6.0, help="default 6")
    testbed_cmd.add_argument(
        "--link-schedule",
        metavar="SPEC",
        help='change the link rate: "0:11,20:5,40:11" (s:Mbit; 0: the link is down)',
    )
    testbed_cmd.add_argument(
        "--link-trace",
        metavar="FILE",
        help="the link follows a recorded trace: OpenNetLab gym's JSON "
        '({"uplink": {"trace_pattern": [{"capacity": kbps, "duration": ms}, ...]}}) or '
        "SECONDS:MBIT lines; its queue keeps the bytes its median rate fills in 200 ms",
    )
    testbed_cmd.add_argument(
        "--estimate", action="store_true", help="estimate the bandwidth instead of assuming it"
    )
    _design_option(testbed_cmd)
    testbed_cmd.add_argument(
        "--uplink",
        metavar="ROBOT=MBIT",
        action="append",
        default=[],
        help="shape a robot's own uplink too (e.g. R1=4); implies --strategy lp",
    )
    testbed_cmd.add_argument(
        "--uplink-schedule",
        metavar="ROBOT=SPEC",
        action="append",
        default=[],
        help='a robot\'s own radio over time, as --link-schedule: "R1=0:11,20:0,30:11" '
        "(R1 out of range from 20 s to 30 s while the others go on)",
    )
    testbed_cmd.add_argument("--strategy", choices=[s.value for s in Strategy])
    testbed_cmd.add_argument(
        "--utilization", type=_positive, help="share of the link dbml may allocate (0.92)"
    )
    testbed_cmd.add_argument(
        "--urgent-stream",
        action="store_true",
        help="R1 also sends a 1,000-byte 20 Hz urgent stream twice, with and without the "
        "transport-priority mapping, and the run reports each one's latency",
    )
    testbed_cmd.add_argument(
        "--robots",
        type=int,
        default=2,
        metavar="N",
        help="robots r1..rN, each its own namespace and uplink (default 2: Table 2; more: "
        "cameras of 84,000 / 21,000 bytes alternating, Table 2's events rotating among them)",
    )
    testbed_cmd.add_argument(
        "--topology",
        choices=TOPOLOGIES,
        default=TOPOLOGIES[0],
        help="peer (default): zenoh peers on explicit endpoints; router: a zenoh router per "
        "host, every role its client, the robots' routers meshed with the operator's",
    )
    testbed_cmd.add_argument(
        "--transport",
        choices=TESTBED_TRANSPORTS,
        default=TESTBED_TRANSPORTS[0],
        help="zenoh (default): dbml's roles over zenoh; rclpy: real ROS 2 (Fast DDS), plain "
        "rclpy cameras and operator, a dbml bridge per camera, dbml's optimizer",
    )
    testbed_cmd.add_argument(
        "--frames",
        choices=["synthetic", "photos"],
        default="synthetic",
        help="synthetic (default): frames of the paper's sizes; photos: cameras over real "
        "photographs as JPEG, rate and quality chosen together (the quality extra)",
    )
    testbed_cmd.add_argument(
        "--rate-only",
        action="store_true",
        help="with --frames photos: no ladder, every frame at the one JPEG quality whose frames "
        "are the paper's 84,000 B (the baseline the ladder is compared with)",
    )
    testbed_cmd.add_argument("--json", action="store_true", help="one JSON object on stdout")
    testbed_cmd.add_argument("--plot", metavar="FILE.png", help="rates, latency and budget")
    _view_options(testbed_cmd)

    foxglove_cmd = commands.add_parser("foxglove", help="the live view's Foxglove layout")
    foxglove_commands = foxglove_cmd.add_subparsers(
        dest="foxglove_command", required=True, parser_class=_Parser
    )
    layout_cmd = foxglove_commands.add_parser(
        "layout", help="print the Foxglove layout (JSON) of dbml's live view"
    )
    layout_cmd.add_argument(
        "--camera",
        action="append",
        default=[],
        metavar="TOPIC",
        help="a channel whose frames get an image panel (repeatable; default the demo's "
        "/r1/camera and /r2/camera)",
    )
    layout_cmd.add_argument(
        "--channel",
        action="append",
        default=[],
        metavar="TOPIC",
        help="a channel whose rates are plotted (repeatable; default the cameras)",
    )
    layout_cmd.add_argument(
        "--compressed",
        action="store_true",
        help="the image panels show [topic]/optimized/compressed: cameras with a ladder "
        "(dbml demo teleop --frames photos, dbml bridge --ladder)",
    )

    secure_cmd = commands.add_parser(
        "secure", help="mutual TLS and access control per role for a fleet across machines"
    )
    secure_commands = secure_cmd.add_subparsers(
        dest="secure_command", required=True, parser_class=_Parser
    )
    init_cmd = secure_commands.add_parser(
        "init", help="write a fleet CA, and a key, certificate and zenoh config per node"
    )
    init_cmd.add_argument("directory", metavar="DIR", help="where the files go")
    init_cmd.add_argument("--optimizer", required=True, metavar="NAME", help="the optimizer")
    init_cmd.add_argument("--robots", required=True, metavar="R1,R2", help="the robots' names")
    init_cmd.add_argument(
        "--operators", default="", metavar="OP1,OP2", help="who may set budget and priorities"
    )
    init_cmd.add_argument(
        "--endpoint",
        action="append",
        default=[],
        metavar="NAME=ENDPOINT",
        help="where a node listens and the others connect, e.g. r1=tls/10.0.0.5:7447 "
        "(repeatable; default tls/127.0.0.1:<base port + index>)",
    )
    init_cmd.add_argument(
        "--san",
        action="append",
        default=[],
        metavar="[NAME=]ADDRESS",
        help="one more IP or DNS name in every certificate, or in NAME's (repeatable)",
    )
    init_cmd.add_argument(
        "--base-port", type=int, default=DEFAULT_BASE_PORT, help=f"default {DEFAULT_BASE_PORT}"
    )
    init_cmd.add_argument(
        "--days",
        type=int,
        default=DEFAULT_DAYS,
        help=f"certificate validity, default {DEFAULT_DAYS}",
    )
    init_cmd.add_argument(
        "--install-dir",
        metavar="PATH",
        help="where the files will be on the nodes, as the configs name them (default: DIR)",
    )
    init_cmd.add_argument("--force", action="store_true", help="replace existing files")
    return parser
