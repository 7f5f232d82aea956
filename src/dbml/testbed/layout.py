"""How a testbed run's processes are laid out in the namespaces, chosen by the transport.

The registry says how a transport's processes meet (``TransportEntry.discovery``); each way the
testbed offers (``options.OFFERS``) has one layout (``LAYOUTS``): zenoh (``zenoh_layout``:
dbml's roles on explicit endpoints, or through a router per host) and DDS (``rclpy_layout``:
plain rclpy cameras and operator, dbml's bridges and optimizer). A layout lays a run out (a
``Plan``), watches what it must while the run lasts, and says what it left behind. What every
layout shares is here: the namespace of each role, the scenario every role is told, the live
view's way in.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

from dbml.core.allocation import Strategy
from dbml.experiment.plan import Plan
from dbml.experiment.spec import RoleSpec
from dbml.testbed.forward import NetnsForward
from dbml.testbed.netns import OPERATOR, Network, TestbedError
from dbml.testbed.options import Policy, TestbedOptions
from dbml.view.target import ViewTarget

__all__ = [
    "NETNS_OF_ROLE",
    "PEER_WAIT_S",
    "VIEW_PORT",
    "LayoutFactory",
    "Leftovers",
    "TestbedLayout",
    "base_spec",
    "forward_view",
    "netns_of",
    "with_view",
]

log = logging.getLogger("dbml.testbed")

PEER_WAIT_S = 15.0
"""How long a role waits for its peers across the namespaces before it reports ready."""
NETNS_OF_ROLE = {"operator": "op", "optimizer": "op", "r1": "r1", "r2": "r2"}
"""The namespace of each role; a fleet's robot ``rK`` runs in its own namespace ``rK``."""
VIEW_PORT = 8765
"""The operator's live view inside its namespace (a fresh one: the port is free there)."""


@dataclass(frozen=True, slots=True)
class Leftovers:
    """What a run's processes held that outlives a killed one (Fast DDS's shared memory)."""

    seen: tuple[Path, ...] = ()
    """What the run's processes held while they ran."""
    removed: tuple[Path, ...] = ()
    """Of those, what a killed process left and the testbed removed (a graceful end: none)."""


class TestbedLayout(Protocol):
    """How one way of meeting runs in the testbed's namespaces (one object per run)."""

    def check(self) -> None:
        """``TestbedError`` naming what to install, when this interpreter lacks it."""
        ...

    def plan(
        self,
        network: Network,
        options: TestbedOptions,
        *,
        run: contextlib.ExitStack,
        folder: Path,
    ) -> Plan:
        """The run laid out in ``network``; what it sets up is undone by ``run``.

        ``folder``: the run's own (for configs and logs of its processes).
        """
        ...

    def during(self, network: Network, stop: threading.Event) -> None:
        """What it watches from step 1 until ``stop`` (the run's end)."""
        ...

    def leftovers(self) -> Leftovers:
        """What a killed process left, removed; after the network is gone."""
        ...


LayoutFactory = Callable[[], TestbedLayout]


def netns_of(role: str) -> str:
    """The namespace a role runs in: the operator's side, or the robot's own."""
    return NETNS_OF_ROLE.get(role, role)


def base_spec(options: TestbedOptions) -> RoleSpec:
    """What every role of a run is told, whatever its transport: the options' scenario."""
    return RoleSpec(
        step_s=options.step_seconds,
        transport=options.transport,
        managed=options.policy is not Policy.UNMANAGED,
        link_mbit=options.link_mbit,
        utilization=options.utilization or 1.0,
        strategy=options.strategy or Strategy.PAPER,
        estimate=options.estimate,
        estimator_design=options.estimator_design,
        uplinks_mbit=dict(options.uplinks_mbit),
        peer_wait_s=PEER_WAIT_S,
        robots=options.robots,
        frames=options.frames,
        ladder=options.ladder,
    )


def with_view(spec: RoleSpec, view: ViewTarget) -> RoleSpec:
    """The operator's spec with its live view: its server inside its namespace."""
    inside = None if view.endpoint is None else f"127.0.0.1:{VIEW_PORT}"
    return replace(spec, foxglove=inside, record=view.record_flag)


@contextlib.contextmanager
def forward_view(network: Network, view: ViewTarget) -> Iterator[None]:
    """``--foxglove [HOST:]PORT`` on this machine, leading to the operator's view inside."""
    if view.endpoint is None:
        yield
        return
    try:
        forward = NetnsForward(
            network.netns_path(OPERATOR),
            host=view.endpoint.host,
            port=view.endpoint.port,
            target_port=VIEW_PORT,
        ).start()
    except OSError as err:
        raise TestbedError(f"--foxglove={view.endpoint}: {err}") from None
    log.info("live view: ws://%s:%d (the operator's, forwarded)", view.endpoint.host, forward.port)
    try:
        yield
    finally:
        forward.close()
