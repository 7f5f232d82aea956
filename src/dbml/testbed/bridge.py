"""``dbml bridge`` as a testbed helper: ended like a role, its publishers' timing kept.

Run as ``python -m dbml.testbed.bridge STATS_FILE BRIDGE_ARGS...``: the ``dbml bridge`` command
itself (``dbml.cli.main.main(["bridge", *BRIDGE_ARGS])``, unchanged), with two things a testbed
run needs besides:

- it ends gracefully on ``stop`` or EOF on stdin, as the roles do (the runner's word for the end,
  or its parent gone): the thread reading stdin raises SIGINT in this process, which ``dbml
  bridge`` takes as Ctrl-C (its transport closed, so no ``/dev/shm/fastdds_*`` is left), and
  the exit code is 0 as for a role told to stop;
- at its exit it writes, as one JSON list in ``STATS_FILE``, the publish statistics its rclpy
  publishers log when they close (``dbml.transports.rclpy.PublishStats``: calls, refusals,
  the longest and the 99th percentile of ``publish()``), so the run can say whether a full
  link ever blocked or refused the bridge's publishes.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

from dbml.transports.worker import BackgroundThread

__all__ = ["STATS_LOGGER", "PublishStatsHandler", "main", "read_stats"]

STATS_LOGGER = "dbml.rclpy"
"""The logger whose records carry ``publish_stats`` (the rclpy transport's)."""
_INTERRUPTED = 130

log = logging.getLogger("dbml.testbed")


class PublishStatsHandler(logging.Handler):
    """Keeps the ``publish_stats`` of every record that carries one, as plain dicts."""

    def __init__(self) -> None:
        super().__init__(level=logging.INFO)
        self.stats: list[dict[str, Any]] = []

    def emit(self, record: logging.LogRecord) -> None:
        """Keep the record's statistics, if it carries any."""
        stats = getattr(record, "publish_stats", None)
        if stats is not None and is_dataclass(stats) and not isinstance(stats, type):
            self.stats.append(asdict(stats))


def read_stats(path: Path) -> list[dict[str, Any]]:
    """What :func:`main` wrote to ``path``; empty if it wrote nothing (killed, or never ran)."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    return [row for row in document if isinstance(row, dict)] if isinstance(document, list) else []


def main(argv: list[str] | None = None) -> int:
    """Run ``dbml bridge`` with ``argv[1:]``; write its publish statistics to ``argv[0]``."""
    args = sys.argv[1:] if argv is None else argv
    if not args:
        sys.stderr.write("usage: python -m dbml.testbed.bridge STATS_FILE BRIDGE_ARGS...\n")
        return 2
    stats_file, bridge_args = Path(args[0]), args[1:]
    handler = PublishStatsHandler()
    logger = logging.getLogger(STATS_LOGGER)
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)  # the statistics are INFO: kept whatever the root's level
    told = threading.Event()

    def watch_stdin() -> None:
        for line in sys.stdin:
            if line.startswith("stop"):  # the experiment runner's word for the end
                break
        told.set()
        os.kill(os.getpid(), signal.SIGINT)  # ``dbml bridge``'s Ctrl-C: it closes and exits

    from dbml.cli.main import main as dbml_main

    BackgroundThread(watch_stdin, name="stdin", log=log).start()
    try:
        code = dbml_main(["bridge", *bridge_args])
    except KeyboardInterrupt:  # before ``dbml bridge`` took the signal over
        code = _INTERRUPTED
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a late word from stdin changes nothing
        logger.removeHandler(handler)
        stats_file.write_text(json.dumps(handler.stats), encoding="utf-8")
    return 0 if told.is_set() and code == _INTERRUPTED else code


if __name__ == "__main__":
    sys.exit(main())
