"""A zenoh router for one host of a run, meshed with another host's router.

``dbml router`` only listens; the testbed's router topology (a router per host, as ROS 2 fleets
run rmw_zenoh's) also needs each robot's router to connect to the operator's, across the shaped
link, and the demo's ROS 2 nodes meet at one. Run as ``python -m dbml.experiment router --listen
EP [--connect EP]`` (inside a namespace); it ends on SIGINT, SIGTERM, ``stop`` or EOF on stdin
(its parent went away), and with exit code 1 when the thread reading stdin dies (it could no
longer be told to stop).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterable, Sequence

import zenoh

from dbml.harness.child import Control
from dbml.runtime.serve import Lifetime
from dbml.transports.zenoh.transport import (
    NET_THREADS,
    RETRY_MAX_MS,
    ROUTER_RX_THREADS,
    RUNTIME_ENV,
    prepare_runtime,
    put_link_timeouts,
)

__all__ = ["open_meshed_router", "serve"]

POLL_S = 0.5
"""How often the main thread looks whether a signal asked it to stop, or a thread died."""


def open_meshed_router(*, listen: list[str], connect: list[str]) -> zenoh.Session:
    """A router session on ``listen`` that keeps trying ``connect``; no scouting, no shm.

    Shared memory would carry payloads past the shaped link, multicast scouting would find
    hosts outside the testbed.
    """
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps(listen))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("transport/shared_memory/enabled", "false")
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(connect))
        config.insert_json5("connect/exit_on_failure", "false")
        config.insert_json5("connect/timeout_ms", "-1")
        config.insert_json5(
            "connect/retry", f"{{period_init_ms: 100, period_max_ms: {RETRY_MAX_MS}}}"
        )
    put_link_timeouts(
        config
    )  # its link crosses the shaped one: an outage's return found as a peer's
    # The testbed's own router: a runtime inherited from the process that started the run (set
    # there by its own sessions, a client's) is not a choice made for a router.
    os.environ.pop(RUNTIME_ENV, None)
    prepare_runtime(rx_threads=ROUTER_RX_THREADS, net_threads=NET_THREADS)
    return zenoh.open(config)


def serve(
    stop: threading.Event,
    *,
    listen: Sequence[str],
    connect: Sequence[str] = (),
    lines: Iterable[str] | None = None,
) -> int:
    """Run one router until ``stop`` (a signal, or ``stop``/EOF on ``lines``); its exit code."""
    session = open_meshed_router(listen=list(listen), connect=list(connect))
    life = Lifetime(stop, None)
    Control(stop, lines=lines, name="stdin").start()
    try:
        while not life.over():
            stop.wait(POLL_S)
    finally:
        session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
    return life.exit_code()
