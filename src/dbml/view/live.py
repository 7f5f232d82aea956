"""The live view: what a process knows of dbml, as Foxglove channels, while it runs.

A ``LiveView`` follows a transport's parameters and graph and writes to a ``Sink`` (a Foxglove
server, an MCAP file) on a thread of its own:

- ``/dbm/allocation``: each round the optimizer reports (``RoundReport``, heard through a
  ``RoundFollower``), as it reported it, and the allocated rate of every channel on
  ``[topic]/dbm/frequency/current_value``; nothing while no optimizer reports;
- ``/dbm/budget`` when it changes and at least every ``BUDGET_INTERVAL_S``;
- ``/dbm/log``: status changes, and values refused (from the network or from a viewer);
- where the process receives frames (``frame``), each one as an image on ``[topic]/optimized``
  and the delivered rate on ``[topic]/dbm/frequency/delivered_value``.

Nothing here runs on a middleware callback but a queue append: the optimizer's reaction never
waits for the view. What the view is fed from the network is bounded (the frames queued, the
channels metered); frames past the queue are dropped, counted and said once per stall.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from dbml.core.errors import SpecError
from dbml.core.extras import require
from dbml.protocol import names
from dbml.protocol.messages import EstimatorState, RoundReport
from dbml.protocol.schema import ParamValue, Writer
from dbml.runtime.graph import published_topics
from dbml.runtime.params import ParamView
from dbml.runtime.rounds import RoundFollower
from dbml.transports.base import COMPRESSED_TYPE, Handle, Transport, Variant
from dbml.transports.overflow import Overflow
from dbml.transports.worker import PeriodicWorker
from dbml.view import frames
from dbml.view.frames import LogLevel
from dbml.view.target import ViewEndpoint, ViewTarget

__all__ = [
    "BUDGET_INTERVAL_S",
    "DELIVERED_WINDOW_S",
    "MAX_ARRIVALS",
    "MAX_METERED",
    "MAX_QUEUED_FRAMES",
    "VIEW_INTERVAL_S",
    "LiveView",
    "ViewCost",
    "ViewSettings",
    "ViewSink",
    "open_view",
]

log = logging.getLogger("dbml.view")

VIEW_INTERVAL_S = 0.25
"""How often the view looks, when no round or frame wakes it: the delivered rates' step."""
BUDGET_INTERVAL_S = 1.0
"""``/dbm/budget`` is written at least this often, so a plot of it has points."""
DELIVERED_WINDOW_S = 1.0
"""The delivered rate is the frames of the last second."""
MAX_QUEUED_FRAMES = 64
"""Frames waiting for the view's thread; past it the oldest is dropped (the view lags)."""
MAX_METERED = 4096
"""Channels whose arrivals the view counts."""
MAX_ARRIVALS = 1024
"""Arrivals kept per channel for its delivered rate: more than a second of any camera."""
_NS = 1_000_000_000
_EARLY = 0.9
"""A periodic wake counts as the interval's end a little early: the worker's clock is another."""


class ViewSettings:
    """The Parameters capability's side: the operator's parameters, as ``dbml budget|priority``.

    ``current`` is the value in force of every settable name of dbml and of the live channels;
    ``set`` checks a value by the schema's rule (``frames.check_setting``) and writes it to the
    store from this process, as ``dbml budget`` and ``dbml priority`` do; the store never
    blocks its caller. A refused value writes nothing. ``writers`` are the roles of the serving
    process: a value the schema gives none of them is refused here, since its own store would
    take it whatever a secure fleet's rules let through on the wire.
    """

    def __init__(
        self, transport: Transport, view: ParamView, *, writers: frozenset[Writer]
    ) -> None:
        self._transport = transport
        self._view = view
        self.writers = writers

    def topics(self) -> list[str]:
        """The live channels: published, with declared bounds."""
        published = published_topics(self._transport.graph.entries())
        return sorted(t for t, c in self._view.channels(published).items() if c.bounded)

    def current(
        self,
        values: Mapping[str, ParamValue] | None = None,
        topics: Sequence[str] | None = None,
    ) -> Mapping[str, ParamValue]:
        """Every settable name and its value in force (of ``values`` and ``topics`` if given)."""
        values = self._view.values() if values is None else values
        topics = self.topics() if topics is None else topics
        return {name: values.get(name) for name in frames.settable_names(topics)}

    def set(self, name: str, value: object) -> ParamValue:
        """Write ``value`` once it passed; ``ParamError`` naming both if it did not."""
        checked = frames.check_setting(name, value, self.topics(), writers=self.writers)
        self._transport.params.set(name, checked)
        log.info("%s set to %s from the view", name, checked)
        return checked


@dataclass(frozen=True, slots=True)
class ViewCost:
    """The view's time per look: allocation, budget, log, delivered rates, parameters."""

    looks: int
    mean_ms: float
    max_ms: float


@dataclass(frozen=True, slots=True)
class _Frame:
    topic: str
    payload: bytes
    time_ns: int
    compressed: bool = False
    """A camera's ``CompressedImage`` in CDR already: logged as it came."""


class _Images:
    """Frames as ROS 2 ``sensor_msgs/msg/Image`` in CDR (rosbags' typestore, no ROS 2)."""

    name = frames.IMAGE_TYPE
    compressed_name = COMPRESSED_TYPE

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self._store = get_typestore(Stores.ROS2_JAZZY)
        self.definition = self._store.generate_msgdef(self.name, ros_version=2)[0]
        self.compressed_definition = self._store.generate_msgdef(
            self.compressed_name, ros_version=2
        )[0]

    def encode(self, frame: _Frame) -> bytes:
        import numpy as np

        types = self._store.types
        height, width = frames.image_shape(len(frame.payload))
        stamp = types["builtin_interfaces/msg/Time"](
            sec=frame.time_ns // _NS, nanosec=frame.time_ns % _NS
        )
        image = types[self.name](
            header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame.topic),
            height=height,
            width=width,
            encoding="mono8",
            is_bigendian=0,
            step=width,
            data=np.frombuffer(frame.payload, dtype=np.uint8),
        )
        return bytes(self._store.serialize_cdr(image, self.name))


class ViewSink(Protocol):
    """Where a ``LiveView`` writes: ``dbml.view.sink.Sink`` (foxglove-sdk), or a test's double."""

    @property
    def address(self) -> ViewEndpoint | None:
        """Where its server listens, if it has one."""

    def log_json(
        self, topic: str, schema: Mapping[str, Any], message: Mapping[str, Any], *, time_ns: int
    ) -> None:
        """A JSON message (its channel advertised with ``schema`` the first time)."""

    def log_cdr(
        self, topic: str, schema_name: str, definition: str, payload: bytes, *, time_ns: int
    ) -> None:
        """A ROS 2 message in CDR."""

    def log_text(self, level: LogLevel, message: str, *, time_ns: int) -> None:
        """A line on ``/dbm/log``."""

    def publish_parameters(self, values: Mapping[str, ParamValue]) -> None:
        """The settable values that changed."""

    def close(self) -> None:
        """The end: the server stops, the recording is finished."""


class LiveView:
    """Follow ``transport`` and write what it shows to ``sink``; ``start()`` runs it.

    ``clock`` gives the messages' log time (ns, wall clock: a recording lines up with other
    ones); ``monotonic`` (ns) times the looks and the delivered rate's window, which a step of
    the wall clock must not stall.
    """

    def __init__(
        self,
        transport: Transport,
        sink: ViewSink,
        *,
        settings: ViewSettings,
        interval_s: float = VIEW_INTERVAL_S,
        clock: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._transport = transport
        self._sink = sink
        self._clock = clock
        self._monotonic = monotonic
        self._view = ParamView.of(transport.params)
        self.settings = settings
        self._lock = threading.Lock()
        self._queued: deque[_Frame] = deque()
        self._dropped = Overflow(
            "frames queued for the view", MAX_QUEUED_FRAMES, log=log, evicts=True
        )
        self._arrivals: dict[str, deque[int]] = {}
        self._metered_full = Overflow("channels metered by the view", MAX_METERED, log=log)
        self._images: _Images | None = None
        self._shown: RoundReport | None = None
        """The last round report written: each one is written once."""
        self._last_budget: tuple[frames.BudgetFrame, int] | None = None
        self._status: tuple[ParamValue, ParamValue] = (None, None)
        self._problems: frozenset[str] = frozenset()
        self._settable: Mapping[str, ParamValue] = {}
        self._looks = 0
        self._look_s = 0.0
        self._look_max_s = 0.0
        """What looking cost this process (the view's price, ``bench/reaction.py`` reads it)."""
        self._round_due = threading.Event()
        self._interval_ns = int(interval_s * _NS * _EARLY)
        self._looked_ns = -self._interval_ns
        """When the view last looked at the parameters (frames alone do not make it look)."""
        self._worker = PeriodicWorker(
            self._tick, interval_s=interval_s, name="dbml-view", log=log, immediate=True
        )
        self._rounds = RoundFollower(transport)
        self._handles: list[Handle] = [self._rounds.watch(self._on_round)]

    # -- fed from callbacks: never block ------------------------------------------------------

    def _on_round(self, _report: RoundReport) -> None:
        self._round_due.set()
        self._worker.wake()

    def frame(self, topic: str, payload: bytes, *, compressed: bool = False) -> None:
        """A frame this process received on ``topic``: an image and a delivered-rate count.

        ``compressed``: a camera's ``sensor_msgs/msg/CompressedImage`` (its JPEG copy), shown
        as it came; else the frame's bytes, shown as a grey image.
        """
        now, tick = self._clock(), self._monotonic()
        with self._lock:
            if len(self._queued) >= MAX_QUEUED_FRAMES:
                self._queued.popleft()
                self._dropped.refuse()
            self._queued.append(_Frame(topic, payload, now, compressed))
            arrivals = self._arrivals.get(topic)
            if arrivals is None:
                if len(self._arrivals) >= MAX_METERED:
                    self._metered_full.refuse()
                    return
                arrivals = self._arrivals[topic] = deque(maxlen=MAX_ARRIVALS)
            arrivals.append(tick)
        self._worker.wake()

    # -- the view's thread --------------------------------------------------------------------

    def _tick(self) -> None:
        """Frames at every wake; the rest after a round, or once an interval passed."""
        self._frames()
        now, tick = self._clock(), self._monotonic()
        if not self._round_due.is_set() and tick - self._looked_ns < self._interval_ns:
            return
        self._round_due.clear()
        self._looked_ns = tick
        started = time.perf_counter()
        values = self._view.values()
        self._allocation(self._rounds.latest(), now)
        self._budget(values, now, tick)
        self._log_changes(values, now)
        self._delivered(now, tick)
        self._parameters(values, self.settings.topics())
        spent = time.perf_counter() - started
        self._looks += 1
        self._look_s += spent
        self._look_max_s = max(self._look_max_s, spent)

    def _allocation(self, report: RoundReport | None, now: int) -> None:
        """The optimizer's newest round, once: between rounds nothing new was decided."""
        if report is None or report is self._shown:
            return
        self._shown = report
        self._sink.log_json(
            frames.ALLOCATION_TOPIC, frames.ALLOCATION_SCHEMA, report.as_json(), time_ns=now
        )
        for channel in report.channels:
            if channel.rate_hz is not None:
                self._sink.log_json(
                    frames.frequency_topic(channel.topic),
                    frames.FREQUENCY_SCHEMA,
                    {"data": channel.rate_hz},
                    time_ns=now,
                )

    def _budget(self, values: Mapping[str, ParamValue], now: int, tick: int) -> None:
        budget = frames.budget_frame(values, estimator_phase=_phase(values))
        last = self._last_budget
        if last is not None and last[0] == budget and tick - last[1] < BUDGET_INTERVAL_S * _NS:
            return
        self._last_budget = (budget, tick)
        self._sink.log_json(
            frames.BUDGET_TOPIC, frames.BUDGET_SCHEMA, budget.as_json(), time_ns=now
        )

    def _log_changes(self, values: Mapping[str, ParamValue], now: int) -> None:
        status = (values.get(names.STATUS), values.get(names.STATUS_MESSAGE))
        if status != self._status and status[0] is not None:
            level = LogLevel.WARNING if status[0] == "infeasible" else LogLevel.INFO
            self._sink.log_text(level, f"{status[0]}: {status[1]}", time_ns=now)
        self._status = status
        problems = frozenset(self._view.problems())
        for problem in sorted(problems - self._problems):
            self._sink.log_text(LogLevel.WARNING, f"ignored: {problem}", time_ns=now)
        self._problems = problems

    def _frames(self) -> None:
        with self._lock:
            queued, self._queued = self._queued, deque()
            self._dropped.room(0)
        if not queued:
            return
        if self._images is None:
            self._images = _Images()
        images = self._images
        for frame in queued:
            if frame.compressed:
                self._sink.log_cdr(
                    Variant.COMPRESSED.key(frame.topic),
                    images.compressed_name,
                    images.compressed_definition,
                    frame.payload,
                    time_ns=frame.time_ns,
                )
                continue
            self._sink.log_cdr(
                frames.image_topic(frame.topic),
                images.name,
                images.definition,
                images.encode(frame),
                time_ns=frame.time_ns,
            )

    def _delivered(self, now: int, tick: int) -> None:
        since = tick - int(DELIVERED_WINDOW_S * _NS)
        with self._lock:
            counts = {}
            for topic, arrivals in self._arrivals.items():
                while arrivals and arrivals[0] <= since:
                    arrivals.popleft()
                counts[topic] = len(arrivals)
        for topic, count in sorted(counts.items()):
            self._sink.log_json(
                frames.delivered_topic(topic),
                frames.FREQUENCY_SCHEMA,
                {"data": count / DELIVERED_WINDOW_S},
                time_ns=now,
            )

    def _parameters(self, values: Mapping[str, ParamValue], topics: Sequence[str]) -> None:
        current = dict(self.settings.current(values, topics))
        changed = {n: v for n, v in current.items() if self._settable.get(n) != v}
        self._settable = current
        self._sink.publish_parameters(changed)

    # -- life ---------------------------------------------------------------------------------

    @property
    def endpoint(self) -> ViewEndpoint | None:
        """Where the Foxglove server listens; None without one."""
        return self._sink.address

    @property
    def alive(self) -> bool:
        """False once the view's thread died."""
        return self._worker.alive

    def start(self) -> LiveView:
        """Run the view's thread."""
        self._worker.start()
        return self

    def close(self) -> None:
        """Stop following, write what is queued, and close the sink (the recording's end)."""
        for handle in self._handles:
            handle.close()
        self._handles.clear()
        self._rounds.close()
        self._worker.stop()
        try:
            self._round_due.set()
            self._tick()  # the last round and frames make it into the recording
        except Exception:
            log.exception("the view's last write failed")
        self._sink.close()
        cost = self.cost
        if cost.looks:
            log.info(
                "live view: %d looks, %.3f ms mean, %.3f ms max per look",
                cost.looks,
                cost.mean_ms,
                cost.max_ms,
            )

    @property
    def cost(self) -> ViewCost:
        """What looking (after a round, or an interval) cost this process so far."""
        looks = self._looks
        return ViewCost(looks, self._look_s / looks * 1e3 if looks else 0.0, self._look_max_s * 1e3)


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _phase(values: Mapping[str, ParamValue]) -> str | None:
    state = values.get(names.ESTIMATOR_STATE)
    if not isinstance(state, str):
        return None
    try:
        return EstimatorState.decode(state).phase.value
    except SpecError:
        return None


def open_view(transport: Transport, target: ViewTarget, *, writers: frozenset[Writer]) -> LiveView:
    """A started ``LiveView`` of ``transport`` to a Foxglove server and/or an MCAP file.

    ``writers``: the roles of this process (what a viewer may set through it). Needs the
    ``viz`` extra (foxglove-sdk; rosbags for the images).
    """
    require("foxglove", extra="viz", what="--foxglove and --record", package="foxglove-sdk")
    require("rosbags", extra="viz", what="--foxglove and --record")
    from dbml.view.sink import Sink

    endpoint = target.endpoint
    if endpoint is not None and not _loopback(endpoint.host):
        log.warning(
            "the live view on %s has no authentication: whoever reaches it sees the allocation "
            "and the frames, and may set the budget and priorities",
            endpoint,
        )
    settings = ViewSettings(transport, ParamView.of(transport.params), writers=writers)
    sink = Sink(
        endpoint=target.endpoint,
        record=target.record,
        settings=None if target.endpoint is None else settings,
    )
    return LiveView(transport, sink, settings=settings).start()
