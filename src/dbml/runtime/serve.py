"""A node served until stopped: the optimizer as ``dbml optimizer`` and the experiment run it.

It waits for its peers, runs the optimizer (and the estimator when asked), and exits 1 when a
worker thread dies, so a supervisor restarts it. ``Lifetime`` is every command's run, and the
one place that tells a dead thread's end of it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable
from typing import Protocol

from dbml.core.config import DbmSettings
from dbml.core.spec import LinkSpec
from dbml.protocol import names
from dbml.runtime.estimator import LinkEstimator
from dbml.runtime.optimizer import OptimizerNode
from dbml.transports.base import Transport
from dbml.transports.worker import death_count

__all__ = ["PEER_WAIT_S", "Lifetime", "Running", "run_optimizer"]

log = logging.getLogger("dbml")

PEER_WAIT_S = 2.0
"""How long a command waits to reach a running dbml process before going on alone."""


class Running(Protocol):
    """What a run watches: a node part whose ``alive`` turns False when its work ended."""

    @property
    def alive(self) -> bool:
        """False once its thread died or ended."""


class Lifetime:
    """A command's run: over at ``stop``, after ``duration_s``, or when a dbml thread dies.

    ``duration_s`` None runs until stopped. A thread of this process that died since the run
    began makes its exit code 1, so a supervisor restarts it (a process that looks alive and does
    nothing is worse). So does the end of anything in ``watching`` while the run lasts, death or
    not (a bridge's loop that returned): ``over`` looks, so closing them after the run is none.
    """

    def __init__(
        self, stop: threading.Event, duration_s: float | None, *, watching: Iterable[Running] = ()
    ) -> None:
        self._stop = stop
        self._deadline = None if duration_s is None else time.monotonic() + duration_s
        self._deaths = death_count()
        self._watching = tuple(watching)
        self._ended = False
        """Whether ``over`` found one of ``watching`` no longer alive."""

    @property
    def failed(self) -> bool:
        """Whether a dbml thread of this process died, or one watched ended, during the run."""
        return self._ended or death_count() > self._deaths

    def over(self) -> bool:
        """Whether the run should end now."""
        if not self._ended and not all(running.alive for running in self._watching):
            self._ended = True
        return (
            self._stop.is_set()
            or (self._deadline is not None and time.monotonic() >= self._deadline)
            or self.failed
        )

    def exit_code(self) -> int:
        """1 when a thread died or one watched ended (said once, critical), else 0."""
        if not self.failed:
            return 0
        log.critical("a worker thread died (see above); exiting so a supervisor restarts it")
        return 1


def run_optimizer(
    transport: Transport,
    *,
    settings: DbmSettings | None,
    links: tuple[LinkSpec, ...],
    stop: threading.Event,
    duration_s: float | None = None,
    estimate: bool = False,
    write_defaults: bool = False,
) -> int:
    """``dbml optimizer``: the optimizer node (and the estimator with ``estimate``)."""
    transport.wait_for_peers(PEER_WAIT_S)
    if settings is None and transport.params.get(names.BANDWIDTH) is None:
        log.warning("no budget yet: waiting for %s (or pass --config)", names.BANDWIDTH)
    estimator = LinkEstimator(transport) if estimate else None
    node = OptimizerNode(
        transport,
        settings=settings,
        links=links,
        budget_mbit=None if estimator is None else estimator.budget_mbit,
        write_defaults=write_defaults,
    )
    if estimator is not None:
        estimator.on_change = node.poke
        estimator.start()
        log.info("estimating the bandwidth from reception reports (at most the configured)")
    node.start()
    log.info("optimizer running on host %s", transport.host)
    life = Lifetime(stop, duration_s, watching=(node,) if estimator is None else (node, estimator))
    try:
        while not life.over():
            stop.wait(0.1)
    finally:
        node.stop()
        if estimator is not None:
            estimator.close()
    return life.exit_code()
