"""The optimizer's rounds as another process hears them: the newest report, checked on its way in.

The live view and ``dbml monitor`` show what the optimizer decided from its ``RoundReport``s
(``dbml.protocol.messages``) instead of allocating again from the values they hold, which lack the
optimizer's links, frame headroom and estimate. A report comes from the network: a malformed one
is logged once per reason and dropped; only the newest good one is kept.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from dbml.core.errors import TransportError
from dbml.protocol.keys import ROUND_TOPIC
from dbml.protocol.messages import RoundReport
from dbml.transports.base import Handle, Sample, Transport
from dbml.transports.callbacks import CallbackList
from dbml.transports.overflow import LogOnce

__all__ = ["RoundFollower"]

log = logging.getLogger("dbml.rounds")


class RoundFollower:
    """The newest round report heard on ``transport``; ``watch`` is told of each new one.

    Decoding runs on the middleware's thread: a report is a few hundred bytes a channel, so it
    costs what reading it later would, and a bad one never reaches a reader.
    """

    def __init__(self, transport: Transport) -> None:
        self._lock = threading.Condition()
        self._latest: RoundReport | None = None
        self._bad = LogOnce(log)
        self._watchers: CallbackList[[RoundReport]] = CallbackList()
        self._subscription = transport.subscribe(ROUND_TOPIC, self._on_sample)

    def _on_sample(self, sample: Sample) -> None:
        try:
            report = RoundReport.decode(sample.payload)
        except TransportError as err:
            self._bad.warning(str(err)[:40], "ignoring a round report: %s", err)
            return
        with self._lock:
            self._latest = report
            self._lock.notify_all()
        self._watchers.fire(report)

    def latest(self) -> RoundReport | None:
        """The newest report heard (None before the first)."""
        with self._lock:
            return self._latest

    def wait(self, timeout_s: float) -> RoundReport | None:
        """The newest report, waiting up to ``timeout_s`` for the first one."""
        with self._lock:
            self._lock.wait_for(lambda: self._latest is not None, timeout=timeout_s)
            return self._latest

    def watch(self, callback: Callable[[RoundReport], None]) -> Handle:
        """Call ``callback(report)`` for every good report from now on (middleware thread)."""
        return self._watchers.add(callback)

    def close(self) -> None:
        """Stop hearing reports."""
        self._subscription.close()
