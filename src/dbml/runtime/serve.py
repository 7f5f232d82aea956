"""A node served until stopped: the optimizer and the bridges, as commands and as the experiment's.

``run_optimizer`` waits for its peers, runs the optimizer (and the estimator when asked);
``run_bridge`` puts existing topics under management. Each exits 1 when a worker thread dies,
so a supervisor restarts it. ``Lifetime`` is every command's run, and the one place that tells
a dead thread's end of it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from typing import Protocol

from dbml.core.config import BridgeChannel, DbmSettings
from dbml.core.errors import TransportError
from dbml.core.spec import LinkSpec
from dbml.estimator import EstimatorSettings
from dbml.estimator.designs import DEFAULT_DESIGN, Design, settings_of
from dbml.protocol import names
from dbml.runtime.bridge import FIRST_MESSAGE_TIMEOUT_S, Bridge
from dbml.runtime.estimator import LinkEstimator
from dbml.runtime.optimizer import OptimizerNode, Round
from dbml.transports.base import Transport, Variant
from dbml.transports.worker import death_count

__all__ = [
    "PEER_WAIT_S",
    "Lifetime",
    "OptimizerRun",
    "Running",
    "run_bridge",
    "run_optimizer",
    "serve_optimizer",
]

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


class OptimizerRun:
    """The optimizer node and its estimator (with ``estimate``), built together, run as one.

    Built idle: ``start`` runs both (after a ``pause``, it resumes the allocation; the
    estimator measured throughout), ``close`` ends both. ``alive`` is False once a thread of
    theirs died. A lifecycle drives these; ``serve_optimizer`` starts at once.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        settings: DbmSettings | None,
        links: tuple[LinkSpec, ...],
        estimate: bool = False,
        design: Design = DEFAULT_DESIGN,
        write_defaults: bool = False,
        on_round: Callable[[Round], None] | None = None,
    ) -> None:
        if settings is None and transport.params.get(names.BANDWIDTH) is None:
            log.warning("no budget yet: waiting for %s (or pass --config)", names.BANDWIDTH)
        self.estimator = (
            LinkEstimator(transport, settings=EstimatorSettings(detector=settings_of(design)))
            if estimate
            else None
        )
        self._design = design
        self.node = OptimizerNode(
            transport,
            settings=settings,
            links=links,
            budget_mbit=None if self.estimator is None else self.estimator.budget_mbit,
            write_defaults=write_defaults,
            on_round=on_round,
        )
        self._host = transport.host
        self._started = False

    @property
    def alive(self) -> bool:
        """False once the optimizer's or the estimator's thread died."""
        return self.node.alive and (self.estimator is None or self.estimator.alive)

    def start(self) -> None:
        """Run the estimator and the optimizer (the first round now); after a pause, resume."""
        if self._started:
            self.node.resume()
            return
        self._started = True
        if self.estimator is not None:
            self.estimator.on_change = self.node.poke
            self.estimator.start()
            log.info(
                "estimating the bandwidth from reception reports (design %s, at most the "
                "configured)",
                self._design.value,
            )
        self.node.start()
        log.info("optimizer running on host %s", self._host)

    def pause(self) -> None:
        """Allocate nothing until ``start``: the publishers fall back as with no optimizer."""
        self.node.pause()
        log.info("optimizer paused: no allocation until it is activated")

    def close(self) -> None:
        """End both (bounded waits)."""
        self.node.stop()
        if self.estimator is not None:
            self.estimator.close()


def run_optimizer(
    transport: Transport,
    *,
    settings: DbmSettings | None,
    links: tuple[LinkSpec, ...],
    stop: threading.Event,
    duration_s: float | None = None,
    estimate: bool = False,
    design: Design = DEFAULT_DESIGN,
    write_defaults: bool = False,
    on_round: Callable[[Round], None] | None = None,
) -> int:
    """``dbml optimizer``: the optimizer node (with ``estimate``, the estimator of ``design``).

    ``on_round`` sees each round (``OptimizerNode``'s).
    """
    return serve_optimizer(
        transport,
        build=lambda: OptimizerRun(
            transport,
            settings=settings,
            links=links,
            estimate=estimate,
            design=design,
            write_defaults=write_defaults,
            on_round=on_round,
        ),
        stop=stop,
        duration_s=duration_s,
    )


def serve_optimizer(
    transport: Transport,
    *,
    build: Callable[[], OptimizerRun],
    stop: threading.Event,
    duration_s: float | None = None,
) -> int:
    """Wait for peers, build the optimizer with ``build`` and run it until the run is over."""
    transport.wait_for_peers(PEER_WAIT_S)
    run = build()
    run.start()
    life = Lifetime(stop, duration_s, watching=(run,))
    try:
        while not life.over():
            stop.wait(0.1)
    finally:
        run.close()
    return life.exit_code()


def run_bridge(
    transport: Transport,
    channels: Sequence[BridgeChannel],
    *,
    stop: threading.Event,
    duration_s: float | None = None,
    wait_s: float = FIRST_MESSAGE_TIMEOUT_S,
    typed_topics: bool = False,
    closed: Callable[[Bridge], None] | None = None,
) -> int:
    """``dbml bridge``: put existing topics under management, one ``Bridge`` each.

    A channel without a type takes the one the graph shows. Where topics are typed
    (``typed_topics``: ROS 1, ROS 2) and the graph shows none, ``TransportError`` names the
    topic: republishing under a guessed type would deliver what no subscriber can read. Every
    topic must deliver a first message within ``wait_s``, else ``TransportError`` names it.
    ``closed`` sees each bridge once it is closed (what it sent is final then).
    """
    transport.wait_for_peers(PEER_WAIT_S)
    deadline = time.monotonic() + wait_s
    bridges: list[Bridge] = []
    try:
        for given in channels:
            channel = given
            if given.msg_type is None:
                left_s = max(0.0, deadline - time.monotonic())
                found = transport.topic_type(given.topic, timeout_s=left_s)
                if found is not None:
                    channel = replace(given, msg_type=found)
                elif typed_topics:
                    raise TransportError(
                        f"topic={given.topic!r}: its type cannot be resolved (no publisher "
                        f"seen within {wait_s:g} s); name it with --type pkg/msg/Name"
                    )
            bridges.append(Bridge(transport, channel))
        for bridge in bridges:
            if not bridge.wait_first(max(0.0, deadline - time.monotonic())):
                raise TransportError(
                    f"topic={bridge.topic!r}: no message within {wait_s:g} s "
                    "(is its publisher running on this host?)"
                )
            bridge.start(timeout_s=0)
            log.info(
                "%s: bridged to %s (%s)",
                bridge.topic,
                (Variant.COMPRESSED if bridge.channel.ladder else Variant.OPTIMIZED).key(
                    bridge.topic
                ),
                bridge.channel.msg_type or "bytes",
            )
        life = Lifetime(stop, duration_s, watching=bridges)
        while not life.over():
            stop.wait(0.1)
    finally:
        for bridge in bridges:
            bridge.close()
            if closed is not None:
                closed(bridge)
    return life.exit_code()
