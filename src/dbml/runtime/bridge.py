"""The bridge: an existing topic under management without touching its publisher.

What the original package's ``dbm_bridge_node`` did for ROS 1, over any transport. The bridge
subscribes to the full-rate ``[topic]`` on its own host and republishes it on
``[topic]/optimized`` at the allocated rate, as a ``ManagedPublisher`` that leaves ``[topic]``
to its original publisher. It forwards the newest message only: one slot, no queue, each
message at most once, nothing when nothing new arrived. A queue would send stale frames late;
the newest value is what a remote operator needs. The size parameter follows what it forwards.
"""

from __future__ import annotations

import logging
import threading

from dbml.core.config import BridgeChannel
from dbml.core.errors import TransportError
from dbml.runtime.camera import ManagedCamera
from dbml.runtime.publisher import FAILSAFE_PERIODS, ManagedPublisher
from dbml.transports.base import Handle, Sample, Transport, Variant
from dbml.transports.worker import BackgroundThread

__all__ = ["FIRST_MESSAGE_TIMEOUT_S", "Bridge"]

log = logging.getLogger("dbml.bridge")

FIRST_MESSAGE_TIMEOUT_S = 10.0
"""How long ``start`` waits for the bridged topic's first message before giving up."""
_STOP_POLL_S = 0.1
"""How often the pacing thread, waiting for a message, looks whether it should stop."""
_RETRY_POLL_S = 0.05
"""The longest wait before a refused message is offered again: a new allocation applies."""
_JOIN_TIMEOUT_S = 5.0
"""How long ``close`` waits for the pacing thread before it says so (and waits for its send)."""


class _StoppedError(Exception):
    """The bridge is closing: leave the pacing loop from inside its sleep."""


class Bridge:
    """One bridged channel: subscribe to ``[topic]``, forward the newest to the optimized copy.

    The subscription callback only swaps the newest payload into one slot (under a lock held
    for the swap alone, never across a middleware call). ``start`` waits for the first message
    (which proves the topic exists and, over ROS 1, tells its type), declares the managed
    publisher and starts the pacing thread. ``forward()`` is one step of that thread, public so
    a test with a manual clock can drive it.
    """

    def __init__(
        self,
        transport: Transport,
        channel: BridgeChannel,
        *,
        failsafe_periods: float = FAILSAFE_PERIODS,
    ) -> None:
        self.channel = channel
        self._transport = transport
        self._failsafe_periods = failsafe_periods
        self._lock = threading.Lock()
        self._newest: bytes | None = None
        self._arrived = threading.Event()
        self._stop = threading.Event()
        self._sending = threading.Lock()
        """Held across one send, and by ``close`` around the publisher's close: never both."""
        self._publisher: ManagedPublisher | None = None
        self._camera: ManagedCamera | None = None
        """A laddered channel's camera (its publisher is ``_publisher``)."""
        self._thread: BackgroundThread | None = None
        self._paced = threading.Event()
        """Set when the pacing loop ended, by ``close`` or by dying."""
        self.forwarded = 0
        """Messages sent on ``[topic]/optimized`` so far."""
        if channel.msg_type is not None:
            for variant in (Variant.FULL, Variant.OPTIMIZED):  # a compressed copy is typed
                transport.set_topic_type(variant.key(channel.topic), channel.msg_type)
        self._subscription: Handle = transport.subscribe(channel.topic, self._on_sample)

    @property
    def topic(self) -> str:
        """The bridged topic (its managed copy is ``[topic]/optimized``)."""
        return self.channel.topic

    @property
    def publisher(self) -> ManagedPublisher | None:
        """The managed publisher of ``[topic]/optimized``, once started."""
        return self._publisher

    def _on_sample(self, sample: Sample) -> None:
        with self._lock:
            self._newest = sample.payload
            self._arrived.set()  # with the slot, so a taker never sees one without the other

    def _take(self) -> bytes | None:
        with self._lock:
            payload, self._newest = self._newest, None
            self._arrived.clear()
        return payload

    def _put_back(self, payload: bytes) -> None:
        """Keep a payload the limiter refused, unless a newer one arrived meanwhile."""
        with self._lock:
            if self._newest is None:
                self._newest = payload
                self._arrived.set()

    def wait_first(self, timeout_s: float) -> bool:
        """Whether a first message arrived (waiting up to ``timeout_s`` for it)."""
        return self._publisher is not None or self._arrived.wait(timeout_s)

    def start(self, *, timeout_s: float = FIRST_MESSAGE_TIMEOUT_S, pace: bool = True) -> Bridge:
        """Wait for the first message, declare the managed publisher, start pacing.

        Raises ``TransportError`` naming the topic when no message came within ``timeout_s``.
        ``pace=False`` leaves the pacing to the caller's ``forward()`` calls.
        """
        if not self._arrived.wait(timeout_s):
            raise TransportError(
                f"topic={self.topic!r}: no message within {timeout_s:g} s "
                "(is its publisher running on this host?)"
            )
        channel = self.channel
        if channel.ladder:  # a camera: its publisher is the one the bridge paces
            self._camera = ManagedCamera(
                self._transport,
                channel.topic,
                min_rate_hz=channel.min_rate_hz,
                max_rate_hz=channel.max_rate_hz,
                priority=channel.priority,
                failsafe_periods=self._failsafe_periods,
                republish_full=False,
            )
            self._publisher = self._camera.publisher
        else:
            self._publisher = ManagedPublisher(
                self._transport,
                channel.topic,
                min_rate_hz=channel.min_rate_hz,
                max_rate_hz=channel.max_rate_hz,
                priority=channel.priority,
                failsafe_periods=self._failsafe_periods,
                republish_full=False,
            )
        if pace:
            self._thread = BackgroundThread(
                self._run, name=f"dbml-bridge {channel.topic}", log=log
            ).start()
        return self

    @property
    def alive(self) -> bool:
        """Whether the pacing thread runs (False once it died or was stopped).

        A death is also counted by ``dbml.transports.worker``, so ``dbml bridge`` exits 1.
        """
        thread = self._thread
        return thread is not None and thread.alive and not self._paced.is_set()

    def forward(self) -> bool:
        """Send the newest unsent message if the rate allows; True if one went out.

        Nothing is sent once ``close`` began: its publisher is, or is about to be, closed.
        """
        publisher = self._publisher
        if publisher is None:
            return False
        payload = self._take()
        if payload is None:
            return False
        with self._sending:
            if self._stop.is_set():
                return False
            camera = self._camera
            sent = publisher.publish(payload) if camera is None else camera.publish(payload)
        if sent:
            self.forwarded += 1
            return True
        self._put_back(payload)
        return False

    def retry_s(self) -> float:
        """How long the pacing thread waits before offering a refused message again.

        Until the limiter has earned a frame, polled every ``_RETRY_POLL_S`` so a new
        allocation applies within that; a message refused for another reason (held through an
        outage, no first allocation yet) is offered again after ``_RETRY_POLL_S``.
        """
        publisher = self._publisher
        if publisher is None:
            return _RETRY_POLL_S
        wait_s = publisher.wait_s()
        return min(wait_s, _RETRY_POLL_S) if wait_s > 0 else _RETRY_POLL_S

    def _sleep(self, seconds: float) -> None:
        if self._stop.wait(seconds):
            raise _StoppedError

    def _run(self) -> None:
        """Forward each new message as soon as the limiter allows it.

        The publisher's limiter is the one schedule. A second one at the same rate (a pacer
        ticking once a period) drifts from it by how long each tick waits for its source: a
        message it hands over a little early is refused and waits a whole period more.
        """
        publisher = self._publisher
        assert publisher is not None  # started before the thread
        try:  # an exception out of here is the thread's death, said by ``BackgroundThread``
            while not self._stop.is_set():
                while not self._arrived.wait(_STOP_POLL_S):  # wait for a message to send
                    if self._stop.is_set():
                        return
                    publisher.say_if_stopped()  # a driver gone silent: said before a heartbeat
                if not self.forward():
                    self._sleep(self.retry_s())
        except _StoppedError:
            return
        finally:
            self._paced.set()

    def close(self) -> None:
        """Stop pacing, unsubscribe and withdraw the managed publisher.

        The publisher closes only after a send in progress returned (a stuck one is logged
        first), and no send starts after: the pacing thread never writes to a closed publisher.
        """
        self._stop.set()
        thread = self._thread
        if thread is not None:
            thread.join(_JOIN_TIMEOUT_S)
            if not self._paced.is_set():
                log.warning(
                    "%s: the bridge's pacing thread did not stop within %g s; "
                    "closing once its send returns",
                    self.topic,
                    _JOIN_TIMEOUT_S,
                )
        self._subscription.close()
        if self._publisher is not None:
            with self._sending:
                if self._camera is not None:
                    self._camera.close()  # its publisher too
                else:
                    self._publisher.close()
