"""The ``dbml`` command line: each command's handler, JSON at the edge, one error line.

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
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live

from dbml.cli import commands, render
from dbml.cli.parser import DEFAULT_ROUTER_ENDPOINT, EXIT_USAGE, build_parser
from dbml.core.allocation import Allocation, Status, allocate
from dbml.core.config import BridgeChannel, DbmSettings, load_bridge_channels, load_config
from dbml.core.errors import DbmlError
from dbml.core.extras import require
from dbml.core.spec import LinkSpec
from dbml.estimator.designs import Design
from dbml.experiment.analysis import SeriesPoint
from dbml.harness.child import stop_on_signals
from dbml.harness.processes import free_port
from dbml.protocol import names
from dbml.protocol.schema import Writer
from dbml.runtime.lifecycle import run_managed_optimizer
from dbml.runtime.monitor import MonitorView
from dbml.runtime.optimizer import Round
from dbml.runtime.serve import OptimizerRun, serve_optimizer
from dbml.scenarios.reproduce import RobotRow, reproduce_table2
from dbml.transports.base import Transport
from dbml.transports.rclpy.rosargs import channel_bounds, namespace_of, overrides, split_ros_args
from dbml.transports.registry import TRANSPORTS, open_transport
from dbml.view.target import ViewTarget

__all__ = ["EXIT_INFEASIBLE", "EXIT_MISMATCH", "EXIT_OK", "EXIT_USAGE", "main"]

EXIT_OK = 0
EXIT_MISMATCH = 1
EXIT_INFEASIBLE = 3
EXIT_INTERRUPTED = 130
"""What a shell reports for a program ended by Ctrl-C."""
log = logging.getLogger("dbml")

_ROUTER_POLL_S = 0.5
"""How often ``dbml router`` looks whether a signal asked it to stop."""


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


def _cmd_allocate(args: argparse.Namespace) -> int:
    config = load_config(args.config, strategy=args.strategy)
    allocation = allocate(config.problem(), strategy=config.dbm.strategy)
    if args.json:
        print(json.dumps(_allocation_json(allocation)))
    else:
        Console().print(render.allocation_table(allocation))
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


def _cmd_reproduce(args: argparse.Namespace) -> int:
    steps = reproduce_table2()
    all_match = all(row.match for step in steps for row in step)
    if args.json:
        document = {
            "steps": [
                {"step": step[0].step, "robots": [_row_json(r) for r in step]} for step in steps
            ],
            "all_match": all_match,
        }
        print(json.dumps(document))
    else:
        Console().print(render.reproduce_table(steps))
    return EXIT_OK if all_match else EXIT_MISMATCH


def _open(args: argparse.Namespace, *, follow_all_params: bool = True) -> Transport:
    return open_transport(
        args.transport,
        host=args.host,
        connect=args.connect,
        listen=args.listen,
        config_file=args.zenoh_config,
        follow_all_params=follow_all_params,
        domain_id=args.domain_id,
        ros_distro=args.ros_distro,
        msg_paths=args.msg_path,
        priority_links=args.priority_links,
        ros_args=args.ros_args,
    )


def _setup_logging(verbose: bool = True) -> None:
    """Log to stderr.

    Called after the transport opens: rospy's node start replaces the root handlers with ROS's
    own (a file under ~/.ros/log), which would hide dbml's warnings.
    """
    logging.basicConfig(
        force=True,
        level=logging.INFO if verbose else logging.WARNING,
        format="%(asctime)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
    )
    logging.getLogger("rospy").setLevel(logging.WARNING)  # its INFO is its own start-up chatter


def _view_target(args: argparse.Namespace, *, pick_port: bool = False) -> ViewTarget | None:
    """``--foxglove`` and ``--record``, checked (and the ``viz`` extra there) before a run.

    ``pick_port``: port 0 is chosen here, for a view served by a child process (``_announce``
    says it once the run's options are known to be good).
    """
    target = ViewTarget.from_flags(args.foxglove, args.record)
    if target is None:
        return None
    require("foxglove", extra="viz", what="--foxglove and --record", package="foxglove-sdk")
    require("rosbags", extra="viz", what="--foxglove and --record")
    endpoint = target.endpoint
    if pick_port and endpoint is not None and endpoint.port == 0:
        target = replace(target, endpoint=replace(endpoint, port=free_port()))
    return target


def _announce(view: ViewTarget | None) -> None:
    """Where a child process serves the view, on stderr (stdout may be ``--json``'s)."""
    if view is not None and view.endpoint is not None:
        sys.stderr.write(f"live view: ws://{view.endpoint} (Foxglove: Open connection)\n")


def _run_node(
    args: argparse.Namespace,
    body: Callable[[Transport, threading.Event], int],
    *,
    follow_all_params: bool = True,
    view: ViewTarget | None = None,
    writers: frozenset[Writer] = frozenset({Writer.OPERATOR}),
) -> int:
    with stop_on_signals() as stop:
        transport = _open(args, follow_all_params=follow_all_params)
        _setup_logging()
        try:
            if view is None:
                return body(transport, stop)
            from dbml.view.live import open_view

            live = open_view(transport, view, writers=writers)
            try:
                if view.endpoint is not None:
                    log.info("live view: ws://%s (Foxglove: Open connection)", live.endpoint)
                return body(transport, stop)
            finally:
                live.close()
        finally:
            transport.close()


def _cmd_optimizer(args: argparse.Namespace) -> int:
    entry = TRANSPORTS[args.transport]
    if args.estimate and not entry.send_times:
        raise DbmlError(
            "--estimate needs per-message send times and sequence numbers, which "
            f"--transport {args.transport} messages do not carry: use --transport zenoh or rclpy"
        )
    if args.lifecycle and args.transport != "rclpy":
        raise DbmlError(
            f"--lifecycle: a ROS 2 managed node, over --transport rclpy only (not {args.transport})"
        )
    view = _view_target(args)
    settings: DbmSettings | None = None
    links: tuple[LinkSpec, ...] = ()
    if args.config:
        config = load_config(args.config, require_channels=False)
        settings, links = config.dbm, config.links

    def body(t: Transport, stop: threading.Event) -> int:
        on_round = _diagnostics(t) if args.transport == "rclpy" else None  # one publisher

        def build() -> OptimizerRun:
            return OptimizerRun(
                t,
                settings=settings,
                links=links,
                estimate=args.estimate,
                design=Design(args.estimator_design),
                write_defaults=entry.params_complete_at_start,
                on_round=on_round,
            )

        if not args.lifecycle:
            return serve_optimizer(t, build=build, stop=stop, duration_s=args.duration)
        from dbml.transports.rclpy.lifecycle import LifecycleServer
        from dbml.transports.rclpy.transport import RclpyTransport

        if not isinstance(t, RclpyTransport):  # refused above: a lifecycle is ROS 2's
            raise DbmlError(f"--lifecycle: over --transport rclpy only (not {args.transport})")
        return run_managed_optimizer(
            t,
            build=build,
            serve=lambda lifecycle: LifecycleServer(t, lifecycle),
            stop=stop,
            duration_s=args.duration,
        )

    return _run_node(
        args,
        body,
        view=view,
        writers=frozenset({Writer.OPTIMIZER, Writer.ESTIMATOR}),  # what the optimizer's node runs
    )


def _diagnostics(transport: Transport) -> Callable[[Round], None]:
    """Each round's statuses on ``/diagnostics`` (ROS 2's health topic), from the optimizer."""
    from dbml.runtime.diagnostics import statuses
    from dbml.transports.rclpy.diagnostics import DiagnosticsPublisher
    from dbml.transports.rclpy.transport import RclpyTransport

    assert isinstance(transport, RclpyTransport)
    publisher = DiagnosticsPublisher(transport)

    def publish(result: Round) -> None:
        estimate = transport.params.get(names.ESTIMATE)
        publisher.publish(
            statuses(
                result.report(),
                estimate_mbit=estimate if isinstance(estimate, float) else None,
            )
        )

    return publish


def _cmd_publish(args: argparse.Namespace) -> int:
    return _run_node(
        args,
        lambda t, stop: commands.run_publisher(
            t,
            args.topic,
            transport_name=args.transport,
            size_bytes=args.size_bytes,
            min_rate_hz=args.min_hz,
            max_rate_hz=args.max_hz,
            priority=args.priority,
            stop=stop,
            duration_s=args.duration,
            transport_priority=args.transport_priority,
        ),
        follow_all_params=False,  # a publisher needs the allocation, not the fleet's reports
    )


def _cmd_subscribe(args: argparse.Namespace) -> int:
    return _run_node(
        args,
        lambda t, stop: commands.run_subscriber(
            t, args.topic, as_json=args.json, stop=stop, duration_s=args.duration
        ),
    )


def _bridge_channels(args: argparse.Namespace) -> tuple[BridgeChannel, ...]:
    """The channels to bridge: TOPIC with its flags, or ``--config`` (exactly one of them)."""
    flags = {"--min-hz": args.min_hz, "--max-hz": args.max_hz}
    extras = {"--priority": args.priority, "--type": args.type}
    if args.config is not None:
        given = [
            f"{name}={value!r}" for name, value in (flags | extras).items() if value is not None
        ]
        if args.topic is not None or given:
            what = f"topic={args.topic!r}" if args.topic is not None else given[0]
            raise DbmlError(f"--config={args.config!r} and {what}: give one or the other")
        return load_bridge_channels(args.config)
    if args.topic is None and args.ros_args:
        return _ros_bridge_channels(args)
    if args.topic is None:
        raise DbmlError(
            "topic=None: give TOPIC --min-hz A --max-hz B, --config FILE, or (rclpy) "
            "--ros-args --params-file FILE"
        )
    for name, value in flags.items():
        if value is None:
            raise DbmlError(f"{name}=None: required with topic={args.topic!r}")
    return (
        BridgeChannel(args.topic, args.min_hz, args.max_hz, args.priority, args.type, args.ladder),
    )


def _ros_bridge_channels(args: argparse.Namespace) -> tuple[BridgeChannel, ...]:
    """The channels a params file declares under the bridge's namespace (``-r __ns:=/r1``)."""
    namespace = namespace_of(args.ros_args)
    bounds = channel_bounds(overrides(args.ros_args), namespace=namespace)
    if not bounds:
        raise DbmlError(
            f"--ros-args ({' '.join(args.ros_args)}): no channel under namespace={namespace!r} "
            "with frequency.min and frequency.max in a params file ([topic]/dbm)"
        )
    return tuple(
        BridgeChannel(topic, low, high, priority, ladder=args.ladder)
        for topic, (low, high, priority) in sorted(bounds.items())
    )


def _cmd_bridge(args: argparse.Namespace) -> int:
    channels = _bridge_channels(args)  # bad input exits before any network is opened
    return _run_node(
        args,
        lambda t, stop: commands.run_bridge(
            t,
            channels,
            stop=stop,
            duration_s=args.duration,
            wait_s=args.wait,
            typed_topics=TRANSPORTS[args.transport].typed_topics,
        ),
        follow_all_params=False,  # like a publisher: it needs its allocations only
    )


def _cmd_router(args: argparse.Namespace) -> int:
    from dbml.transports.zenoh.transport import open_router

    endpoints = args.listen or [DEFAULT_ROUTER_ENDPOINT]
    with stop_on_signals() as stop:
        session = open_router(endpoints)
        try:
            print(f"zenoh router listening on {', '.join(endpoints)}", flush=True)
            while not stop.wait(_ROUTER_POLL_S):
                pass
        finally:
            session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
    return EXIT_OK


def _cmd_priority(args: argparse.Namespace) -> int:
    return _run_node(args, lambda t, _stop: commands.set_priority(t, args.topic, args.value))


def _cmd_budget(args: argparse.Namespace) -> int:
    return _run_node(
        args, lambda t, _stop: commands.set_budget(t, args.mbit, utilization=args.utilization)
    )


def _cmd_monitor(args: argparse.Namespace) -> int:
    view = _view_target(args)
    if args.json:

        def show(view: MonitorView) -> None:
            for row in view.rows:
                sys.stdout.write(json.dumps(row.as_json()) + "\n")
            sys.stdout.flush()

        return _run_node(
            args,
            lambda t, stop: commands.run_monitor(t, show=show, stop=stop, duration_s=args.duration),
            view=view,
        )
    with Live(console=Console(), auto_refresh=False) as live:
        return _run_node(
            args,
            lambda t, stop: commands.run_monitor(
                t,
                show=lambda shown: live.update(render.monitor_table(shown), refresh=True),
                stop=stop,
                duration_s=args.duration,
            ),
            view=view,
        )


def _show(
    args: argparse.Namespace,
    console: Console,
    document: dict[str, Any],
    table: Callable[[], None],
    plot: Callable[[Path], None] | None = None,
) -> None:
    """A scenario's result: one JSON object with ``--json``, else the table; and the plot."""
    if args.plot and plot is not None:
        plot(Path(args.plot))
    if args.json:
        print(json.dumps(document))
        return
    table()
    if args.plot:
        console.print(f"plot written to {args.plot}")


@dataclass(frozen=True, slots=True)
class ExperimentPlot:
    """What ``--plot`` draws of a demo or testbed run."""

    series: Sequence[SeriesPoint]
    step_s: float
    title: str
    budget_label: str = "budget"
    capacity: Sequence[tuple[float, float]] = ()
    """A recorded trace's capacity, ``(seconds, Mbit/s)`` at each change, drawn as it is."""


def _show_run(
    args: argparse.Namespace,
    console: Console,
    document: dict[str, Any],
    table: Callable[[], None],
    plot: ExperimentPlot,
) -> None:
    """A demo's or testbed's result, and with ``--plot`` its PNG."""
    from dbml.cli.plots import plot_series

    def draw(path: Path) -> None:
        plot_series(
            plot.series,
            path,
            step_s=plot.step_s,
            title=plot.title,
            budget_label=plot.budget_label,
            capacity=plot.capacity,
        )

    _show(args, console, document, table, draw)


def _require_plot(args: argparse.Namespace) -> None:
    """Before a run, not after it: ``--plot`` without matplotlib would lose the run."""
    if args.plot:
        require("matplotlib", extra="plot", what="--plot")


def _cmd_photo_demo(args: argparse.Namespace) -> int:
    """``dbml demo teleop --frames photos``: the ladder, then rate only, on the same frames."""
    from dbml.cli.documents import photo_demo_document
    from dbml.demo.photos import PhotoDemoResult, check_photo_options, run_photo

    transport = check_photo_options(
        transport=args.transport, step_seconds=args.step_seconds, plot=args.plot is not None
    )
    require("simplejpeg", extra="quality", what="--frames photos")
    target = _view_target(args, pick_port=True)
    _announce(target)
    console = Console(stderr=args.json)
    runs = []
    for ladder in (True, False):
        title = f"dbml demo teleop — real frames, {'the ladder' if ladder else 'rate only'}"
        with render.ExperimentView(
            Console(stderr=True), title=title, step_s=args.step_seconds, show=not args.json
        ) as view:
            runs.append(
                run_photo(
                    transport,
                    step_seconds=args.step_seconds,
                    ladder=ladder,
                    observe=view.update,
                    view=target if ladder else None,  # the ladder's run: one recording
                )
            )
        if runs[-1].interrupted:
            break
    rate_only = runs[1] if len(runs) > 1 else None
    result = PhotoDemoResult(transport, args.step_seconds, runs[0], rate_only)
    _show(
        args,
        console,
        photo_demo_document(result),
        lambda: console.print(render.photo_demo_table(result)),
    )
    if runs[-1].interrupted:
        return EXIT_OK
    return EXIT_OK if result.ok else EXIT_MISMATCH


def _cmd_demo(args: argparse.Namespace) -> int:
    if args.frames == "photos":
        return _cmd_photo_demo(args)
    _require_plot(args)
    from dbml.cli.documents import demo_document
    from dbml.demo.runner import DemoOptions, run_teleop_demo

    options = DemoOptions.from_flags(
        step_seconds=args.step_seconds,
        transport=args.transport,
        view=_view_target(args, pick_port=True),
    )
    _announce(options.view)
    console = Console(stderr=args.json)
    title = "dbml demo teleop — live"
    with render.ExperimentView(
        Console(stderr=True), title=title, step_s=options.step_seconds, show=not args.json
    ) as view:
        result = run_teleop_demo(options, observe=view.update)
    _show_run(
        args,
        console,
        demo_document(result),
        lambda: console.print(render.demo_table(result)),
        ExperimentPlot(
            result.series,
            options.step_seconds,
            f"dbml teleoperation demo over {options.transport.name}",
        ),
    )
    if result.interrupted:
        return EXIT_OK
    return EXIT_OK if result.ok else EXIT_MISMATCH


def _cmd_testbed(args: argparse.Namespace) -> int:
    _require_plot(args)
    from dbml.cli.documents import testbed_document
    from dbml.scenarios.fleet import fleet_cameras
    from dbml.testbed.runner import TestbedOptions, run_teleop_testbed

    options = TestbedOptions.from_flags(
        policy=args.policy,
        link_mbit=args.link_mbit,
        step_seconds=args.step_seconds,
        link_schedule=args.link_schedule,
        link_trace=args.link_trace,
        estimate=args.estimate,
        estimator_design=args.estimator_design,
        uplinks=args.uplink,
        uplink_schedules=args.uplink_schedule,
        strategy=args.strategy,
        utilization=args.utilization,
        urgent_stream=args.urgent_stream,
        robots=args.robots,
        topology=args.topology,
        transport=args.transport,
        view=_view_target(args, pick_port=True),
        frames=args.frames,
        rate_only=args.rate_only,
    )
    if options.frames.value == "photos":
        require("simplejpeg", extra="quality", what="--frames photos")
    _announce(options.view)
    console = Console(stderr=args.json)
    with render.ExperimentView(
        Console(stderr=True),
        title=f"dbml testbed teleop — {options.policy} over {options.transport.name}, live",
        step_s=options.step_seconds,
        robots=[camera.robot for camera in fleet_cameras(options.robots)],
        link_mbit=options.link_mbit,
        schedule=options.link_schedule,
        show=not args.json,
    ) as view:
        result = run_teleop_testbed(options, observe=view.update)
    _show_run(
        args,
        console,
        testbed_document(result),
        lambda: console.print(render.testbed_table(result)),
        ExperimentPlot(
            result.series,
            options.step_seconds,
            f"dbml testbed teleop: policy {options.policy} over {options.transport.name} "
            "on a tc-shaped link",
            budget_label="budget (estimate)" if options.estimate else "budget",
            capacity=options.link_schedule if options.link_trace is not None else (),
        ),
    )
    return EXIT_INTERRUPTED if result.interrupted else EXIT_OK


def _cmd_foxglove(args: argparse.Namespace) -> int:
    from dbml.protocol.names import check_channel
    from dbml.view.layout import DEFAULT_CAMERAS, studio_layout

    cameras = [check_channel(t) for t in args.camera] or list(DEFAULT_CAMERAS)
    channels = [check_channel(t) for t in args.channel] or cameras
    layout = studio_layout(cameras=cameras, channels=channels, compressed=args.compressed)
    print(json.dumps(layout, indent=2))
    return EXIT_OK


def _cmd_secure(args: argparse.Namespace) -> int:
    require("cryptography", extra="secure", what="dbml secure init")
    from dbml.secure import fleet_from_flags, init_fleet

    fleet = fleet_from_flags(
        optimizer=args.optimizer,
        robots=args.robots,
        operators=args.operators,
        endpoints=args.endpoint,
        sans=args.san,
        base_port=args.base_port,
    )
    written = init_fleet(
        args.directory,
        fleet,
        force=args.force,
        days=args.days,
        install_dir=args.install_dir,
    )
    for file in written:
        print(f"wrote {file.path}{' (0600)' if file.secret else ''}: {file.description}")
    config = Path(args.install_dir or Path(args.directory).resolve())
    print(
        f"run a node as: dbml ... --zenoh-config {config}/NAME.json5 --host NAME "
        "(the host identity must be the node's name)"
    )
    return EXIT_OK


_HANDLERS: dict[str, Callable[[argparse.Namespace], int]] = {
    "allocate": _cmd_allocate,
    "reproduce": _cmd_reproduce,
    "optimizer": _cmd_optimizer,
    "publish": _cmd_publish,
    "subscribe": _cmd_subscribe,
    "priority": _cmd_priority,
    "budget": _cmd_budget,
    "monitor": _cmd_monitor,
    "bridge": _cmd_bridge,
    "router": _cmd_router,
    "demo": _cmd_demo,
    "testbed": _cmd_testbed,
    "secure": _cmd_secure,
    "foxglove": _cmd_foxglove,
}


_ROS_COMMANDS = frozenset(
    {"optimizer", "publish", "subscribe", "priority", "budget", "monitor", "bridge"}
)
"""The commands that run one node, which ``--ros-args`` configures over ``--transport rclpy``."""


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``dbml`` with ``argv`` (default: the process's arguments); the exit code.

    ROS 2's own arguments (``--ros-args ... [--]``) are set apart first, as rcl does, and given
    to rclpy by the commands that run a node over ``--transport rclpy``.
    """
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(own)
    args.ros_args = ros_args
    try:
        if ros_args and (
            args.command not in _ROS_COMMANDS or getattr(args, "transport", None) != "rclpy"
        ):
            raise DbmlError(
                f"--ros-args ({' '.join(ros_args)}): only a node's command over --transport "
                f"rclpy takes them ({', '.join(sorted(_ROS_COMMANDS))})"
            )
        return _HANDLERS[args.command](args)
    except DbmlError as err:
        sys.stderr.write(f"dbml: error: {err}\n")
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # e.g. `dbml monitor --json | head`: the reader is gone, not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_OK
