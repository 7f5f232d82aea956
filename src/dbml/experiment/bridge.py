"""The experiment's bridge: ``dbml bridge``'s run as a child of a run, its publishes reported.

The demo and the testbed put each plain ROS 2 camera under management with a bridge on its
robot's host (``python -m dbml.experiment bridge SPEC_JSON``). It runs the runtime's
``run_bridge`` (as ``dbml bridge`` does) with two things a run needs besides:

- it ends on ``stop`` or EOF on stdin, as the roles do (the runner's word for the end, or its
  parent gone), and closes its transport (so no ``/dev/shm/fastdds_*`` is left), exit code 0;
- at its end it reports how its publishes on ``[topic]/optimized`` went, where the middleware's
  publisher keeps such statistics (rclpy's: calls, refusals, the longest and the 99th
  percentile of ``publish()``): one :class:`PublishReport`, a JSON line the runner collects,
  so the run can say whether a full link ever blocked or refused the bridge.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from dbml.core.config import BridgeChannel
from dbml.core.errors import DbmlError
from dbml.experiment.report import PublishReport, PublishTiming
from dbml.experiment.spec import transport_entry
from dbml.harness.child import Control, Emit, emit_json
from dbml.runtime.bridge import Bridge
from dbml.runtime.serve import run_bridge
from dbml.transports.registry import TransportEntry, open_transport

__all__ = ["BridgeSpec", "serve", "timing_of"]


@dataclass(frozen=True, slots=True, kw_only=True)
class BridgeSpec:
    """One bridge of a run: the channel, and the transport it opens on its robot's host."""

    topic: str
    min_rate_hz: float
    max_rate_hz: float
    msg_type: str | None
    wait_s: float
    """How long it waits for the camera's first frame (the robots start after it)."""
    host: str
    transport: TransportEntry
    domain_id: int | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()

    def to_json(self) -> str:
        """The spec as one JSON object (the bridge process's argument)."""
        return json.dumps(
            {
                "topic": self.topic,
                "min_rate_hz": self.min_rate_hz,
                "max_rate_hz": self.max_rate_hz,
                "msg_type": self.msg_type,
                "wait_s": self.wait_s,
                "host": self.host,
                "transport": self.transport.name,
                "domain_id": self.domain_id,
                "connect": list(self.connect),
                "listen": list(self.listen),
            }
        )

    @classmethod
    def from_json(cls, text: str) -> BridgeSpec:
        """The spec ``to_json`` wrote; ``DbmlError`` naming a field it cannot take."""
        document: dict[str, Any] = json.loads(text)
        if not isinstance(document, dict):
            raise DbmlError(f"bridge spec={text[:80]!r} is not a JSON object")
        document["transport"] = transport_entry(str(document.get("transport")))
        document["connect"] = tuple(document.get("connect", ()))
        document["listen"] = tuple(document.get("listen", ()))
        try:
            return cls(**document)
        except TypeError as err:
            raise DbmlError(f"bridge spec: {err}") from None

    @property
    def channel(self) -> BridgeChannel:
        """The bridged channel, as ``dbml bridge TOPIC --min-hz --max-hz --type`` gives it."""
        return BridgeChannel(self.topic, self.min_rate_hz, self.max_rate_hz, None, self.msg_type)


class _Stats(Protocol):
    topic: str
    published: int
    dropped: int
    max_ms: float | None
    p99_ms: float | None


@runtime_checkable
class _TimedPublisher(Protocol):
    """A middleware publisher that times its calls (rclpy's)."""

    def stats(self) -> _Stats: ...


def timing_of(bridge: Bridge) -> PublishTiming | None:
    """How ``bridge``'s publishes went, if its middleware's publisher says (None otherwise)."""
    managed = bridge.publisher
    publisher = None if managed is None else managed.optimized_publisher
    if not isinstance(publisher, _TimedPublisher):
        return None
    stats = publisher.stats()
    return PublishTiming(stats.topic, stats.published, stats.dropped, stats.max_ms, stats.p99_ms)


def serve(
    spec: BridgeSpec,
    stop: threading.Event,
    *,
    lines: Iterable[str] | None = None,
    emit: Emit = emit_json,
) -> int:
    """Bridge ``spec``'s channel until ``stop`` (or ``stop``/EOF on ``lines``); its exit code."""
    transport = open_transport(
        spec.transport.name,
        host=spec.host,
        connect=spec.connect,
        listen=spec.listen,
        domain_id=spec.domain_id,
        follow_all_params=False,  # like a publisher: it needs its allocations only
    )
    timings: list[PublishTiming] = []

    def closed(bridge: Bridge) -> None:
        timing = timing_of(bridge)
        if timing is not None:
            timings.append(timing)

    try:
        Control(stop, lines=lines, name="bridge-control").start()
        code = run_bridge(
            transport,
            [spec.channel],
            stop=stop,
            wait_s=spec.wait_s,
            typed_topics=spec.transport.typed_topics,
            closed=closed,
        )
    finally:
        transport.close()
        emit(PublishReport(tuple(timings)).encode())
    return code
