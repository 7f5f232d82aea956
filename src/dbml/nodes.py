"""The long-running commands behind ``dbml optimizer|publish|subscribe|priority|monitor``.

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
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TextIO

from rich.console import Console
from rich.live import Live
from rich.table import Table

from dbml.core.config import DbmSettings
from dbml.core.errors import SpecError
from dbml.core.spec import BYTES_PER_S_PER_MBIT, LinkSpec
from dbml.runtime import names
from dbml.runtime.estimator import LinkEstimator
from dbml.runtime.graph import is_managed, published_topics, publisher_hosts
from dbml.runtime.optimizer import OptimizerNode
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports.base import Sample, Transport, param_number

__all__ = [
    "ChannelRow",
    "channel_rows",
    "run_monitor",
    "run_optimizer",
    "run_publisher",
    "run_subscriber",
    "set_priority",
    "stop_on_signals",
    "synthetic_frame",
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


def _reach_peers(transport: Transport) -> bool:
    wait = getattr(transport, "wait_for_peers", None)
    return True if wait is None else bool(wait(PEER_WAIT_S))


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
    _reach_peers(transport)
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
            stop.wait(0.1)
    finally:
        node.stop()
        if estimator is not None:
            estimator.close()
    return 0


def synthetic_frame(transport: Transport, topic: str, size_bytes: int) -> bytes:
    """A synthetic camera frame of ``size_bytes``: raw bytes, or over ROS 1 a serialised
    ``sensor_msgs/Image`` of exactly that size (one mono8 row after the header), so the size the
    optimizer sees is the one asked for."""
    ros1 = sys.modules.get("dbml.transports.ros1")
    if ros1 is None or not isinstance(transport, ros1.Ros1Transport):
        return bytes(size_bytes)
    from sensor_msgs.msg import Image

    transport.use_message_class(topic, Image)
    image = Image(height=1, encoding="mono8", data=b"")
    pixels = size_bytes - len(ros1.serialize(image))
    image.width = image.step = pixels
    image.data = bytes(pixels)
    serialized: bytes = ros1.serialize(image)
    assert len(serialized) == size_bytes
    return serialized


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
) -> int:
    if size_bytes <= 0:
        raise SpecError(f"--size-bytes={size_bytes!r} must be > 0")
    _reach_peers(transport)
    payload = synthetic_frame(transport, topic, size_bytes)  # first: it may set the ROS type
    publisher = ManagedPublisher(
        transport, topic, min_rate_hz=min_rate_hz, max_rate_hz=max_rate_hz, priority=priority
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
    _reach_peers(transport)
    meter = _Meter(deque(), threading.Lock())
    reporter = ReceptionReporter(transport).start()  # for an optimizer that estimates
    subscriber = ManagedSubscriber(transport, topic, meter.add, reporter=reporter)
    done = _until(stop, duration_s)
    try:
        while not done():
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
    if isinstance(value, bool) or not 0.0 <= value <= 1.0:
        raise SpecError(f"priority={value!r} must be within [0, 1]")
    if not _reach_peers(transport):
        log.warning("no running dbml process reached; the value is set for none to read")
    transport.params.set(names.priority(topic), float(value))
    confirm = getattr(transport, "confirm_param", None)
    if confirm is not None and not confirm(names.priority(topic), timeout_s=PEER_WAIT_S):
        log.warning("no other process confirmed %s", names.priority(topic))
    return 0


@dataclass(frozen=True, slots=True)
class ChannelRow:
    topic: str
    host: str
    managed: bool
    priority: float
    size_bytes: float | None
    allocated_hz: float | None
    share: float | None
    status: str
    estimate_mbit: float | None = None
    estimator: str | None = None

    def as_json(self) -> dict[str, Any]:
        return {
            "topic": self.topic,
            "host": self.host,
            "managed": self.managed,
            "priority": self.priority,
            "size_bytes": self.size_bytes,
            "allocated_hz": self.allocated_hz,
            "share": self.share,
            "status": self.status,
            "estimate_mbit": self.estimate_mbit,
            "estimator": self.estimator,
        }


def channel_rows(transport: Transport) -> list[ChannelRow]:
    """Every live channel as ``dbml monitor`` shows it; share is of the budget."""
    entries = transport.graph.entries()
    params = transport.params.snapshot()
    bandwidth = param_number(params.get(names.BANDWIDTH))
    estimate = param_number(params.get(names.ESTIMATE))
    utilization = param_number(params.get(names.UTILIZATION)) or 1.0
    budget = None  # what the optimizer allocates: the estimate is already the usable budget
    if estimate is not None:
        budget = estimate * BYTES_PER_S_PER_MBIT
    elif bandwidth is not None:
        budget = bandwidth * utilization * BYTES_PER_S_PER_MBIT
    status = params.get(names.STATUS)
    estimator = params.get(names.ESTIMATOR_STATE)
    rows = []
    for topic in sorted(published_topics(entries)):
        if names.max_rate(topic) not in params:
            continue  # not a dbml channel (ROS 1's graph lists every topic, /rosout too)
        managed = is_managed(entries, topic)
        size = param_number(params.get(names.size(topic)))
        allocated = param_number(params.get(names.current_value(topic)))
        share = None
        if managed and budget and size is not None and allocated is not None:
            share = allocated * size / budget
        if allocated is None:
            state = "no allocation"
        elif not managed:
            state = "unmanaged"
        else:
            state = str(status) if isinstance(status, str) else "managed"
        rows.append(
            ChannelRow(
                topic=topic,
                host=",".join(sorted(publisher_hosts(entries, topic))),
                managed=managed,
                priority=param_number(params.get(names.priority(topic))) or 0.0,
                size_bytes=size,
                allocated_hz=allocated,
                share=share,
                status=state,
                estimate_mbit=estimate,
                estimator=estimator if isinstance(estimator, str) else None,
            )
        )
    return rows


def _monitor_table(transport: Transport, rows: list[ChannelRow]) -> Table:
    params = transport.params
    budget = param_number(params.get(names.BANDWIDTH))
    estimate = param_number(params.get(names.ESTIMATE))
    title = "dbml monitor"
    if budget is not None:
        title += f" — budget {budget:g} Mbit/s"
    if estimate is not None:
        title += f", estimate {estimate:.2f} Mbit/s"
        state = params.get(names.ESTIMATOR_STATE)
        if isinstance(state, str):
            title += f" ({state})"
    table = Table(title=title)
    for name in (
        "topic",
        "host",
        "managed",
        "priority",
        "size B",
        "allocated Hz",
        "share",
        "status",
    ):
        table.add_column(name, justify="left" if name in {"topic", "host", "status"} else "right")
    for row in rows:
        table.add_row(
            row.topic,
            row.host,
            "yes" if row.managed else "no",
            f"{row.priority:.2f}",
            "-" if row.size_bytes is None else f"{row.size_bytes:,.0f}",
            "-" if row.allocated_hz is None else f"{row.allocated_hz:.2f}",
            "-" if row.share is None else f"{row.share:.1%}",
            row.status,
        )
    message = params.get(names.STATUS_MESSAGE)
    if isinstance(message, str):
        table.caption = message
    return table


def run_monitor(
    transport: Transport,
    *,
    as_json: bool,
    stop: threading.Event,
    duration_s: float | None = None,
    interval_s: float = 1.0,
    out: TextIO = sys.stdout,
) -> int:
    _reach_peers(transport)
    done = _until(stop, duration_s)
    if as_json:
        while not done():
            for row in channel_rows(transport):
                out.write(json.dumps(row.as_json()) + "\n")
            out.flush()
            stop.wait(interval_s)
        return 0
    console = Console(file=out)
    with Live(console=console, auto_refresh=False) as live:
        while not done():
            live.update(_monitor_table(transport, channel_rows(transport)), refresh=True)
            stop.wait(interval_s)
    return 0
