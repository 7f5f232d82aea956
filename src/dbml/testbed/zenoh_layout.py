"""The testbed over zenoh: dbml's roles in the namespaces, on explicit endpoints or via routers.

Under ``--topology peer`` (the default) every role is a zenoh peer: the operator and the
optimizer listen on the operator's side, each robot listens on its own address and connects to
them, shared memory off. Under ``--topology router`` every host runs a zenoh router (each
robot's connected to the operator's, across the shaped link, as ROS 2 fleets run rmw_zenoh's)
and every role is a client of its host's router. The operator's live view, if asked for, is
forwarded from its namespace to this machine.
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import replace
from pathlib import Path

from dbml.experiment.entry import Kind
from dbml.experiment.plan import Helper, Plan, role_launch, router_helper
from dbml.experiment.spec import HOSTS, RoleSpec, host_of
from dbml.scenarios.fleet import fleet_cameras
from dbml.testbed.layout import Leftovers, base_spec, forward_view, netns_of, with_view
from dbml.testbed.netns import Network
from dbml.testbed.options import Policy, TestbedOptions, Topology

__all__ = [
    "CLIENT_CONFIG",
    "OPTIMIZER_PORT",
    "ZENOH_PORT",
    "ZenohLayout",
    "routers",
    "zenoh_specs",
]

CLIENT_CONFIG = '{mode: "client"}\n'
"""The roles' zenoh config under ``--topology router``: they reach others only via routers."""
ZENOH_PORT = 7447
OPTIMIZER_PORT = 7448


def _router_ep(network: Network, host: str) -> str:
    return f"tcp/{network.hosts[host].address}:{ZENOH_PORT}"


def routers(network: Network) -> tuple[Helper, ...]:
    """``--topology router``: a router per host, each robot's connected to the operator's."""
    hub = _router_ep(network, "op")
    return tuple(
        router_helper(
            f"router-{host}",
            listen=_router_ep(network, host),
            connect=(hub,) if host != "op" else (),
            netns=network.hosts[host].netns,
        )
        for host in ("op", *network.robots)
    )


def zenoh_specs(
    network: Network, options: TestbedOptions, *, config_file: str | None = None
) -> dict[str, RoleSpec]:
    """Explicit endpoints: robots connect to the operator's side, where the optimizer runs.

    Under ``--topology router`` every role is instead a client (``config_file``) of its host's
    router, and only the routers cross the shaped link.
    """
    operator_ep = f"tcp/{network.hosts['op'].address}:{ZENOH_PORT}"
    optimizer_ep = f"tcp/{network.hosts['op'].address}:{OPTIMIZER_PORT}"
    managed = options.policy is not Policy.UNMANAGED
    base = replace(
        base_spec(options),
        urgent_stream=options.urgent_stream,
        priority_links=options.urgent_stream,  # the urgent stream's class: a link of its own
    )
    robots = [camera.robot.lower() for camera in fleet_cameras(options.robots)]
    if options.topology is Topology.ROUTER:
        client = replace(base, config_file=config_file)
        specs = {
            role: replace(client, host=HOSTS[role], connect=(operator_ep,))
            for role in ("operator", "optimizer")
            if role == "operator" or managed
        }
        for role in robots:
            host = host_of(role)
            specs[role] = replace(client, host=host, connect=(_router_ep(network, role),))
        return specs
    specs = {"operator": replace(base, host=HOSTS["operator"], listen=(operator_ep,))}
    if managed:
        specs["optimizer"] = replace(
            base, host=HOSTS["optimizer"], listen=(optimizer_ep,), connect=(operator_ep,)
        )
    for role in robots:
        specs[role] = replace(
            base,
            host=host_of(role),
            listen=(f"tcp/{network.hosts[role].address}:{ZENOH_PORT}",),
            connect=(operator_ep, *([optimizer_ep] if managed else [])),
        )
    return specs


class ZenohLayout:
    """dbml's roles over zenoh in the namespaces (``TestbedLayout``)."""

    def check(self) -> None:
        """Zenoh is a dependency: nothing to install."""

    def plan(
        self,
        network: Network,
        options: TestbedOptions,
        *,
        run: contextlib.ExitStack,
        folder: Path,
    ) -> Plan:
        """Each role in its namespace; the routers first under ``--topology router``."""
        router = options.topology is Topology.ROUTER
        config_file: str | None = None
        if router:
            client = folder / "client.json5"
            client.write_text(CLIENT_CONFIG, encoding="utf-8")
            config_file = str(client)
        specs = zenoh_specs(network, options, config_file=config_file)
        if options.view is not None:
            specs["operator"] = with_view(specs["operator"], options.view)
            run.enter_context(forward_view(network, options.view))
        launches = {
            role: role_launch(Kind.ROLE, role, spec, netns=network.hosts[netns_of(role)].netns)
            for role, spec in specs.items()
        }
        return Plan(specs=specs, launches=launches, helpers=routers(network) if router else ())

    def during(self, network: Network, stop: threading.Event) -> None:
        """Nothing to watch."""

    def leftovers(self) -> Leftovers:
        """Nothing outlives a zenoh process."""
        return Leftovers()
