"""The managed subscriber (the paper's DBMSubscriber).

It receives ``[topic]`` when the topic is published on its own host and ``[topic]/optimized``
otherwise, and switches when the publisher moves. Until a publisher is seen it takes the
optimized copy, the one that is safe to receive over a network. Its graph announcement is what
makes the optimizer manage the channel. With a reporter, what arrives over the network is
also reported for bandwidth estimation.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from dbml.runtime.graph import publisher_hosts
from dbml.runtime.reception import ReceptionReporter
from dbml.transports.base import Handle, Role, Sample, Transport, Variant, check_topic

__all__ = ["ManagedSubscriber"]


class ManagedSubscriber:
    def __init__(
        self,
        transport: Transport,
        topic: str,
        callback: Callable[[Sample], None],
        *,
        reporter: ReceptionReporter | None = None,
    ) -> None:
        self.topic = check_topic(topic)
        self._transport = transport
        self._callback = callback
        self._reporter = reporter
        self._lock = threading.RLock()  # announcing may call back into _update
        self._variant: Variant | None = None
        self._subscription: Handle | None = None
        self._token: Handle | None = None
        self._closed = False
        self._graph_watch = transport.graph.watch(self._update)
        self._update()

    @property
    def variant(self) -> Variant:
        with self._lock:
            assert self._variant is not None
            return self._variant

    def _wanted(self) -> Variant:
        hosts = publisher_hosts(self._transport.graph.entries(), self.topic)
        return Variant.FULL if self._transport.host in hosts else Variant.OPTIMIZED

    def _update(self) -> None:
        with self._lock:
            if self._closed:
                return
            wanted = self._wanted()
            if wanted is self._variant:
                return
            old_subscription, old_token = self._subscription, self._token
            self._variant = wanted
            # Subscribe to the new copy before leaving the old one, so nothing is missed.
            callback = self._callback
            if wanted is Variant.OPTIMIZED and self._reporter is not None:
                callback = self._reported
            self._subscription = self._transport.subscribe(self.topic, callback, wanted)
            self._token = self._transport.graph.announce(Role.SUBSCRIBER, self.topic, wanted)
        if old_subscription is not None:
            old_subscription.close()
        if old_token is not None:
            old_token.close()

    def _reported(self, sample: Sample) -> None:
        assert self._reporter is not None
        self._reporter.record(sample)
        self._callback(sample)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            handles = [self._graph_watch, self._subscription, self._token]
        for handle in handles:
            if handle is not None:
                handle.close()
