"""A node served until stopped: the optimizer as ``dbml optimizer`` and the experiment run it.

It waits for its peers, runs the optimizer (and the estimator when asked), and exits 1 when a
worker thread dies, so a supervisor restarts it. ``Lifetime`` is every command's run.
"""

from __future__ import annotations

import logging
import threading
import time

from dbml.core.config import DbmSettings
from dbml.core.spec import LinkSpec
from dbml.protocol import names
from dbml.runtime.estimator import LinkEstimator
from dbml.runtime.optimizer import OptimizerNode
from dbml.transports.base import Transport
from dbml.transports.worker import death_count

__all__ = ["PEER_WAIT_S", "Lifetime", "run_optimizer"]

log = logging.getLogger("dbml")

PEER_WAIT_S = 2.0
"""How long a command waits to reach a running dbml process before going on alone."""


class Lifetime:
    """A command's run: over at ``stop``, after ``duration_s``, or when a dbml thread dies.

    ``duration_s`` None runs until stopped. A thread of this process that died since the run
    began makes its exit code 1, so a supervisor restarts it (a process that looks alive and does
    nothing is worse).
    """

    def __init__(self, stop: threading.Event, duration_s: float | None) -> None:
        self._stop = stop
        self._deadline = None if duration_s is None else time.monotonic() + duration_s
        self._deaths = death_count()

    @property
    def failed(self) -> bool:
        """Whether a dbml thread of this process died since the run began."""
        return death_count() > self._deaths

    def over(self) -> bool:
        """Whether the run should end now."""
        return (
            self._stop.is_set()
            or (self._deadline is not None and time.monotonic() >= self._deadline)
            or self.failed
        )

    def exit_code(self) -> int:
        """1 when a thread died (said once, critical), else 0."""
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
    life = Lifetime(stop, duration_s)
    try:
        while not life.over():
            if not node.alive or (estimator is not None and not estimator.alive):
                log.critical("a worker thread died (see above); exiting so a supervisor restarts")
                return 1
            stop.wait(0.1)
    finally:
        node.stop()
        if estimator is not None:
            estimator.close()
    return life.exit_code()
