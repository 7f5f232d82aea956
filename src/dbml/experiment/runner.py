"""One experiment runner: start the roles, give them one start time, collect what they report.

The demo and the testbed differ only in where the roles run, which their layout says in a
:class:`Plan`: OS processes on loopback (zenoh, ROS 1, ROS 2), OS processes inside network
namespaces, or threads over one in-process memory network. The runner starts them (and the
helpers among them: a router, the bridges) through one ``harness.Supervisor``, waits until every
role is ready, sends step 1's wall-clock time, pumps the operator's reports until it is done (or
a deadline passes), hands a :class:`Snapshot` to the observer after each report (progress, live
view) and returns a :class:`Recording`. Every process it started is ended by PID on the way
out, also on error, Ctrl-C and SIGTERM (raised here as ``KeyboardInterrupt``).

A run is failed (``DbmlError`` naming the role) when a role or helper exits non-zero, whenever
that happens (a role that lost a dbml thread exits 1), and when a thread of the runner's own
process dies (its readers, ``on_start``, the roles run as threads): a run with a dead part
measured something else.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

from dbml.core.errors import DbmlError
from dbml.experiment import roles
from dbml.experiment.analysis import Analysis, Arrival, Tick, analyse
from dbml.experiment.plan import Plan
from dbml.experiment.report import (
    PUBLISH_REPORT,
    TICK,
    OperatorReport,
    PublishReport,
    PublishTiming,
)
from dbml.experiment.spec import RoleSpec
from dbml.harness.supervisor import ChildExitedError, ChildIO, Supervisor
from dbml.runtime.serve import Lifetime
from dbml.scenarios.teleop import ROBOTS, STEPS
from dbml.transports.memory import MemoryNetwork
from dbml.transports.worker import BackgroundThread

__all__ = [
    "HELPER_LISTEN_TIMEOUT_S",
    "READY_TIMEOUT_S",
    "START_MARGIN_S",
    "Observer",
    "Recording",
    "Snapshot",
    "run_experiment",
    "sigterm_as_interrupt",
]

READY_TIMEOUT_S = 60.0
"""How long the roles may take to open their transports and find their peers."""
START_MARGIN_S = 1.5
"""Step 1 starts this long after every role is ready: each has heard ``start`` by then, and a
robot's first frame (sent at once, at the 1 Hz minimum, to make its size known) is more than a
period old, so the rate limiter lets step 1's frames through at the allocated rate."""
REPORT_DEADLINE_S = 30.0
"""The operator's last report may come this long after the last step, then the run fails."""
HELPER_LISTEN_TIMEOUT_S = 15.0
"""How long a helper with a ``port`` (a zenoh router) may take to accept connections."""
_PUMP_S = 0.5
"""How often the runner looks at the time and its own threads while it waits for reports."""
_CONNECT_S = 1.0

log = logging.getLogger("dbml.experiment")


@dataclass(frozen=True, slots=True)
class Snapshot:
    """What the operator reported so far (the lists grow; do not keep them)."""

    t0: float
    elapsed_s: float
    step: int
    arrivals: Sequence[Arrival]
    ticks: Sequence[Tick]


Observer = Callable[[Snapshot], None]


@dataclass(frozen=True, slots=True)
class Recording:
    """What one run collected; ``t0`` is None when it never started."""

    t0: float | None
    arrivals: tuple[Arrival, ...]
    ticks: tuple[Tick, ...]
    interrupted: bool
    publishes: Mapping[str, tuple[PublishTiming, ...]] = field(default_factory=dict)
    """What each helper that reported its publishes (a bridge) said of them, by its name."""

    def steps_done(self, step_s: float) -> int:
        """The steps the operator saw to their end."""
        if self.t0 is None:
            return 0
        if not self.interrupted:
            return len(STEPS)
        last = max((t.t_s for t in self.ticks), default=self.t0)
        return max(0, min(len(STEPS), int((last - self.t0) // step_s)))

    def analyse(
        self,
        *,
        step_s: float,
        link_mbit: float,
        schedule: Sequence[tuple[float, float]] = (),
        robots: Sequence[str] | None = None,
        link_events: bool = True,
    ) -> Analysis:
        """Every step the operator saw, the time series and the link changes (see ``analyse``).

        ``robots`` names the operator's streams in order (a fleet's ``R1``..``RN``; by default
        the paper's two).
        """
        assert self.t0 is not None, "a run that never started has nothing to analyse"
        return analyse(
            self.arrivals,
            self.ticks,
            robots=[camera.robot for camera in ROBOTS] if robots is None else robots,
            t0=self.t0,
            step_s=step_s,
            steps=self.steps_done(step_s),
            link_mbit=link_mbit,
            schedule=schedule,
            link_events=link_events,
        )


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM unwinds like Ctrl-C, so every process and namespace is removed either way."""
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


def _exited_early(what: str, role: str, tail: str, *, code: int | None = None) -> DbmlError:
    """One line: the role, how it ended (early, or failed with ``code``) and its log's end."""
    lines = " | ".join(tail.strip().splitlines()[-3:])
    how = "exited early" if code is None or code <= 0 else f"failed (exit code {code})"
    return DbmlError(f"{what} role {role} {how}{': ' + lines if lines else ''}")


def _listening(port: int) -> bool:
    """Whether something on 127.0.0.1 accepts connections on ``port``."""
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), _CONNECT_S):
        return True
    return False


class _Run:
    """The children of one run, started in the plan's order through one supervisor."""

    def __init__(self, what: str, plan: Plan, children: Supervisor) -> None:
        self._what = what
        self._plan = plan
        self.children = children
        self._network = MemoryNetwork() if plan.launches is None else None

    def start_helpers(self, *, before: str | None) -> None:
        """Start the helpers that go just before role ``before``, in their order."""
        for helper in self._plan.helpers:
            if helper.before != before:
                continue
            launch = helper.launch
            self.children.start(helper.name, launch.argv, env=launch.env, netns=launch.netns)
            port = helper.port
            if port is None:
                continue
            try:
                self.children.wait_until(
                    functools.partial(_listening, port),
                    timeout_s=HELPER_LISTEN_TIMEOUT_S,
                    watch=[helper.name],
                    what=f"{helper.name} on port {port}",
                )
            except ChildExitedError as ended:
                raise _exited_early(self._what, helper.name, ended.tail) from None
            except TimeoutError:
                raise DbmlError(
                    f"{self._what} {helper.name} did not listen on port {port} in time"
                ) from None

    def start_role(self, role: str, spec: RoleSpec) -> None:
        """Start ``role``: its process, or its thread on the run's memory network."""
        if self._plan.launches is not None:
            launch = self._plan.launches[role]
            self.children.start(role, launch.argv, env=launch.env, netns=launch.netns)
            return
        network = self._network

        def body(io: ChildIO) -> int:
            return roles.serve(
                role, spec, threading.Event(), lines=io.lines, emit=io.emit, network=network
            )

        self.children.start_thread(role, body)

    def tail(self, name: str) -> str:
        return self.children[name].log_tail()

    def publishes(self) -> dict[str, tuple[PublishTiming, ...]]:
        """What the helpers reported of their publishes (read once they ended)."""
        found: dict[str, tuple[PublishTiming, ...]] = {}
        for line in self.children.take_all(lambda line: line.kind == PUBLISH_REPORT):
            if line.report is not None:
                found[line.child] = PublishReport.decode(line.report).publishers
        return found


def run_experiment(
    plan: Plan,
    *,
    what: str,
    observe: Observer | None = None,
    on_start: Callable[[float, threading.Event], None] | None = None,
    logs: Path | None = None,
) -> Recording:
    """Run the roles of ``plan``: their processes (or threads), and its helpers among them.

    ``what`` names the experiment in errors; ``on_start(t0, stop)`` runs in a thread from step
    1's start until the run ends (the testbed's link changes); ``logs``: a folder where each
    child's stderr is kept as ``NAME.log`` (None: kept only until the run ends).
    """
    specs = plan.specs
    step_s = next(iter(specs.values())).step_s
    total_s = len(STEPS) * step_s
    arrivals: list[Arrival] = []
    ticks: list[Tick] = []
    t0: float | None = None
    stop = threading.Event()
    life = Lifetime(stop, None)
    children = Supervisor(logs=logs)
    run = _Run(what, plan, children)
    codes: dict[str, int] = {}
    publishes: dict[str, tuple[PublishTiming, ...]] = {}
    interrupted = False
    with sigterm_as_interrupt():
        try:
            run.start_helpers(before=None)
            for role, spec in specs.items():
                run.start_helpers(before=role)
                run.start_role(role, spec)
            try:
                ended = children.wait_ready(specs, timeout_s=READY_TIMEOUT_S)
            except TimeoutError:
                raise DbmlError(f"{what} roles did not get ready in time") from None
            if ended is not None:
                raise _exited_early(what, ended, run.tail(ended))
            t0 = time.time() + START_MARGIN_S
            children.send(f"start {t0!r}")
            if on_start is not None:
                start = functools.partial(on_start, t0, stop)
                BackgroundThread(start, name="on-start", log=log).start()
            while True:
                if life.failed:
                    raise DbmlError(f"{what}: a thread of the runner died (see above)")
                line = children.take(
                    lambda line: line.ended or line.kind in (TICK, "done"), timeout_s=_PUMP_S
                )
                if line is None:
                    if time.time() > t0 + total_s + REPORT_DEADLINE_S:
                        raise DbmlError(f"{what} timed out waiting for the operator")
                    continue
                role = line.child
                if line.ended:
                    code = children[role].poll()  # None if not yet: ``close`` has it then
                    if (code is not None and code > 0) or time.time() < t0 + total_s:
                        raise _exited_early(what, role, run.tail(role), code=code)
                    if role == "operator":
                        break
                    continue
                if line.kind == "done":
                    break
                if line.report is not None:
                    report = OperatorReport.decode(line.report)
                    arrivals.extend(report.frames)
                    ticks.append(report.tick)
                    if observe is not None:
                        elapsed = min(max(0.0, ticks[-1].t_s - t0), total_s)
                        step = min(len(STEPS), int(elapsed // step_s) + 1)
                        observe(Snapshot(t0, elapsed, step, arrivals, ticks))
        except KeyboardInterrupt:
            interrupted = True
        finally:
            stop.set()
            codes = children.close()
            publishes = run.publishes()
    if interrupted:
        return Recording(t0, tuple(arrivals), tuple(ticks), True, publishes)
    # The first child, in start order, that exited non-zero on its own (not ended by a signal).
    failed = next((name for name, code in codes.items() if code > 0), None)
    if failed is not None:
        raise _exited_early(what, failed, run.tail(failed), code=codes[failed])
    if life.failed:
        raise DbmlError(f"{what}: a thread of the runner died (see above)")
    return Recording(t0, tuple(arrivals), tuple(ticks), interrupted=False, publishes=publishes)
