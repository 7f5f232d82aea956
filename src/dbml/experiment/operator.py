"""The operator of the teleoperation experiment: what arrived, and the parameters in force.

Every ``TICK_S`` it reports the frames that arrived (robot, sequence number, send and arrival
time, size, the rate the publisher applied) and the parameters in force (allocation, budget,
estimate, the estimator's state, the variant each subscriber takes): an ``OperatorReport``.
``operator_tick`` builds that report for every operator, dbml's own (here) and the plain ROS 2
ones (``peers``), so the runner and the analysis read one format.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from dbml.core.errors import SpecError, TransportError
from dbml.experiment.analysis import Arrival, Tick
from dbml.experiment.report import OperatorReport
from dbml.experiment.spec import TAIL_S, TICK_S, URGENT_STREAMS, Frames, RoleSpec
from dbml.harness.child import Emit
from dbml.protocol import names
from dbml.protocol.ladders import encoding_label
from dbml.protocol.messages import EstimatorState
from dbml.protocol.metadata import MessageMeta
from dbml.runtime.params import ParamView
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.serve import Lifetime
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.scenarios.fleet import fleet_cameras
from dbml.scenarios.teleop import ROBOTS, RobotCamera
from dbml.transports.base import Handle, Sample, Transport, Variant
from dbml.transports.overflow import LogOnce
from dbml.transports.worker import BackgroundThread
from dbml.view.live import LiveView

__all__ = ["operator_tick", "run_operator"]

log = logging.getLogger("dbml.experiment")


def operator_tick(
    view: ParamView,
    frames: Sequence[Arrival],
    variants: Sequence[str],
    *,
    cameras: Sequence[RobotCamera] = ROBOTS,
) -> OperatorReport:
    """The operator's report: ``frames`` that arrived and the parameters in force now.

    One function for every operator (dbml's own and the plain ROS 2 one of ``ros2peers``), so
    the runner and the analysis read one format; ``cameras`` are the fleet's, in robot order.
    """
    dbm = view.dbm()
    channels = [view.channel(c.topic) for c in cameras]
    tick = Tick(
        t_s=time.time(),
        allocated_hz=tuple(c.current_rate_hz for c in channels),
        budget_mbit=dbm.budget_mbit,
        estimate_mbit=dbm.estimate_mbit,
        estimator=_estimator_state(view.get(names.ESTIMATOR_STATE)),
        variants=tuple(variants),
        encodings=tuple(
            None if c.encoding is None or c.rungs is None else encoding_label(*c.encoding)
            for c in channels
        ),
    )
    return OperatorReport(tick, tuple(frames))


def _estimator_state(value: object) -> EstimatorState | None:
    """The estimator's state in force; None when none runs or a peer wrote a malformed one."""
    if not isinstance(value, str):
        return None
    try:
        return EstimatorState.decode(value)
    except SpecError as err:
        log.debug("%s", err)
        return None


SCORE_QUEUE = 64
"""Frames waiting for their SSIM at most; past it a frame is counted, not scored (said once)."""
_SCORE_JOIN_S = 5.0


class _Scorer:
    """Decodes every camera JPEG that arrives and scores it against the frame that was sent.

    Off the middleware's thread, on its own (a bounded queue between): the operator remakes
    the sent frame from the panning camera's position in the message's ``frame_id`` and
    scores the JPEG as the ladder does (``dbml.media.ladder.score``). A message that does not
    decode is counted unscored and said once, by robot.
    """

    def __init__(self, cameras: Sequence[RobotCamera], record: Callable[[Arrival], None]) -> None:
        from dbml.media.photos import PanCamera  # the quality extra's, imported on use

        self._eyes = [PanCamera(c.width, c.height) for c in cameras]
        self._record = record
        self._queue: queue.Queue[tuple[Arrival, bytes] | None] = queue.Queue(SCORE_QUEUE)
        self._bad = LogOnce(log)
        self._closed = False
        self._thread = BackgroundThread(self._run, name="operator-ssim", log=log).start()

    def offer(self, row: Arrival, payload: bytes) -> None:
        """Score ``payload`` and record ``row`` with it (without it when the queue is full)."""
        try:
            self._queue.put_nowait((row, payload))
        except queue.Full:
            self._bad.warning(
                "full", "more than %d frames waiting for SSIM: some unscored", SCORE_QUEUE
            )
            self._record(row)

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            row, payload = item
            self._record(replace(row, ssim=self._score(row.robot, payload)))

    def _score(self, index: int, payload: bytes) -> float | None:
        from dbml.media.images import decode_compressed
        from dbml.media.ladder import reference, score
        from dbml.media.photos import frame_position

        if index >= len(self._eyes):
            return None
        eye = self._eyes[index]
        try:
            message = decode_compressed(payload)
            x = frame_position(message.frame_id)
            if x is None:
                raise SpecError(f"frame_id={message.frame_id!r} is not a panning camera's")
            sent = reference(eye.window(x), encoding="rgb8")
            return score(sent, message.data, shape=(eye.height, eye.width))
        except SpecError as err:
            self._bad.warning(f"robot {index}", "robot %d: %s (not scored)", index, err)
            return None

    def close(self) -> None:
        """Score what is queued, then stop (bounded; a second call returns at once)."""
        if self._closed:
            return
        self._closed = True
        try:  # bounded: a scorer that died takes nothing off the queue
            self._queue.put(None, timeout=_SCORE_JOIN_S)
        except queue.Full:
            return
        self._thread.join(_SCORE_JOIN_S)


def run_operator(
    transport: Transport,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    emit: Emit,
    live: LiveView | None = None,
) -> None:
    """The operator from ``t0`` to its end: a report every ``TICK_S``, then ``done``.

    Its frames come through managed subscribers (plain ones when unmanaged), shown in ``live``
    if given; a run that lost a thread (``life``) is not done, so the runner fails it.
    """
    lock = threading.Lock()
    rows: list[Arrival] = []
    cameras = fleet_cameras(spec.robots)

    def receiver(index: int) -> Callable[[Sample], None]:
        shown = cameras[index].topic if live is not None and index < len(cameras) else None

        def on_sample(sample: Sample) -> None:
            arrival_s = time.time()
            if shown is not None and live is not None:
                live.frame(shown, sample.payload, compressed=photos)
            try:
                meta: MessageMeta | None = MessageMeta.decode(sample.attachment)
            except TransportError:
                meta = None  # no metadata (ROS 1 messages carry none)
            row = Arrival(
                robot=index,
                seq=None if meta is None else meta.seq,
                sent_s=None if meta is None else meta.sent_ns / 1e9,
                arrival_s=arrival_s,
                size_bytes=len(sample.payload),
                rate_hz=None if meta is None or math.isnan(meta.rate_hz) else meta.rate_hz,
            )
            if scorer is not None and index < len(cameras):
                scorer.offer(row, sample.payload)
                return
            record(row)

        return on_sample

    def record(row: Arrival) -> None:
        with lock:
            rows.append(row)

    photos = spec.frames is Frames.PHOTOS
    scorer = _Scorer(cameras, record) if photos and spec.managed else None

    view = ParamView.of(transport.params)
    reporter = ReceptionReporter(transport).start() if spec.estimate else None
    handles: list[Handle] = []
    subscribers: list[ManagedSubscriber] = []
    for i, camera in enumerate(cameras):
        if spec.managed:
            subscriber = ManagedSubscriber(
                transport,
                camera.topic,
                receiver(i),
                reporter=reporter,
                remote=Variant.COMPRESSED if photos else Variant.OPTIMIZED,
            )
            subscribers.append(subscriber)
            handles.append(subscriber)
        else:
            handles.append(transport.subscribe(camera.topic, receiver(i), Variant.FULL))

    if spec.urgent_stream:
        for k, stream in enumerate(URGENT_STREAMS):
            handles.append(ManagedSubscriber(transport, stream.topic, receiver(len(cameras) + k)))
    unmanaged = [Variant.FULL.value for _ in cameras]

    def tick() -> dict[str, Any]:
        with lock:
            batch, rows[:] = list(rows), []
        variants = [s.variant.value for s in subscribers] or unmanaged
        return operator_tick(view, batch, variants, cameras=cameras).encode()

    try:
        while not life.over() and time.time() < t0 + spec.duration_s + TAIL_S:
            stop.wait(TICK_S)
            emit(tick())
        if scorer is not None:  # the frames still waiting for their SSIM, in a last report
            scorer.close()
            emit(tick())
        if not life.failed:  # a run that lost a thread is not done: the runner fails it
            emit({"type": "done"})
    finally:
        for handle in handles:
            handle.close()
        if reporter is not None:
            reporter.close()
        if scorer is not None:  # again, harmlessly, when the run ended on an error
            scorer.close()
