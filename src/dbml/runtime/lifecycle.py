"""What each transition of a managed (lifecycle) optimizer does, without ROS.

ROS 2's managed nodes (Nav2's lifecycle manager drives them) go unconfigured -> inactive ->
active and back. The optimizer maps them so:

- **configure** builds the optimizer and its estimator, idle: nothing is allocated yet;
- **activate** runs them: the first round now, every rate pushed;
- **deactivate** pauses the allocation: no rate, no status, no heartbeat. Every publisher falls
  back, ``failsafe_periods`` later, to what it does when no optimizer runs at all, which is what
  an inactive node owes its peers;
- **cleanup** and **shutdown** close them (shutdown also ends the command, exit 0).

The middleware keeps the states and refuses a transition its graph lacks (rclpy's lifecycle
node); this class only does the work, so it is tested without one. A transition that cannot be
done raises ``LifecycleError``, which the middleware answers as a failed transition.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

from dbml.core.errors import DbmlError
from dbml.runtime.serve import PEER_WAIT_S, Lifetime, OptimizerRun, Running
from dbml.transports.base import Transport

__all__ = ["LifecycleError", "OptimizerLifecycle", "Served", "run_managed_optimizer"]

log = logging.getLogger("dbml")


class LifecycleError(DbmlError):
    """A transition that cannot be done in the optimizer's present state."""


class OptimizerLifecycle:
    """An optimizer built, run, paused and closed by lifecycle transitions.

    ``build`` makes the idle optimizer (``configure`` calls it); ``stop`` is set by
    ``shutdown``, so the command's run ends. Calls come from one thread at a time (the
    middleware's lifecycle services); ``alive`` may be read from any.
    """

    def __init__(self, build: Callable[[], OptimizerRun], *, stop: threading.Event) -> None:
        self._build = build
        self._stop = stop
        self._run: OptimizerRun | None = None

    @property
    def run(self) -> OptimizerRun | None:
        """The optimizer while configured, else None."""
        return self._run

    @property
    def alive(self) -> bool:
        """False once a thread of the configured optimizer died (the command then exits 1)."""
        run = self._run
        return run is None or run.alive

    def _configured(self, transition: str) -> OptimizerRun:
        if self._run is None:
            raise LifecycleError(f"transition={transition!r}: the optimizer is not configured")
        return self._run

    def configure(self) -> None:
        """Build the optimizer, idle."""
        if self._run is not None:
            raise LifecycleError("transition='configure': the optimizer is configured already")
        self._run = self._build()
        log.info("optimizer configured (inactive: allocating nothing)")

    def activate(self) -> None:
        """Run it: a round now, then every period."""
        self._configured("activate").start()
        log.info("optimizer active")

    def deactivate(self) -> None:
        """Pause the allocation; publishers fall back as with no optimizer."""
        self._configured("deactivate").pause()

    def cleanup(self) -> None:
        """Close the optimizer; configure builds a new one."""
        self._configured("cleanup").close()
        self._run = None
        log.info("optimizer cleaned up (unconfigured)")

    def shutdown(self) -> None:
        """Close whatever runs and end the command."""
        if self._run is not None:
            self._run.close()
            self._run = None
        log.info("optimizer shut down")
        self._stop.set()

    def close(self) -> None:
        """The command's end: close whatever runs (no transition)."""
        if self._run is not None:
            self._run.close()
            self._run = None


class Served(Running, Protocol):
    """The middleware's side of a lifecycle: its services, until closed."""

    def close(self) -> None:
        """Stop serving the lifecycle's services."""


def run_managed_optimizer(
    transport: Transport,
    *,
    build: Callable[[], OptimizerRun],
    serve: Callable[[OptimizerLifecycle], Served],
    stop: threading.Event,
    duration_s: float | None = None,
) -> int:
    """``dbml optimizer --lifecycle``: unconfigured until a lifecycle manager drives it.

    ``serve`` puts the lifecycle on the middleware; the run ends at ``shutdown`` (exit 0), at
    ``stop`` or ``duration_s``, or when a thread dies (exit 1), as ``run_optimizer``'s.
    """
    transport.wait_for_peers(PEER_WAIT_S)
    lifecycle = OptimizerLifecycle(build, stop=stop)
    server = serve(lifecycle)
    life = Lifetime(stop, duration_s, watching=(lifecycle, server))
    try:
        while not life.over():
            stop.wait(0.1)
    finally:
        server.close()  # no transition runs after this
        lifecycle.close()
    return life.exit_code()
