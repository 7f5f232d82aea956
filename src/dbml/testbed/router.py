"""A zenoh router for one testbed host, meshed with another host's router.

``dbml router`` only listens; the testbed's router topology (a router per host, as ROS 2 fleets
run rmw_zenoh's) also needs each robot's router to connect to the operator's, across the shaped
link. Run as ``python -m dbml.testbed.router --listen EP [--connect EP]`` inside a namespace;
it ends on SIGINT, SIGTERM, ``stop`` or EOF on stdin (its parent went away), and with exit
code 1 when the thread reading stdin dies (it could no longer be told to stop).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

import zenoh

from dbml.harness.processes import stop_on_signals
from dbml.runtime.serve import Lifetime
from dbml.transports.worker import BackgroundThread
from dbml.transports.zenoh.transport import RETRY_MAX_MS, prepare_runtime, put_link_timeouts

__all__ = ["main", "open_meshed_router"]

POLL_S = 0.5
"""How often the main thread looks whether a signal asked it to stop, or a thread died."""

log = logging.getLogger("dbml.testbed")


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
    prepare_runtime()
    return zenoh.open(config)


def main(argv: list[str] | None = None) -> int:
    """Run one router until a signal or the end of stdin."""
    parser = argparse.ArgumentParser(prog="python -m dbml.testbed.router")
    parser.add_argument("--listen", action="append", required=True, metavar="ENDPOINT")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    args = parser.parse_args(argv)
    with stop_on_signals() as stop:
        session = open_meshed_router(listen=args.listen, connect=args.connect)

        def watch_stdin() -> None:
            for line in sys.stdin:
                if line.startswith("stop"):  # the experiment runner's word for the end
                    break
            stop.set()

        life = Lifetime(stop, None)
        BackgroundThread(watch_stdin, name="stdin", log=log).start()
        try:
            while not life.over():
                stop.wait(POLL_S)
        finally:
            session.close()  # type: ignore[no-untyped-call]  # unannotated in the stubs
    return life.exit_code()


if __name__ == "__main__":
    sys.exit(main())
