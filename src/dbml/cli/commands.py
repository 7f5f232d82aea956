"""The bodies of ``dbml optimizer|publish|subscribe|bridge|priority|budget|monitor``.

Each runs on a transport ``dbml.cli.main`` opened, until its duration ends or ``stop`` is set
(SIGINT or SIGTERM, through ``harness.stop_on_signals``); the caller closes the transport (zenoh
sessions must be closed for the process to exit). They live beside the parser, not in the
runtime: they are what a command does with the runtime's nodes. ``dbml optimizer``'s body is the
runtime's ``run_optimizer`` (``dbml.runtime.serve``), which the experiment's optimizer role runs
too, and so is ``dbml bridge``'s (``run_bridge``), which the experiment's bridges run.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TextIO

from dbml.core.spec import MAX_SIZE_BYTES, check_number, check_priority
from dbml.protocol import names
from dbml.protocol.schema import check_param
from dbml.runtime.monitor import MonitorView, monitor_view
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.rounds import RoundFollower
from dbml.runtime.serve import PEER_WAIT_S, Lifetime, run_bridge, run_optimizer
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports.base import ParamValue, Sample, Transport, TransportPriority
from dbml.transports.registry import camera_frame

__all__ = [
    "PEER_WAIT_S",
    "run_bridge",
    "run_monitor",
    "run_optimizer",
    "run_publisher",
    "run_subscriber",
    "set_budget",
    "set_priority",
]

log = logging.getLogger("dbml")


def run_publisher(
    transport: Transport,
    topic: str,
    *,
    transport_name: str,
    size_bytes: int,
    min_rate_hz: float,
    max_rate_hz: float,
    priority: float | None,
    stop: threading.Event,
    duration_s: float | None = None,
    transport_priority: TransportPriority | None = None,
) -> int:
    """``dbml publish``: a managed publisher of synthetic frames, paced by its rate.

    ``transport_name`` is the registry's name of ``transport`` (it says how frames are made).
    ``transport_priority`` fixes the middleware class of its messages (a control stream's),
    instead of the one its priority maps to.
    """
    check_number(size_bytes, field="--size-bytes", minimum=0, exclusive_minimum=True)
    check_number(size_bytes, field="--size-bytes", maximum=MAX_SIZE_BYTES)
    transport.wait_for_peers(PEER_WAIT_S)
    payload = camera_frame(
        transport, transport_name, topic, size_bytes
    )  # first: it types the topic
    publisher = ManagedPublisher(
        transport,
        topic,
        min_rate_hz=min_rate_hz,
        max_rate_hz=max_rate_hz,
        priority=priority,
        transport_priority=transport_priority,
    )
    life = Lifetime(stop, duration_s)
    shown: float | None = None
    try:
        while not life.over():
            publisher.rate.sleep()
            publisher.publish(payload)
            rate = publisher.current_rate_hz()
            if rate != shown:
                shown = rate
                log.info("%s: publishing %d B at %.3f Hz", topic, size_bytes, rate)
    finally:
        publisher.close()
    return life.exit_code()


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
    life = Lifetime(stop, duration_s, watching=(reporter, subscriber))
    try:
        while not life.over():
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
    return life.exit_code()


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
    """Hand a fresh ``MonitorView`` to ``show`` every ``interval_s`` until stopped.

    The optimizer reports every period: the first view waits up to ``interval_s`` for its
    report, so it shows the shares of the budget from the start.
    """
    rounds = RoundFollower(transport)
    try:
        transport.wait_for_peers(PEER_WAIT_S)
        life = Lifetime(stop, duration_s)
        first = True
        while not life.over():
            report = rounds.wait(interval_s) if first else rounds.latest()
            first = False
            show(monitor_view(transport, report))
            stop.wait(interval_s)
        return life.exit_code()
    finally:
        rounds.close()
