"""One experiment runner: start the roles, give them one start time, collect what they report.

The demo and the testbed differ only in where the roles run: OS processes on loopback (zenoh,
ROS 1), OS processes inside network namespaces (the caller's ``command`` wraps the argv), or
threads over one in-process memory network. The runner starts them, waits until every one is
ready, sends step 1's wall-clock time, pumps the operator's reports until it is done (or a
deadline passes), hands a :class:`Snapshot` to the observer after each report (progress, live
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
from dbml.runtime.serve import Lifetime
from dbml.scenarios.teleop import ROBOTS, STEPS
from dbml.transports.memory import MemoryNetwork, MemoryTransport
from dbml.transports.worker import BackgroundThread

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

_CLOSE_WAIT_S = 5.0
"""How long closing waits for each role run as a thread."""

log = logging.getLogger("dbml.experiment")

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
        self._threads: dict[str, BackgroundThread] = {}
        self._ended: set[str] = set()
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
                self._ended.add(role)
                self.messages.put((role, None))

        self._threads[role] = BackgroundThread(body, name=f"role-{role}", log=log).start()

    def start(self, t0: float) -> None:
        """Every role starts step 1 at ``t0``."""
        self._t0 = t0
        self._started.set()

    def log_tail(self, role: str) -> str:
        """The traceback of a role that failed."""
        return self._errors.get(role, "")

    def exit_code(self, role: str, *, timeout_s: float = 0.0) -> int | None:
        """1 for a role that raised, 0 for one that returned; None while it runs."""
        self._threads[role].join(timeout_s)
        if role not in self._ended:
            return None
        return 1 if role in self._errors else 0

    def close(self) -> dict[str, int]:
        """Stop every role and wait for it; each one's ``exit_code`` (-1: it still runs)."""
        self._stop.set()
        self._started.set()
        codes: dict[str, int] = {}
        for role in self._threads:
            code = self.exit_code(role, timeout_s=_CLOSE_WAIT_S)
            codes[role] = -1 if code is None else code
        return codes


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


def _exited_early(what: str, role: str, tail: str, *, code: int | None = None) -> DbmlError:
    """One line: the role, how it ended (early, or failed with ``code``) and its log's end."""
    lines = " | ".join(tail.strip().splitlines()[-3:])
    how = "exited early" if code is None or code <= 0 else f"failed (exit code {code})"
    return DbmlError(f"{what} role {role} {how}{': ' + lines if lines else ''}")


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
    life = Lifetime(stop, None)
    codes: dict[str, int] = {}
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
                start = functools.partial(on_start, t0, stop)
                BackgroundThread(start, name="on-start", log=log).start()
            while True:
                if life.failed:
                    raise DbmlError(f"{what}: a thread of the runner died (see above)")
                try:
                    role, message = roles.messages.get(timeout=0.5)
                except queue.Empty:
                    if time.time() > t0 + total_s + REPORT_DEADLINE_S:
                        raise DbmlError(f"{what} timed out waiting for the operator") from None
                    continue
                if message is None:
                    code = roles.exit_code(role)  # None if not yet: ``close`` has it then
                    if (code is not None and code > 0) or time.time() < t0 + total_s:
                        raise _exited_early(what, role, roles.log_tail(role), code=code)
                    if role == "operator":
                        break
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
            codes = roles.close()
    # The first role, in start order, that exited non-zero on its own (not ended by a signal).
    failed = next((role for role, code in codes.items() if code > 0), None)
    if failed is not None:
        raise _exited_early(what, failed, roles.log_tail(failed), code=codes[failed])
    if life.failed:
        raise DbmlError(f"{what}: a thread of the runner died (see above)")
    return Recording(t0, tuple(arrivals), tuple(ticks), interrupted=False)
