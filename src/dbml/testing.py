"""An in-memory fleet for tests and simulations: what ``httpx.MockTransport`` is to httpx.

A ``Fleet`` is one ``MemoryNetwork`` whose hosts share one clock, with the paper's roles on it:
managed publishers on robots, an operator whose managed subscribers make their channels managed
(and keep what they receive), and an optimizer on the base station. Delivery is synchronous and
the clock moves only when told to, so a test steps the fleet round by round, exactly::

    from dbml import DbmSettings
    from dbml.testing import Fleet

    with Fleet(settings=DbmSettings(max_bandwidth_mbit=11)) as fleet:
        r1 = fleet.publisher("/r1/camera", size_bytes=84_000)
        r2 = fleet.publisher("/r2/camera", size_bytes=21_000)
        fleet.watch("/r1/camera")
        fleet.watch("/r2/camera")
        fleet.priority("/r2/camera", 10 / 17)  # Table 2, step 1
        fleet.optimize()
        assert r2.current_rate_hz() == 16.0

Every part is the product's own (``ManagedPublisher``, ``ManagedSubscriber``,
``OptimizerNode`` over ``MemoryTransport``): only the network and the clock are stand-ins.
"""

from __future__ import annotations

from collections.abc import Callable
from types import TracebackType
from typing import Self

from dbml.core.config import DbmSettings
from dbml.core.errors import SpecError
from dbml.core.ladder import Preference
from dbml.core.spec import LinkSpec
from dbml.protocol import names
from dbml.runtime.camera import PROBE_INTERVAL_S, ManagedCamera
from dbml.runtime.failsafe import FAILSAFE_PERIODS
from dbml.runtime.optimizer import ACK_TIMEOUT_S, OptimizerNode, Round
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.transports.base import Handle, ParamValue, Sample, TransportPriority, Variant
from dbml.transports.memory import ManualClock, MemoryNetwork, MemoryTransport

__all__ = ["BASE", "OPERATOR", "Fleet"]

BASE = "base"
"""The optimizer's host."""
OPERATOR = "operator"
"""The operator's host: its subscribers are remote to every robot."""
FIRST_TIME_S = 100.0
"""Where a fleet's manual clock starts (not 0: a test may step back from a time it read)."""


class Fleet:
    """Robots, an operator and an optimizer on one in-memory network (see the module docstring).

    ``clock``: the hosts' shared clock; by default a ``ManualClock`` (``fleet.clock.advance``),
    or ``time.monotonic`` for a fleet whose threads run (``OptimizerNode.start``).
    ``settings``: written by the optimizer at start, as ``dbml optimizer --config`` does;
    ``optimizer=False``: no optimizer (a test that pushes rates itself, ``allocate``).
    """

    def __init__(
        self,
        *,
        settings: DbmSettings | None = None,
        links: tuple[LinkSpec, ...] = (),
        optimizer: bool = True,
        clock: Callable[[], float] | None = None,
        ack_timeout_s: float = ACK_TIMEOUT_S,
    ) -> None:
        self.network = MemoryNetwork()
        self.clock: Callable[[], float] = ManualClock(FIRST_TIME_S) if clock is None else clock
        self._hosts: dict[str, MemoryTransport] = {}
        self._closing: list[Handle | ManagedPublisher | ManagedSubscriber | ManagedCamera] = []
        self.publishers: dict[str, ManagedPublisher] = {}
        self.received: dict[str, list[Sample]] = {}
        """What the operator's subscribers received, by topic."""
        self._optimizer: OptimizerNode | None = None
        if optimizer:
            self._optimizer = OptimizerNode(
                self.host(BASE),
                settings=settings,
                links=links,
                ack_timeout_s=ack_timeout_s,
                report_interval_s=0.0,  # every round reported, however close: a test steps them
            )
        elif settings is not None or links:
            raise SpecError("settings and links are the optimizer's: optimizer=False takes none")

    def host(self, name: str) -> MemoryTransport:
        """The transport of host ``name`` (made on first use; one per host)."""
        transport = self._hosts.get(name)
        if transport is None:
            transport = self._hosts[name] = MemoryTransport(
                self.network, host=name, clock=self.clock
            )
        return transport

    @property
    def optimizer(self) -> OptimizerNode:
        """The base station's optimizer (``SpecError`` in a fleet made without one)."""
        if self._optimizer is None:
            raise SpecError("this fleet has no optimizer (optimizer=False)")
        return self._optimizer

    @property
    def operator(self) -> MemoryTransport:
        """The operator's transport."""
        return self.host(OPERATOR)

    def advance(self, seconds: float) -> None:
        """Move the manual clock forward."""
        if not isinstance(self.clock, ManualClock):
            raise SpecError("advance() needs the fleet's manual clock (clock=None)")
        self.clock.advance(seconds)

    # -- the roles ----------------------------------------------------------------------------

    def publisher(
        self,
        topic: str,
        *,
        size_bytes: int | None = None,
        host: str | None = None,
        min_rate_hz: float = 1.0,
        max_rate_hz: float = 16.0,
        priority: float | None = None,
        failsafe_periods: float = FAILSAFE_PERIODS,
        transport_priority: TransportPriority | None = None,
        map_transport_priority: bool = True,
    ) -> ManagedPublisher:
        """A managed publisher of ``topic`` on ``host`` (by default the topic's first segment).

        ``size_bytes``: a first message of that size is published, so the optimizer knows the
        channel's size before its first round (as the demo's robots do).
        """
        robot = host if host is not None else topic.split("/")[1]
        publisher = ManagedPublisher(
            self.host(robot),
            topic,
            min_rate_hz=min_rate_hz,
            max_rate_hz=max_rate_hz,
            priority=priority,
            failsafe_periods=failsafe_periods,
            transport_priority=transport_priority,
            map_transport_priority=map_transport_priority,
        )
        self.publishers[topic] = publisher
        self._closing.append(publisher)
        if size_bytes is not None:
            publisher.publish(bytes(size_bytes))
        return publisher

    def camera(
        self,
        topic: str,
        *,
        host: str | None = None,
        min_rate_hz: float = 1.0,
        max_rate_hz: float = 16.0,
        priority: float | None = None,
        preference: Preference | None = None,
        ladder: bool = True,
        probe_interval_s: float = PROBE_INTERVAL_S,
    ) -> ManagedCamera:
        """A managed camera of ``topic`` on ``host`` (JPEG and a ladder: the ``quality`` extra).

        Its ladder is measured on the first frame it is given (``publish_frame``).
        """
        robot = host if host is not None else topic.split("/")[1]
        camera = ManagedCamera(
            self.host(robot),
            topic,
            min_rate_hz=min_rate_hz,
            max_rate_hz=max_rate_hz,
            priority=priority,
            preference=preference,
            ladder=ladder,
            probe_interval_s=probe_interval_s,
        )
        self._closing.append(camera)
        return camera

    def watch(
        self, topic: str, *, host: str = OPERATOR, remote: Variant = Variant.OPTIMIZED
    ) -> ManagedSubscriber:
        """A managed subscriber of ``topic`` on ``host``: remote, so the channel is managed.

        What it receives is kept in ``received[topic]``; ``remote=Variant.COMPRESSED`` takes a
        camera's JPEG copy.
        """
        received = self.received.setdefault(topic, [])
        subscriber = ManagedSubscriber(self.host(host), topic, received.append, remote=remote)
        self._closing.append(subscriber)
        return subscriber

    # -- the parameters -----------------------------------------------------------------------

    def set(self, name: str, value: ParamValue, *, host: str = OPERATOR) -> None:
        """Write a parameter from ``host`` (the operator's by default)."""
        self.host(host).params.set(name, value)

    def get(self, name: str) -> ParamValue:
        """A parameter's value as the operator's host holds it."""
        return self.operator.params.get(name)

    def priority(self, topic: str, value: float) -> None:
        """The operator sets ``topic``'s raw priority (``dbml priority``)."""
        self.set(names.priority(topic), value)

    def budget(self, mbit: float) -> None:
        """The operator sets the link's bandwidth (``dbml budget``)."""
        self.set(names.BANDWIDTH, mbit)

    def allocate(self, topic: str, rate_hz: float) -> None:
        """Push ``rate_hz`` to ``topic`` from the base station, as an optimizer's round would."""
        self.set(names.current_value(topic), rate_hz, host=BASE)

    def optimize(self) -> Round:
        """One round of the optimizer."""
        return self.optimizer.optimize()

    def rates(self) -> dict[str, float]:
        """Each publisher's rate in force, by topic."""
        return {topic: p.current_rate_hz() for topic, p in self.publishers.items()}

    # -- life ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the optimizer, close every publisher and subscriber, then every host."""
        if self._optimizer is not None:
            self._optimizer.stop()
        for part in reversed(self._closing):
            part.close()
        self._closing.clear()
        for transport in self._hosts.values():
            transport.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        _type: type[BaseException] | None,
        _value: BaseException | None,
        _traceback: TracebackType | None,
    ) -> None:
        self.close()
