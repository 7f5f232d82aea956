"""One experiment runner: start the roles, give them one start time, collect what they report.

The demo and the testbed differ only in where the roles run: OS processes on loopback (zenoh,
ROS 1), OS processes inside network namespaces (the caller's ``command`` wraps the argv), or
threads over one in-process memory network. The runner starts them, waits until every one is
ready, sends step 1's wall-clock time, pumps the operator's reports until it is done (or a
deadline passes), hands a :class:`Snapshot` to the observer after each report (progress, live
view) and returns a :class:`Recording`. Every process it started is ended by PID on the way
out, also on error, Ctrl-C and SIGTERM (raised here as ``KeyboardInterrupt``).
"""

from __future__ import annotations

import contextlib
import queue
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from types import FrameType

from dbml.core.errors import DbmlError
from dbml.experiment.analysis import Analysis, Arrival, Tick, analyse
from dbml.experiment.report import TICK, OperatorReport
from dbml.experiment.roles import RoleSpec, run_role
from dbml.harness.processes import Message, RoleProcesses, wait_ready
from dbml.scenarios.teleop import ROBOTS, STEPS
from dbml.transports.memory import MemoryNetwork, MemoryTransport

__all__ = [
    "HELPER_LISTEN_TIMEOUT_S",
    "READY_TIMEOUT_S",
    "START_MARGIN_S",
    "Command",
    "Helper",
    "Observer",
    "Recording",
    "RoleThreads",
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

Command = Callable[[str, list[str]], tuple[list[str], Mapping[str, str] | None]]
"""A role and the argv that runs it -> the argv and environment to start (netns exec, env)."""
HELPER_LISTEN_TIMEOUT_S = 15.0
"""How long a helper with a ``port`` (a zenoh router) may take to accept connections."""


@dataclass(frozen=True, slots=True, kw_only=True)
class Helper:
    """A process the roles need that speaks no role protocol: a zenoh router, a bridge.

    It starts just before role ``before`` (None: before every role), once ``port`` on
    127.0.0.1 accepts connections when given; it counts as a role that exits early if it ends
    before the last step, and is ended by PID with the roles.
    """

    name: str
    argv: tuple[str, ...]
    env: Mapping[str, str] | None = None
    before: str | None = None
    port: int | None = None


def _wait_listening(what: str, helper: Helper, roles: RoleProcesses) -> None:
    """Wait until ``helper.port`` accepts a connection; fail naming it if it ended or timed out."""
    assert helper.port is not None
    deadline = time.monotonic() + HELPER_LISTEN_TIMEOUT_S
    while time.monotonic() < deadline:
        if roles.children[helper.name].poll() is not None:
            raise _exited_early(what, helper.name, roles.log_tail(helper.name))
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", helper.port), 1):
            return
        time.sleep(0.05)
    raise DbmlError(f"{what} {helper.name} did not listen on port {helper.port} in time")


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
        )


class RoleThreads:
    """The roles as threads sharing one in-process memory network."""

    def __init__(self) -> None:
        self.messages: queue.Queue[Message] = queue.Queue()
        self._network = MemoryNetwork()
        self._stop = threading.Event()
        self._started = threading.Event()
        self._t0 = 0.0
        self._threads: list[threading.Thread] = []
        self._errors: dict[str, str] = {}

    def spawn(self, role: str, spec: RoleSpec) -> None:
        """Start ``role`` on its own host of the memory network."""
        transport = MemoryTransport(self._network, host=spec.host)

        def emit(message: dict[str, object]) -> None:
            self.messages.put((role, message))

        def body() -> None:
            try:
                emit({"type": "ready", "role": role})
                self._started.wait()
                if not self._stop.is_set():
                    run_role(role, transport, spec, t0=self._t0, stop=self._stop, emit=emit)
            except Exception:
                self._errors[role] = traceback.format_exc()
            finally:
                transport.close()
                self.messages.put((role, None))

        thread = threading.Thread(target=body, name=f"role-{role}", daemon=True)
        thread.start()
        self._threads.append(thread)

    def start(self, t0: float) -> None:
        """Every role starts step 1 at ``t0``."""
        self._t0 = t0
        self._started.set()

    def log_tail(self, role: str) -> str:
        """The traceback of a role that failed."""
        return self._errors.get(role, "")

    def close(self) -> None:
        """Stop every role and wait for it."""
        self._stop.set()
        self._started.set()
        for thread in self._threads:
            thread.join(timeout=5.0)


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


def _start_helpers(
    what: str, helpers: Sequence[Helper], roles: RoleThreads | RoleProcesses, *, before: str | None
) -> None:
    """Start the helpers that go just before role ``before``, in their order."""
    for helper in helpers:
        if helper.before == before and isinstance(roles, RoleProcesses):
            roles.spawn(helper.name, helper.argv, env=helper.env)
            if helper.port is not None:
                _wait_listening(what, helper, roles)


def _exited_early(what: str, role: str, tail: str) -> DbmlError:
    """One line: the role and the last lines of its log."""
    lines = " | ".join(tail.strip().splitlines()[-3:])
    return DbmlError(f"{what} role {role} exited early{': ' + lines if lines else ''}")


def run_experiment(
    specs: Mapping[str, RoleSpec],
    *,
    what: str,
    command: Command | None,
    observe: Observer | None = None,
    on_start: Callable[[float, threading.Event], None] | None = None,
    helpers: Sequence[Helper] = (),
) -> Recording:
    """Run the roles of ``specs`` (processes through ``command``, or threads when it is None).

    ``what`` names the experiment in errors; ``on_start(t0, stop)`` runs in a thread from step
    1's start until the run ends (the testbed's link changes); ``helpers`` are processes started
    among the roles (each just before its ``before`` role), which need ``command``.
    """
    if helpers and command is None:
        raise DbmlError(f"{what}: helper processes need role processes, not threads")
    step_s = next(iter(specs.values())).step_s
    total_s = len(STEPS) * step_s
    roles = RoleThreads() if command is None else RoleProcesses()
    arrivals: list[Arrival] = []
    ticks: list[Tick] = []
    t0: float | None = None
    stop = threading.Event()
    with sigterm_as_interrupt():
        try:
            _start_helpers(what, helpers, roles, before=None)
            for role, spec in specs.items():
                _start_helpers(what, helpers, roles, before=role)
                if isinstance(roles, RoleThreads):
                    roles.spawn(role, spec)
                else:
                    assert command is not None
                    argv = [sys.executable, "-m", "dbml.experiment.roles", role, spec.to_json()]
                    argv, env = command(role, argv)
                    roles.spawn(role, argv, env=env)
            try:
                ended = wait_ready(roles.messages, set(specs), timeout_s=READY_TIMEOUT_S)
            except queue.Empty:
                raise DbmlError(f"{what} roles did not get ready in time") from None
            if ended is not None:
                raise _exited_early(what, ended, roles.log_tail(ended))
            t0 = time.time() + START_MARGIN_S
            roles.start(t0)
            if on_start is not None:
                threading.Thread(target=on_start, args=(t0, stop), daemon=True).start()
            while True:
                try:
                    role, message = roles.messages.get(timeout=0.5)
                except queue.Empty:
                    if time.time() > t0 + total_s + REPORT_DEADLINE_S:
                        raise DbmlError(f"{what} timed out waiting for the operator") from None
                    continue
                if message is None:
                    if role == "operator":
                        break
                    if time.time() < t0 + total_s:
                        raise _exited_early(what, role, roles.log_tail(role))
                    continue
                if message.get("type") == "done":
                    break
                if message.get("type") == TICK:
                    report = OperatorReport.decode(message)
                    arrivals.extend(report.frames)
                    ticks.append(report.tick)
                    if observe is not None:
                        elapsed = min(max(0.0, ticks[-1].t_s - t0), total_s)
                        step = min(len(STEPS), int(elapsed // step_s) + 1)
                        observe(Snapshot(t0, elapsed, step, arrivals, ticks))
        except KeyboardInterrupt:
            return Recording(t0, tuple(arrivals), tuple(ticks), interrupted=True)
        finally:
            stop.set()
            roles.close()
    return Recording(t0, tuple(arrivals), tuple(ticks), interrupted=False)
