"""A managed camera: the rate and the detail of its frames chosen together (quality as a knob).

A ``ManagedCamera`` is a ``ManagedPublisher`` whose managed copy is
``[topic]/optimized/compressed``: a ``sensor_msgs/msg/CompressedImage`` of each frame that goes,
encoded at the rung the optimizer pushed (``[topic]/dbm/encoding/current_value``, acknowledged
in ``encoding/applied_value``), with the ``format`` string compressed_image_transport writes.
Local subscribers keep the full ``sensor_msgs/msg/Image`` on ``[topic]``.

Its ladder is measured on its own frames (``dbml.media.ladder``): the first frame's at once, so
the optimizer can allocate before anything is sent, then one frame every ``probe_interval_s``
on a background thread that takes at most ``PROBE_CPU_SHARE`` of a core (it waits longer when
a probe took long) and holds one frame (the newest offered). The bytes actually sent correct
the ladder: when the last ``SENT_WINDOW`` frames ran above what the ladder said of their rung
(a scene busier than the probed frame), every rung's bytes are scaled up by that much, so the
budget holds on the wire as the scene changes. The ladder is written to ``[topic]/dbm/ladder``
when a rung's bytes rose by ``LADDER_RISE`` (at once) or fell by ``SIZE_CHANGE`` (once
``FALL_S`` after the measurement that says so, with the frames sent since). Until the optimizer
allocates on it, frames are held to the bytes their rung was counted at (the pushed label's,
``ByteWindow``): one that would take a 1-s window past them is dropped.

With ``ladder=False`` it publishes no ladder: the optimizer allocates its rate alone, on frames
at the one ``default_encoding`` (the rate-only baseline, on the same frames).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace

from dbml.core.errors import SpecError
from dbml.core.ladder import Preference, Rung
from dbml.media.images import Frame, decode_image, encode_compressed, encode_image
from dbml.media.jpeg import compressed_format, encode_jpeg
from dbml.media.ladder import measure_ladder
from dbml.protocol import names
from dbml.protocol.ladders import Encoding, encode_rungs
from dbml.runtime.publisher import FAILSAFE_PERIODS, ManagedPublisher
from dbml.runtime.rate import ByteWindow
from dbml.runtime.size import SIZE_CHANGE
from dbml.transports.base import Transport, Variant
from dbml.transports.overflow import LogOnce
from dbml.transports.worker import PeriodicWorker

__all__ = [
    "DEFAULT_ENCODING",
    "FALL_S",
    "LADDER_RISE",
    "PROBE_CPU_SHARE",
    "PROBE_INTERVAL_S",
    "SENT_WINDOW",
    "ManagedCamera",
]

log = logging.getLogger("dbml.camera")

DEFAULT_ENCODING: Encoding = (1.0, 80)
"""The rung a camera sends before the optimizer chose one (and always, without a ladder)."""
PROBE_INTERVAL_S = 5.0
"""How often the ladder is measured again on a new frame."""
PROBE_CPU_SHARE = 0.05
"""The most of a core the probe takes: after a probe of ``t`` seconds it waits at least
``t / PROBE_CPU_SHARE``. A 640x480 probe of 21 rungs takes about 80 ms here: 1.6 % at 5 s."""
LADDER_RISE = 0.02
"""A rung's bytes risen by this much are written at once (fallen: by ``SIZE_CHANGE``): the
allocation fills the budget, so a ladder that says too little overspends it by as much."""
_FACTOR_STEP = 0.005
"""A correction within this of the last one's makes no new ladder (a quarter of
``LADDER_RISE``, so a rise is still seen): each frame would otherwise build 21 rungs."""
SENT_WINDOW = 32
"""Frames whose bytes against the ladder's correct it (two seconds at 16 Hz)."""
FALL_S = 0.5
"""How long after a probe its measurement may lower the ladder written, corrected by the frames
sent since (eight at 16 Hz); until then each rung is written at the larger of its two words. A
probe measures one frame, older than those sent after it: in a scene panning into detail the
frames ran 16 % above the last measurement when the next one reset the correction, the ladder
fell for one round and rose again with the next frames, and the allocation flipped a 16-Hz
camera to q90 at 14.5 Hz and back within 0.1 s, a frame lost on the way (``dbml demo teleop
--frames photos``: in 4 of 34 runs a step's rate 5 % short of its allocation). A rise is
written at once: it is what keeps the budget."""


class ManagedCamera:
    """Publish a camera's frames: full on ``[topic]``, JPEG at the allocated rung and rate.

    ``publish_frame(frame)`` takes pixels in hand (a camera driver in this process);
    ``publish(image)`` a serialised ``sensor_msgs/msg/Image`` (a bridge's driver). A message
    that is not an rgb8, bgr8 or mono8 image is dropped and reported once (a one-line error
    naming it), never raised on the caller's thread.
    """

    def __init__(
        self,
        transport: Transport,
        topic: str,
        *,
        min_rate_hz: float,
        max_rate_hz: float,
        priority: float | None = None,
        preference: Preference | None = None,
        min_quality: float | None = None,
        ladder: bool = True,
        default_encoding: Encoding = DEFAULT_ENCODING,
        probe_interval_s: float = PROBE_INTERVAL_S,
        republish_full: bool = True,
        failsafe_periods: float = FAILSAFE_PERIODS,
    ) -> None:
        scale, quality = default_encoding
        if quality is None:
            raise SpecError(f"default_encoding={default_encoding!r}: a camera sends JPEG")
        self.topic = topic
        self._transport = transport
        self._laddered = ladder
        self._default = default_encoding
        self._default_jpeg = (scale, quality)
        self.publisher = ManagedPublisher(
            transport,
            topic,
            min_rate_hz=min_rate_hz,
            max_rate_hz=max_rate_hz,
            priority=priority,
            republish_full=republish_full,
            failsafe_periods=failsafe_periods,
            variant=Variant.COMPRESSED,
            encoding=default_encoding,
        )
        params = transport.params
        if preference is not None:
            params.set(names.preference(topic), Preference(preference).value)
        if min_quality is not None:
            params.set(names.min_quality(topic), float(min_quality))
        self._lock = threading.Lock()
        self._offered: Frame | None = None
        """The newest frame offered to the probe (one at most: the probe's memory bound)."""
        self._measured: tuple[Rung, ...] | None = None
        self._written: tuple[Rung, ...] | None = None
        self._factor = 1.0
        """The correction the ladder last written was made with."""
        self._measured_at = -math.inf
        """When the ladder was last measured (the transport's clock): a fall waits ``FALL_S``."""
        self._falls = True
        """Whether the ladder last written could fall (``FALL_S`` had passed)."""
        self._last_bytes: int | None = None
        """The last message's size (what the optimizer is told without a ladder)."""
        self._sent: collections.deque[float] = collections.deque(maxlen=SENT_WINDOW)
        """Recent frames' bytes over what the ladder said of their rung."""
        self._bad = LogOnce(log)
        self._probe_interval_s = probe_interval_s
        self._probe = PeriodicWorker(
            self._probe_once,
            interval_s=self._probe_wait,
            name=f"dbml-ladder{topic}",
            log=log,
        )
        self._probe_took_s = 0.0
        self._window = ByteWindow()
        """Frames held to the bytes the allocation counted them at (a busier scene's lag)."""
        self.rate = self.publisher.rate

    # -- publishing ---------------------------------------------------------------------------

    def publish(self, image: bytes) -> bool:
        """Publish a serialised ``sensor_msgs/msg/Image``; False if it did not go (or is bad)."""
        try:
            frame = decode_image(image)
        except SpecError as err:
            self._bad.warning("image", "%s: %s (dropped)", self.topic, err)
            return False
        return self.publish_frame(frame, image=image)

    def publish_frame(self, frame: Frame, *, image: bytes | None = None) -> bool:
        """Publish one frame; True if it went to ``[topic]/optimized/compressed``."""
        if self._measured is None:
            self._measure(frame)  # at once: the optimizer needs a size and a ladder to admit us
            self._probe.start()
        else:
            with self._lock:
                self._offered = frame
        payload: bytes | Callable[[], bytes] = (
            image
            if image is not None
            else (
                lambda: encode_image(frame)  # made only when a local subscriber takes it
            )
        )
        pushed = self.publisher.rung  # read once: the rung and the bytes it was counted at
        (scale, quality), counted = pushed or (self._default_jpeg, None)
        if quality is None:  # a raw rung: a camera's ladder has none; keep to JPEG
            (scale, quality), counted = self._default_jpeg, None
        encoding: Encoding = (scale, quality)
        sent: list[int] = []

        def compress() -> bytes:
            data = encode_jpeg(frame.pixels, encoding=frame.encoding, quality=quality, scale=scale)
            sent.append(len(data))
            message = encode_compressed(frame, data, format=compressed_format(frame.encoding))
            self._last_bytes = len(message)
            return message

        windowed: list[bool] = []

        def admit(_message: bytes, rate_hz: float) -> bool:  # the JPEG against its count
            if counted is None or not sent:
                return True
            fits = self._window.admit(self._transport.now(), sent[0], counted, rate_hz=rate_hz)
            windowed.append(fits)
            return fits

        went = self.publisher.publish(
            payload, encode=compress, size_bytes=self._size_bytes(), admit=admit
        )
        if went and windowed:  # the byte window counts it from when it left
            self._window.left(self._transport.now())
        if sent:
            self._account(encoding, sent[0])
        elif self._laddered and not self._falls:  # no frame to correct it: a fall still comes
            self._write_ladder()
        return went

    def _size_bytes(self) -> int:
        """The size the optimizer is told.

        Without a ladder, the last message's (the paper's publisher: what it sends). With one,
        the default rung's by the (corrected) ladder, not the last message's: the rung changes
        with the allocation, and a size that followed it would move the priorities' weights
        (eq. 2) and re-allocate for nothing.
        """
        if not self._laddered and self._last_bytes is not None:
            return self._last_bytes
        rungs = self._written or self._measured or ()
        for rung in rungs:
            if (rung.scale, rung.jpeg_quality) == self._default:
                return round(rung.size_bytes)
        return 1

    def _account(self, encoding: Encoding, size_bytes: int) -> None:
        """A frame's bytes against the ladder's word for its rung; correct the ladder if over."""
        with self._lock:
            for rung in self._measured or ():
                if (rung.scale, rung.jpeg_quality) == encoding:
                    self._sent.append(size_bytes / rung.size_bytes)
                    break
        if self._laddered:
            self._write_ladder()

    # -- the ladder ---------------------------------------------------------------------------

    def _measure(self, frame: Frame) -> None:
        start = time.perf_counter()
        rungs = measure_ladder(frame.pixels, encoding=frame.encoding)
        self._probe_took_s = time.perf_counter() - start
        with self._lock:
            self._measured = rungs
            self._measured_at = self._transport.now()
            self._sent.clear()  # what ran over the old measurement says nothing of this one
            self._factor = math.nan  # a new measurement: compared with what was written
            if not self._laddered:
                self._written = rungs  # the size told comes from it; nothing is published
        if self._laddered:
            self._write_ladder()

    def _write_ladder(self) -> None:
        """Write the corrected ladder if a rung moved (the module docstring; outside the lock)."""
        now = self._transport.now()
        with self._lock:
            measured, written = self._measured, self._written
            if measured is None:
                return
            factor = max((*self._sent, 1.0))  # how far recent frames ran above the ladder
            falls = now - self._measured_at >= FALL_S
            if (
                written is not None
                and falls == self._falls
                and abs(factor - self._factor) <= _FACTOR_STEP * self._factor
            ):
                return  # nothing moved since the last look (most frames): no rung is made
            self._factor, self._falls = factor, falls
            rungs = tuple(
                Rung(r.size_bytes * factor, r.quality, r.scale, r.jpeg_quality) for r in measured
            )
            if written is not None and not falls:  # too soon after the probe for a fall
                rungs = tuple(
                    replace(new, size_bytes=max(new.size_bytes, old.size_bytes))
                    for new, old in zip(rungs, written, strict=True)
                )
            if written is not None and all(
                -SIZE_CHANGE * old.size_bytes
                <= new.size_bytes - old.size_bytes
                <= LADDER_RISE * old.size_bytes
                and abs(new.quality - old.quality) <= SIZE_CHANGE * max(old.quality, 1e-3)
                for new, old in zip(rungs, written, strict=True)
            ):
                return
            self._written = rungs
        self._transport.params.set(names.ladder(self.topic), encode_rungs(rungs))

    def _probe_wait(self) -> float:
        return max(self._probe_interval_s, self._probe_took_s / PROBE_CPU_SHARE)

    def _probe_once(self) -> None:
        with self._lock:
            frame, self._offered = self._offered, None
        if frame is not None:
            self._measure(frame)

    @property
    def probe_seconds(self) -> float:
        """How long the last probe of the ladder took (its thread's wall time)."""
        return self._probe_took_s

    @property
    def ladder(self) -> tuple[Rung, ...] | None:
        """The ladder as last written (or measured, without ``ladder``)."""
        return self._written

    @property
    def refused_frames(self) -> int:
        """Frames the rate let through that went over the bytes they were counted at (dropped)."""
        return self._window.refused

    @property
    def alive(self) -> bool:
        """False once the probe's thread died."""
        return self._probe.alive

    def current_rate_hz(self) -> float:
        """The rate in force."""
        return self.publisher.current_rate_hz()

    def close(self) -> None:
        """Stop the probe and close the publisher."""
        self._probe.stop()
        self.publisher.close()
