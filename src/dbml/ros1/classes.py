"""DBMPublisher, DBMSubscriber, DBMRate and DBMOptimizer: rospy-shaped faces of the runtime.

Each is a thin adapter: it resolves the ROS name, (de)serialises rospy messages and hands bytes
to ``ManagedPublisher``, ``ManagedSubscriber``, ``Rate`` or ``OptimizerNode``, so ROS 1 gets the
same allocation, fail-safe and local/remote rules as every other transport.
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Callable, Iterable
from typing import Any

from dbml.transports.ros1.master import ROSPY_MISSING

try:
    import rospy
except ImportError as err:  # pragma: no cover - depends on the machine
    raise ImportError(ROSPY_MISSING) from err

from dbml.core.config import DbmSettings
from dbml.core.errors import SpecError
from dbml.core.spec import ChannelSpec, LinkSpec
from dbml.protocol import names
from dbml.runtime.optimizer import OptimizerNode, Round
from dbml.runtime.params import ParamView
from dbml.runtime.publisher import FAILSAFE_PERIODS, ManagedPublisher
from dbml.runtime.rate import Rate
from dbml.runtime.serve import Lifetime
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports.base import Sample, Variant, check_topic
from dbml.transports.ros1.transport import Ros1Transport, serialize
from dbml.transports.worker import BackgroundThread

__all__ = ["DBMOptimizer", "DBMPublisher", "DBMRate", "DBMSubscriber", "ros1_transport"]

log = logging.getLogger("dbml.ros1")

_JOIN_TIMEOUT_S = 5.0
"""How long ``unregister`` waits for a ``start`` thread's current message before closing."""
_SPIN_POLL_S = 0.1
"""How often ``DBMOptimizer.spin`` looks whether ROS shut down or a dbml thread died."""


def ros1_transport() -> Ros1Transport:
    """This process's ROS 1 transport, started on first use (on the rospy node, if one runs)."""
    return Ros1Transport.shared()


def _resolve(name: str) -> str:
    """A ROS name as the node sees it (``camera`` in namespace ``/r1`` is ``/r1/camera``)."""
    return check_topic(rospy.resolve_name(name))


_PUBLISHERS: weakref.WeakValueDictionary[str, DBMPublisher] = weakref.WeakValueDictionary()
"""This process's DBMPublishers by resolved topic, for ``DBMRate(topic_name, ...)``."""


class _StoppedError(Exception):
    """A ``start`` loop's publisher was unregistered (or ROS shut down): end the loop."""


def _message_type(data_class: type) -> str:
    kind = getattr(data_class, "_type", None)
    if not isinstance(kind, str) or not hasattr(data_class, "serialize"):
        raise SpecError(f"data_class={data_class!r} is not a rospy message class")
    return kind


class DBMPublisher:
    """Publish ``data_class`` messages on ``name`` at the frequency the optimizer allocates.

    The frequency stays between ``min_frequency`` and ``max_frequency`` (Hz).

    ``publish(msg)`` sends every message to ``[name]`` when someone on this host listens, and to
    ``[name]/optimized`` within the allocated frequency; it returns True when the message went
    to the optimized copy. The message size parameter follows the serialised size.
    """

    def __init__(
        self,
        name: str,
        data_class: type,
        min_frequency: float,
        max_frequency: float,
        *,
        priority: float | None = None,
        failsafe_periods: float = FAILSAFE_PERIODS,
    ) -> None:
        self._type = _message_type(data_class)
        self.data_class = data_class
        self.name = _resolve(name)
        transport = ros1_transport()
        transport.use_message_class(self.name, data_class)
        self._managed = ManagedPublisher(
            transport,
            self.name,
            min_rate_hz=min_frequency,
            max_rate_hz=max_frequency,
            priority=priority,
            failsafe_periods=failsafe_periods,
        )
        self._stop = threading.Event()
        self._thread: BackgroundThread | None = None
        self._ended = threading.Event()
        """Set when the ``start`` loop ended: unregistered, ROS's shutdown, or its death."""
        _PUBLISHERS[self.name] = self

    @property
    def frequency(self) -> float:
        """The frequency in force (Hz): the allocation, or the minimum before one."""
        return self._managed.current_rate_hz()

    def publish(self, message: Any) -> bool:
        """Send ``message``; True when it also went to ``[name]/optimized``."""
        if not isinstance(message, self.data_class):
            raise SpecError(
                f"message={type(message).__name__} is not {self._type} (topic {self.name})"
            )
        return self._managed.publish(serialize(message))

    @property
    def alive(self) -> bool:
        """Whether the ``start`` thread runs: False before ``start``, after it failed or ended."""
        thread = self._thread
        return thread is not None and thread.alive and not self._ended.is_set()

    def start(self, get_message: Callable[[], Any], *, full_rate: bool = True) -> None:
        """Publish ``get_message()`` in a background thread, as the original package's nodes do.

        ``full_rate=True`` calls it at ``max_frequency``: every message goes to ``[name]`` (for
        local readers) and the allocated share to ``[name]/optimized``. ``full_rate=False``
        calls it only at the allocated frequency (no capture that would be dropped). The thread
        ends with ``unregister()`` or ROS's shutdown, quietly also when ``get_message`` or the
        publish raises meanwhile (rospy does, shutting down). Any other exception from them is
        the thread's death: logged (critical), ``alive`` turns False and it counts as a dead dbml
        thread, so ``DBMOptimizer.spin`` in this process exits 1. One ``start`` per publisher.
        """
        if self._thread is not None:
            raise SpecError(f"DBMPublisher({self.name!r}).start(): already started")

        def pause(seconds: float) -> None:
            if self._stop.wait(seconds) or rospy.is_shutdown():
                raise _StoppedError

        max_hz = self._managed.max_rate_hz
        rate = Rate((lambda: max_hz) if full_rate else self._managed.current_rate_hz, sleep=pause)

        def stopping() -> bool:
            return self._stop.is_set() or rospy.is_shutdown()

        def loop() -> None:
            try:
                while not stopping():
                    rate.sleep()
                    self.publish(get_message())
            except _StoppedError:
                return
            except Exception:
                # Between the check and the call, ROS may shut down (or ``unregister`` close the
                # channel), and rospy raises: that is the end asked for, not a death.
                if stopping():
                    log.debug("%s: start thread stopped", self.name, exc_info=True)
                    return
                raise  # BackgroundThread says it died, with the traceback: once
            finally:
                self._ended.set()

        # Known before it runs: ``get_message`` may call ``unregister`` at once.
        self._thread = BackgroundThread(loop, name=f"dbm-publisher {self.name}", log=log)
        self._thread.start()

    def unregister(self) -> None:
        """Stop publishing (and a ``start`` thread) and withdraw the channel."""
        self._stop.set()
        if _PUBLISHERS.get(self.name) is self:
            del _PUBLISHERS[self.name]  # a DBMRate(name) made later must not follow this one
        thread = self._thread
        if thread is not None:
            thread.join(_JOIN_TIMEOUT_S)  # at once from the thread itself (get_message's)
            if not self._ended.is_set() and not thread.is_current():
                log.warning(
                    "%s: the start thread did not stop within %g s; closing anyway",
                    self.name,
                    _JOIN_TIMEOUT_S,
                )
        self._managed.close()


class _Allocation:
    """A channel's allocated frequency, for a ``DBMRate`` whose topic has no DBMPublisher here.

    As the original ``DBMRate(topic_name, ...)``: it declares the bounds and follows the
    allocation (within them); the size comes from whoever publishes the topic.
    """

    def __init__(self, topic: str, min_hz: float, max_hz: float, default_hz: float | None) -> None:
        spec = ChannelSpec(topic, min_hz, max_hz, 1.0)
        self.min_hz, self.max_hz = spec.min_rate_hz, spec.max_rate_hz
        self._initial = spec.min_rate_hz if default_hz is None else default_hz
        self._topic = topic
        transport = ros1_transport()
        transport.params.set(names.min_rate(topic), self.min_hz)
        transport.params.set(names.max_rate(topic), self.max_hz)
        self._view = ParamView.of(transport.params)

    def rate_hz(self) -> float:
        """The allocation, capped at the maximum; ``default_frequency`` (or min) before one.

        Not raised to the minimum: an infeasible budget's rates sit below the minimums on
        purpose, so that they still fit it (as ``ManagedPublisher`` applies them).
        """
        value = self._view.get(names.current_value(self._topic))
        rate = value if isinstance(value, float) else self._initial
        return min(rate, self.max_hz)


class DBMRate:
    """``rospy.Rate`` at a channel's allocated frequency: ``sleep()`` follows every change.

    ``DBMRate(publisher)``, or the original package's ``DBMRate(topic_name, min_frequency,
    max_frequency[, default_frequency])``: the rate of that topic's DBMPublisher in this process
    if there is one, else the allocation read from the parameter server. Like
    ``rospy.Rate.sleep``, it raises ``rospy.ROSInterruptException`` once ROS shuts down.
    """

    def __init__(
        self,
        publisher: DBMPublisher | str,
        min_frequency: float | None = None,
        max_frequency: float | None = None,
        default_frequency: float | None = None,
    ) -> None:
        self._rate_hz: Callable[[], float]
        if isinstance(publisher, DBMPublisher):
            self._rate = publisher._managed.rate
            self._rate_hz = publisher._managed.current_rate_hz
            return
        topic = _resolve(publisher)
        known = _PUBLISHERS.get(topic)
        if known is not None:
            self._rate = known._managed.rate
            self._rate_hz = known._managed.current_rate_hz
            return
        if min_frequency is None or max_frequency is None:
            raise SpecError(
                f"DBMRate({publisher!r}): min_frequency and max_frequency are required "
                "for a topic without a DBMPublisher in this process"
            )
        self._allocation = _Allocation(topic, min_frequency, max_frequency, default_frequency)
        self._rate = Rate(self._allocation.rate_hz)
        self._rate_hz = self._allocation.rate_hz

    @property
    def frequency(self) -> float:
        """The frequency ``sleep()`` keeps now (Hz): the allocation within the bounds."""
        return self._rate_hz()

    def sleep(self) -> None:
        """Sleep until the next period at the allocated frequency."""
        if rospy.is_shutdown():
            raise rospy.ROSInterruptException("ROS shutdown request")
        self._rate.sleep()

    def reset(self) -> None:
        """Start the schedule again at the next ``sleep()``."""
        self._rate.reset()


class DBMSubscriber:
    """Subscribe to ``name``: ``[name]`` from a publisher on this host, else the optimized copy.

    ``callback(msg)`` (or ``callback(msg, callback_args)``) gets ``data_class`` messages. The
    subscription to ``[name]/optimized`` from another host is what makes the topic managed.
    """

    def __init__(
        self,
        name: str,
        data_class: type,
        callback: Callable[..., None],
        callback_args: Any = None,
    ) -> None:
        _message_type(data_class)
        self.data_class = data_class
        self.name = _resolve(name)
        transport = ros1_transport()
        transport.use_message_class(self.name, data_class)

        def deliver(sample: Sample) -> None:
            message = data_class()
            message.deserialize(sample.payload)
            if callback_args is None:
                callback(message)
            else:
                callback(message, callback_args)

        self._managed = ManagedSubscriber(transport, self.name, deliver)

    @property
    def optimized(self) -> bool:
        """True while it receives ``[name]/optimized`` (the publisher is on another host)."""
        return self._managed.variant is Variant.OPTIMIZED

    def unregister(self) -> None:
        """Stop receiving."""
        self._managed.close()


class DBMOptimizer:
    """The optimizer node: allocate periodically and at once on every change.

    The period is ``/dbm/optimization_rate_in_seconds``; a priority, size, bound, budget or
    graph change triggers a round at once. With ``settings`` it writes the ``/dbm/...``
    parameters first; without, it uses what is on the parameter server (``rosparam set
    /dbm/max_bandwidth_in_mbit 11``) and writes the defaults of the others. An infeasible budget
    is reported in ``/dbm/status`` and ``/dbm/status_message``, never silently ignored.
    """

    def __init__(
        self, settings: DbmSettings | None = None, *, links: Iterable[LinkSpec] = ()
    ) -> None:
        self._node = OptimizerNode(
            ros1_transport(), settings=settings, links=links, write_defaults=True
        )

    def optimize(self) -> Round:
        """One round now: read, allocate, push."""
        return self._node.optimize()

    @property
    def last_round(self) -> Round | None:
        """The latest round's allocation, or None before the first."""
        return self._node.last_round

    def start(self) -> DBMOptimizer:
        """Run rounds in the background; returns itself."""
        self._node.start()
        return self

    def stop(self) -> None:
        """Stop the background rounds."""
        self._node.stop()

    def spin(self) -> None:
        """Run until ROS shuts down (or Ctrl-C), as ``rospy.spin()``.

        When a dbml thread of this process dies meanwhile (this optimizer's, a ``DBMPublisher``
        ``start`` thread's, the transport's), it raises ``SystemExit(1)``: the node exits
        non-zero, so roslaunch's ``respawn`` or a supervisor restarts it, instead of a node that
        looks alive and allocates nothing.
        """
        self.start()
        life = Lifetime(threading.Event(), None)
        try:
            while not rospy.is_shutdown() and not life.over():
                rospy.rostime.wallsleep(_SPIN_POLL_S)
        except KeyboardInterrupt:  # as rospy.spin() with signals disabled
            rospy.signal_shutdown("keyboard interrupt")
        finally:
            self.stop()
        if life.exit_code() != 0:
            raise SystemExit(1)
