"""``dbml testbed teleop``: the paper's teleoperation scenario over a real, shaped network.

Robots R1 and R2 (or a fleet's r1..rN) and the operator are network namespaces; their traffic
to the operator shares one ``tc``-shaped link (and, with ``--uplink``, a robot's own slower
uplink). The experiment's roles run inside, laid out for the transport (``layout``: zenoh's,
``zenoh_layout``; real ROS 2's, ``rclpy_layout``), the optimizer on the operator's side
(policies ``dbml`` and ``static``; none under ``unmanaged``). The link's rate changes on
schedule; the result (``result``) holds, per step and robot, allocated and delivered rates,
latency, losses and goodput, the recovery after each link change, and the targets that apply.

Every namespace and process is removed at the end, also on error, Ctrl-C or SIGTERM; so is what
a killed process left behind (Fast DDS's shared memory).
"""

from __future__ import annotations

import contextlib
import logging
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

from dbml.core.spec import mbit_to_bytes_per_s
from dbml.experiment.analysis import StepResult, link_at, outages, recoveries, stream_latency
from dbml.experiment.analysis.windows import settle_s
from dbml.experiment.plan import bridge_name
from dbml.experiment.report import PublishTiming
from dbml.experiment.runner import Observer, Recording, run_experiment, sigterm_as_interrupt
from dbml.experiment.spec import URGENT_STREAMS
from dbml.harness.sniffer import window_stats
from dbml.scenarios.fleet import fleet_allocation, fleet_cameras, fleet_steps, urgent_robot
from dbml.testbed.layout import LayoutFactory, Leftovers
from dbml.testbed.netns import OPERATOR, Network, TestbedError, privilege_problem
from dbml.testbed.options import Policy, TestbedOptions
from dbml.testbed.rclpy_layout import RclpyLayout
from dbml.testbed.result import BridgePublish, LinkTiming, TestbedResult
from dbml.testbed.zenoh_layout import ZenohLayout
from dbml.transports.base import EXPEDITED_TOS
from dbml.transports.registry import Discovery

__all__ = ["LAYOUTS", "TestbedOptions", "TestbedResult", "run_teleop_testbed"]

log = logging.getLogger("dbml.testbed")

LAYOUTS: Mapping[Discovery, LayoutFactory] = {
    Discovery.ZENOH: ZenohLayout,
    Discovery.DDS: RclpyLayout,
}
"""The testbed's layout for each way of meeting it offers (``options.OFFERS``)."""


def _change_link(
    network: Network,
    options: TestbedOptions,
    t0: float,
    stop: threading.Event,
    timing: list[tuple[float, float]],
) -> None:
    """Apply the shared link's schedule and each robot's own, in time order, until ``stop``.

    Appends each change's lateness and the time its ``tc`` call took (seconds) to ``timing``.
    A change at 0 s is the rate the link was built at, but for a trace that starts down.
    """
    changes = [(at, OPERATOR, mbit) for at, mbit in options.link_schedule]
    for robot, schedule in options.robot_schedules.items():
        changes += [(at, robot.lower(), mbit) for at, mbit in schedule]
    for at, host, mbit in sorted(changes):
        if at <= 0 and mbit > 0:
            continue
        if stop.wait(max(0.0, t0 + at - time.time())):
            return
        started = time.time()
        try:
            if mbit == 0:
                network.take_link_down(host=host)
            else:
                network.set_link_rate(mbit, host=host)
        except TestbedError:
            if not stop.is_set():  # else the network is being torn down
                raise
            return
        timing.append((started - (t0 + at), time.time() - started))


def _expected_hz(
    options: TestbedOptions, steps: Sequence[StepResult]
) -> tuple[tuple[float, ...], ...]:
    """A fleet under dbml on a known budget: ``allocate`` on each step's implied channels."""
    known = options.policy is Policy.DBML and not options.estimate and not options.uplinks_mbit
    if not (options.fleet and known and options.strategy and options.utilization):
        return ()
    cameras = fleet_cameras(options.robots)
    return tuple(
        fleet_allocation(
            event_step,
            cameras,
            link_mbit=step.link_mbit,
            utilization=options.utilization,
            strategy=options.strategy,
        )
        for event_step, step in zip(fleet_steps(options.robots), steps, strict=False)
    )


def _urgent_index(options: TestbedOptions, t_s: float) -> int:
    """The robot whose channel has the highest priority ``t_s`` into the run (first on a tie)."""
    steps = fleet_steps(options.robots)
    step = steps[min(len(steps) - 1, max(0, int(t_s // options.step_seconds)))]
    return urgent_robot(step) or 0


def _frame_ms(size_bytes: int, mbit: float) -> float:
    """One frame of ``size_bytes`` on a link of ``mbit``, in ms."""
    return size_bytes * 8 / (mbit * 1e6) * 1e3


def _bridges(
    options: TestbedOptions, publishes: Mapping[str, Sequence[PublishTiming]]
) -> tuple[BridgePublish, ...]:
    """What each bridge said of its publishes on ``[topic]/optimized`` (none: not known)."""
    first = _built_mbit(options)
    if options.link_trace is not None:  # its slowest 200 ms are a fade: its median instead
        slowest = options.link_trace.median_up_mbit or first
    else:
        slowest = min([first, *(mbit for _, mbit in options.link_schedule if mbit > 0)])
    cameras = fleet_cameras(options.robots)
    frame_ms = _frame_ms(max(c.size_bytes for c in cameras), slowest)
    found = []
    for camera in cameras:
        rows = [t for t in publishes.get(bridge_name(camera), ()) if t.topic.endswith("/optimized")]
        if not rows:
            continue
        maxima = [r.max_ms for r in rows if r.max_ms is not None]
        p99s = [r.p99_ms for r in rows if r.p99_ms is not None]
        found.append(
            BridgePublish(
                robot=camera.robot,
                published=sum(r.published for r in rows),
                dropped=sum(r.dropped for r in rows),
                max_ms=max(maxima, default=None),
                p99_ms=max(p99s, default=None),
                frame_ms=frame_ms,
            )
        )
    return tuple(found)


def _built_mbit(options: TestbedOptions) -> float:
    """The shared link's first rate: the schedule's at 0 s, a trace's first one above 0."""
    first = link_at(options.link_schedule, 0.0, options.link_mbit)
    if first == 0 and options.link_trace is not None:  # down at 0 s: up before, to meet
        return options.link_trace.first_up_mbit or options.link_mbit
    return first


def _network(options: TestbedOptions) -> Network:
    """The run's network (not built yet): a namespace per robot, every link at its first rate."""
    return Network(
        robots=tuple(camera.robot.lower() for camera in fleet_cameras(options.robots)),
        link_mbit=_built_mbit(options),
        uplinks_mbit={
            robot.lower(): mbit
            for robot, mbit in {
                **options.uplinks_mbit,
                **{
                    r: link_at(own, 0.0, options.link_mbit)
                    for r, own in options.robot_schedules.items()
                },
            }.items()
        },
        # The urgent stream's run: its own link is marked EF, and the shared link honours it.
        expedited_tos=EXPEDITED_TOS if options.urgent_stream else None,
        queue_bytes=options.link_queue_bytes,
    )


def run_teleop_testbed(
    options: TestbedOptions,
    *,
    observe: Observer | None = None,
    run_dir: Path | None = None,
) -> TestbedResult:
    """Build the network, run the roles inside, remove it all; ``observe`` sees every report.

    ``run_dir``: the run's folder, kept (each process's stderr under ``logs/``, over rclpy the
    ROS logs under ``ros/``); None: a temporary one, removed at the end.
    """
    problem = privilege_problem()
    if problem is not None:
        raise TestbedError(f"dbml testbed needs root to build network namespaces: {problem}")
    layout = LAYOUTS[options.transport.discovery]()
    layout.check()
    cameras = fleet_cameras(options.robots)
    network = _network(options)
    recording = Recording(None, (), (), interrupted=True)
    leftovers = Leftovers()
    timing: list[tuple[float, float]] = []
    with (
        sigterm_as_interrupt(),
        contextlib.suppress(KeyboardInterrupt),
        tempfile.TemporaryDirectory(prefix="dbml-testbed-") as scratch,
        contextlib.ExitStack() as run,
    ):
        folder = Path(scratch) if run_dir is None else run_dir
        folder.mkdir(parents=True, exist_ok=True)
        try:
            network.build()
            plan = layout.plan(network, options, run=run, folder=folder)

            def on_start(t0: float, stop: threading.Event) -> None:
                watch = threading.Thread(
                    target=layout.during, args=(network, stop), name="during", daemon=True
                )
                watch.start()
                _change_link(network, options, t0, stop, timing)
                watch.join()

            recording = run_experiment(
                plan,
                what="testbed",
                observe=observe,
                on_start=on_start,
                logs=None if run_dir is None else run_dir / "logs",
            )
        finally:
            try:
                network.close()
            finally:
                leftovers = layout.leftovers()
    if leftovers.removed:
        log.warning(
            "removed %d Fast DDS shared-memory files of killed processes", len(leftovers.removed)
        )
    result = TestbedResult(
        options,
        network.run_id,
        interrupted=recording.interrupted,
        bridges=_bridges(options, recording.publishes),
        run_dir=run_dir,
        shm_files=leftovers.seen,
        shm_removed=leftovers.removed,
        link_timing=LinkTiming.of(timing),
    )
    if recording.t0 is None:
        return result
    traced = options.link_trace is not None  # every 200 ms a change: none judged alone
    analysis = recording.analyse(
        step_s=options.step_seconds,
        link_mbit=options.link_mbit,
        schedule=options.link_schedule,
        robots=[camera.robot for camera in cameras],
        link_events=not traced,
    )
    if options.steady and options.utilization is not None:
        start = recording.t0 + settle_s(options.step_seconds)
        arrived = [(a.arrival_s, a.size_bytes) for a in recording.arrivals if a.arrival_s >= start]
        limit = mbit_to_bytes_per_s(options.link_mbit * options.utilization) + max(
            (size for _, size in arrived), default=0
        )
        result = replace(result, wire=window_stats(arrived, limit_bytes=limit), limit_bytes=limit)
    return replace(
        result,
        steps=analysis.steps,
        series=analysis.series,
        changes=analysis.changes,
        phases=analysis.phases,
        outages=()
        if traced
        else outages(
            recording.arrivals,
            recording.ticks,
            robots=[camera.robot for camera in cameras],
            t0=recording.t0,
            schedule=options.link_schedule,
            urgent_at=lambda t_s: _urgent_index(options, t_s),
        ),
        recoveries=()
        if traced
        else recoveries(
            recording.arrivals,
            recording.ticks,
            robots=[camera.robot for camera in cameras],
            t0=recording.t0,
            end_s=len(analysis.steps) * options.step_seconds,
            schedule=options.link_schedule,
            robot_schedules=options.robot_schedules,
        ),
        expected_hz=_expected_hz(options, analysis.steps),
        urgent=tuple(
            stream_latency(
                recording.arrivals, len(cameras) + k, name="mapped" if s.mapped else "unmapped"
            )
            for k, s in enumerate(URGENT_STREAMS)
            if options.urgent_stream
        ),
    )
