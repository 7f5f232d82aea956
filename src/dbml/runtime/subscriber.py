"""The managed subscriber (the paper's DBMSubscriber).

It receives ``[topic]`` when the topic is published on its own host only and
``[topic]/optimized`` otherwise, and switches when the publisher moves. Until a publisher is
seen it takes the optimized copy, the one that is safe to receive over a network. Its graph
announcement is what makes the optimizer manage the channel. With a reporter, what arrives over
the network is also reported for bandwidth estimation.

A switch subscribes and announces: middleware calls, which must not run on the middleware's
callback thread that tells of a graph change (zenoh's liveliness thread, a ROS master's poll).
A graph change only wakes the subscriber's own worker thread, which switches; it also looks
every ``RECHECK_S``, so a switch that failed is retried without waiting for another change.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from dbml.core.errors import TransportError
from dbml.protocol import names
from dbml.runtime.graph import publisher_hosts
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.worker import PeriodicWorker
from dbml.transports.base import Handle, Role, Sample, Transport, Variant

__all__ = ["FIRST_SWITCH_TIMEOUT_S", "RECHECK_S", "ManagedSubscriber"]

log = logging.getLogger("dbml.subscriber")

FIRST_SWITCH_TIMEOUT_S = 10.0
"""How long the constructor waits for its first subscription."""
RECHECK_S = 1.0
"""How often the worker looks at the graph unprompted: it retries a failed switch within a
second, and reading the graph view is cheap (every transport keeps it in memory)."""


class ManagedSubscriber:
    """Receive ``topic`` in the right copy, following the publisher's host.

    ``remote``: the copy taken from another host; a camera's JPEG is ``Variant.COMPRESSED``.
    """

    def __init__(
        self,
        transport: Transport,
        topic: str,
        callback: Callable[[Sample], None],
        *,
        reporter: ReceptionReporter | None = None,
        remote: Variant = Variant.OPTIMIZED,
    ) -> None:
        if not remote.managed:
            raise ValueError(f"remote={remote.value!r} is not a managed copy")
        self.topic = names.check_channel(topic)
        self._remote = remote
        self._transport = transport
        self._callback = callback
        self._reporter = reporter
        # The lock guards state only; graph reads, subscribing and announcing happen outside it
        # (announcing fires every graph watcher, other subscribers' updates among them).
        self._lock = threading.Lock()
        self._variant: Variant | None = None
        self._subscription: Handle | None = None
        self._token: Handle | None = None
        self._pending = False
        self._updating = False
        self._closed = False
        self._subscribed = threading.Event()
        self._worker = PeriodicWorker(
            self._update, interval_s=RECHECK_S, name=f"dbml-subscriber {topic}", log=log
        )
        # A graph change only wakes the worker: the watch may call on a middleware thread.
        self._graph_watch = transport.graph.watch(self._worker.wake, topic=topic)
        try:
            self._update()  # the first switch here, so that its error is the caller's
        except BaseException:
            self._graph_watch.close()
            raise
        self._worker.start()
        # The first switch above subscribed; the wait bounds it should that ever change.
        if not self._subscribed.wait(timeout=FIRST_SWITCH_TIMEOUT_S):
            self.close()
            raise TransportError(
                f"subscriber of {topic!r}: no subscription after {FIRST_SWITCH_TIMEOUT_S:g} s"
            )

    @property
    def variant(self) -> Variant:
        """The copy received now: ``full`` from a local publisher, else ``optimized``."""
        with self._lock:
            assert self._variant is not None
            return self._variant

    def _wanted(self) -> Variant:
        # Full rate only when every publisher is here: a forged "publisher on this host" beside
        # a real remote one must not pull the full-rate stream across the network.
        hosts = publisher_hosts(self._transport.graph.entries(topic=self.topic), self.topic)
        return Variant.FULL if hosts == {self._transport.host} else self._remote

    @property
    def alive(self) -> bool:
        """False once the worker thread died (a command then exits non-zero)."""
        return self._worker.alive

    def _update(self) -> None:
        """Follow the graph (on the worker's thread, or the constructor's for the first time).

        One thread at a time switches; a change seen meanwhile (also one caused by our own
        announcement) makes that thread look again instead of waiting.
        """
        with self._lock:
            self._pending = True
            if self._updating or self._closed:
                return
            self._updating = True
        try:
            while True:
                with self._lock:  # "nothing pending" and "no longer updating" in one step
                    if not self._pending or self._closed:
                        self._updating = False
                        return
                    self._pending = False
                    current = self._variant
                wanted = self._wanted()
                if wanted is not current:
                    self._switch(wanted)
        except BaseException:
            with self._lock:
                self._updating = False
                self._pending = True  # a failed read or switch: the next graph event retries
            raise

    def _switch(self, wanted: Variant) -> None:
        # Subscribe to the new copy before leaving the old one, so nothing is missed.
        callback = self._callback
        if wanted.managed and self._reporter is not None:
            callback = self._reported
        subscription = self._transport.subscribe(self.topic, callback, wanted)
        token = self._transport.graph.announce(Role.SUBSCRIBER, self.topic, wanted)
        with self._lock:
            old = [self._subscription, self._token]
            if self._closed:  # closed meanwhile: the new handles go too
                old = [subscription, token]
            else:
                self._variant, self._subscription, self._token = wanted, subscription, token
                self._subscribed.set()
        for handle in old:
            if handle is not None:
                handle.close()

    def _reported(self, sample: Sample) -> None:
        assert self._reporter is not None
        self._reporter.record(sample)
        self._callback(sample)

    def close(self) -> None:
        """Stop following the graph (waiting for a switch under way), unsubscribe, withdraw."""
        with self._lock:
            self._closed = True
        self._graph_watch.close()
        self._worker.stop()
        with self._lock:
            handles = [self._subscription, self._token]
            self._subscription = self._token = None
        for handle in handles:
            if handle is not None:
                handle.close()
