"""The commands behind ``dbml optimizer|publish|subscribe|priority|budget|monitor``.

Each opens a transport, runs until its duration ends, SIGINT or SIGTERM, and closes the
transport on the way out (zenoh sessions must be closed for the process to exit).
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import TextIO

from dbml.core.config import BridgeChannel, DbmSettings
from dbml.core.errors import TransportError
from dbml.core.spec import MAX_SIZE_BYTES, LinkSpec, check_number, check_priority
from dbml.runtime import names
from dbml.runtime.bridge import FIRST_MESSAGE_TIMEOUT_S, Bridge
from dbml.runtime.estimator import LinkEstimator
from dbml.runtime.monitor import MonitorView, monitor_view
from dbml.runtime.optimizer import OptimizerNode
from dbml.runtime.params import check_param
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports.base import ParamValue, Sample, Transport, TransportPriority

__all__ = [
    "PEER_WAIT_S",
    "run_bridge",
    "run_monitor",
    "run_optimizer",
    "run_publisher",
    "run_subscriber",
    "set_budget",
    "set_priority",
    "stop_on_signals",
]

log = logging.getLogger("dbml")

PEER_WAIT_S = 2.0
"""How long a command waits to reach a running dbml process before going on alone."""


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM, so loops end cleanly and transports get closed."""
    stop = threading.Event()
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda *_: stop.set())
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _until(stop: threading.Event, duration_s: float | None) -> Callable[[], bool]:
    deadline = None if duration_s is None else time.monotonic() + duration_s
    return lambda: stop.is_set() or (deadline is not None and time.monotonic() >= deadline)


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
    done = _until(stop, duration_s)
    try:
        while not done():
            if not node.alive or (estimator is not None and not estimator.alive):
                log.critical("a worker thread died (see above); exiting so a supervisor restarts")
                return 1
            stop.wait(0.1)
    finally:
        node.stop()
        if estimator is not None:
            estimator.close()
    return 0


def run_publisher(
    transport: Transport,
    topic: str,
    *,
    size_bytes: int,
    min_rate_hz: float,
    max_rate_hz: float,
    priority: float | None,
    stop: threading.Event,
    duration_s: float | None = None,
    transport_priority: TransportPriority | None = None,
) -> int:
    """``dbml publish``: a managed publisher of synthetic frames, paced by its rate.

    ``transport_priority`` fixes the middleware class of its messages (a control stream's),
    instead of the one its priority maps to.
    """
    check_number(size_bytes, field="--size-bytes", minimum=0, exclusive_minimum=True)
    check_number(size_bytes, field="--size-bytes", maximum=MAX_SIZE_BYTES)
    transport.wait_for_peers(PEER_WAIT_S)
    payload = transport.camera_frame(topic, size_bytes)  # first: it may set the ROS type
    publisher = ManagedPublisher(
        transport,
        topic,
        min_rate_hz=min_rate_hz,
        max_rate_hz=max_rate_hz,
        priority=priority,
        transport_priority=transport_priority,
    )
    done = _until(stop, duration_s)
    shown: float | None = None
    try:
        while not done():
            publisher.rate.sleep()
            publisher.publish(payload)
            rate = publisher.current_rate_hz()
            if rate != shown:
                shown = rate
                log.info("%s: publishing %d B at %.3f Hz", topic, size_bytes, rate)
    finally:
        publisher.close()
    return 0


def run_bridge(
    transport: Transport,
    channels: Sequence[BridgeChannel],
    *,
    stop: threading.Event,
    duration_s: float | None = None,
    wait_s: float = FIRST_MESSAGE_TIMEOUT_S,
    typed_topics: bool = False,
) -> int:
    """``dbml bridge``: put existing topics under management, one ``Bridge`` each.

    A channel without a type takes the one the graph shows. Where topics are typed
    (``typed_topics``: ROS 1, ROS 2) and the graph shows none, ``TransportError`` names the
    topic: republishing under a guessed type would deliver what no subscriber can read. Every
    topic must deliver a first message within ``wait_s``, else ``TransportError`` names it.
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
                "%s: bridged to %s/optimized (%s)",
                bridge.topic,
                bridge.topic,
                bridge.channel.msg_type or "bytes",
            )
        done = _until(stop, duration_s)
        while not done():
            if not all(bridge.alive for bridge in bridges):
                log.critical("a bridge's thread died (see above); exiting")
                return 1
            stop.wait(0.1)
    finally:
        for bridge in bridges:
            bridge.close()
    return 0


@dataclass
class _Meter:
    """Counts what arrives, for rates over the last second."""

    arrivals: deque[tuple[float, int]]
    lock: threading.Lock

    def add(self, sample: Sample) -> None:
        with self.lock:
            self.arrivals.append((time.monotonic(), len(sample.payload)))

    def window(self, seconds: float) -> tuple[float, float]:
        now = time.monotonic()
        with self.lock:
            while self.arrivals and self.arrivals[0][0] < now - seconds:
                self.arrivals.popleft()
            count = len(self.arrivals)
            size = sum(n for _, n in self.arrivals)
        return count / seconds, size / seconds


def run_subscriber(
    transport: Transport,
    topic: str,
    *,
    as_json: bool,
    stop: threading.Event,
    duration_s: float | None = None,
    out: TextIO = sys.stdout,
) -> int:
    """``dbml subscribe``: a managed subscriber printing what it receives once a second."""
    transport.wait_for_peers(PEER_WAIT_S)
    meter = _Meter(deque(), threading.Lock())
    reporter = ReceptionReporter(transport).start()  # for an optimizer that estimates
    subscriber = ManagedSubscriber(transport, topic, meter.add, reporter=reporter)
    done = _until(stop, duration_s)
    try:
        while not done():
            if not reporter.alive:
                log.critical("the reception reporter died (see above); exiting")
                return 1
            stop.wait(1.0)
            rate_hz, bytes_per_s = meter.window(1.0)
            variant = subscriber.variant.value
            if as_json:
                line = {
                    "topic": topic,
                    "variant": variant,
                    "rate_hz": rate_hz,
                    "bytes_per_s": bytes_per_s,
                }
                out.write(json.dumps(line) + "\n")
            else:
                out.write(f"{topic} [{variant}] {rate_hz:.2f} Hz {bytes_per_s:,.0f} B/s\n")
            out.flush()
    finally:
        subscriber.close()
        reporter.close()
    return 0


def set_priority(transport: Transport, topic: str, value: float) -> int:
    """``dbml priority``: write a channel's raw priority and wait for a peer to hold it."""
    names.check_channel(topic)
    priority = check_priority(value)
    if not transport.wait_for_peers(PEER_WAIT_S):
        log.warning("no running dbml process reached; the value is set for none to read")
    transport.params.set(names.priority(topic), priority)
    if not transport.confirm_param(names.priority(topic), timeout_s=PEER_WAIT_S):
        log.warning("no other process confirmed %s", names.priority(topic))
    return 0


def set_budget(transport: Transport, mbit: float, *, utilization: float | None = None) -> int:
    """``dbml budget``: write the link's bandwidth (and utilization) and wait for a peer."""
    values: dict[str, ParamValue] = {names.BANDWIDTH: check_param(names.BANDWIDTH, mbit)}
    if utilization is not None:
        values[names.UTILIZATION] = check_param(names.UTILIZATION, utilization)
    if not transport.wait_for_peers(PEER_WAIT_S):
        log.warning("no running dbml process reached; the value is set for none to read")
    for name, value in values.items():
        transport.params.set(name, value)
    for name in values:
        if not transport.confirm_param(name, timeout_s=PEER_WAIT_S):
            log.warning("no other process confirmed %s", name)
    return 0


def run_monitor(
    transport: Transport,
    *,
    show: Callable[[MonitorView], None],
    stop: threading.Event,
    duration_s: float | None = None,
    interval_s: float = 1.0,
) -> int:
    """Hand a fresh ``MonitorView`` to ``show`` every ``interval_s`` until stopped."""
    transport.wait_for_peers(PEER_WAIT_S)
    done = _until(stop, duration_s)
    while not done():
        show(monitor_view(transport))
        stop.wait(interval_s)
    return 0
