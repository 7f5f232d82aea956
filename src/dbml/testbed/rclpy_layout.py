"""The testbed over real ROS 2 (rclpy on Fast DDS), laid out as the demo over rclpy is.

In each robot's namespace a plain rclpy camera (``rclpypeers``) and, managed, a bridge of its
topic (``experiment.bridge``); in the operator's the optimizer (dbml's role) and a plain rclpy
operator subscribing each ``/rN/camera/optimized`` (``/rN/camera`` unmanaged), taking DDS's
sequence numbers and send times. Every process joins a ROS 2 domain of the run's own, its ROS
logs under the run's folder (``ros/``); DDS discovery crosses the router by unicast, see
:func:`ros_env`. While the run lasts, the Fast DDS shared memory its processes own is listed, so
what a killed one leaves is removed after it.
"""

from __future__ import annotations

import contextlib
import importlib.util
import subprocess
import threading
from dataclasses import replace
from pathlib import Path

from dbml.experiment.entry import Kind
from dbml.experiment.plan import Plan, bridge_helper, role_launch
from dbml.experiment.rclpypeers import RCLPY_MISSING
from dbml.experiment.spec import HOSTS, host_of
from dbml.harness.ros2env import claim_domain, fastdds_shm_files, remove_fastdds_shm, ros2_child_env
from dbml.scenarios.fleet import fleet_cameras
from dbml.testbed.layout import Leftovers, base_spec, netns_of
from dbml.testbed.netns import Network, TestbedError
from dbml.testbed.options import Policy, TestbedOptions

__all__ = [
    "BUILTIN_TRANSPORTS",
    "ROS_LOG_DIR",
    "SHM_WATCH_S",
    "RclpyLayout",
    "ros_env",
]

ROS_LOG_DIR = "ros"
"""Where in the run's folder the ROS 2 processes log (``ROS_LOG_DIR``)."""
BUILTIN_TRANSPORTS = "FASTDDS_BUILTIN_TRANSPORTS"
"""Fast DDS's choice of its built-in transports (``UDPv4``: no shared memory)."""
SHM_WATCH_S = 5.0
"""How often the Fast DDS shared memory of the run's processes is listed while they run."""


def ros_env(network: Network, host: str, *, domain_id: int, log_dir: Path) -> dict[str, str]:
    """The environment of a ROS 2 process in ``host``'s namespace (``"op"`` or a robot's).

    ``ros2_child_env``'s (the run's domain, ROS logs in ``log_dir``, the fast-discovery Fast
    DDS profile) and what discovery needs across the router. Fast DDS finds its peers by
    multicast, which stays in its own segment (every namespace is one, and the router forwards
    no multicast): the processes of one namespace meet that way, those of two never do. So a
    robot's processes also announce themselves by unicast to the operator's address
    (``ROS_STATIC_PEERS``); the operator's, having heard them, answer and keep announcing to
    them, so one address on the robots' side is all it takes (measured: a robot's two
    publishers matched in 0.1-0.4 s, held through 40 s with the 3-s lease, and after an outage
    the robots' periodic announcements find the operator again). Robots are not told of each
    other: nothing of one robot is for another. The discovery range is the default
    (``SUBNET``), whatever this environment says, and a discovery server is not used.

    Fast DDS's shared-memory transport is off (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``), as zenoh's
    is in the testbed: ``/dev/shm`` is one for every namespace, so it is a path around the
    shaped link, and with it on, runs whose processes all ended cleanly (exit 0) still left
    port segments there (``fastdds_port7000``, ``fastdds_port7661``, ... of the operator's
    side). With UDP only, a run's processes make no ``/dev/shm/fastdds_*`` at all, and a
    robot's camera reaches its bridge over the namespace's own interfaces.
    """
    env = ros2_child_env(domain_id=domain_id, log_dir=log_dir)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
    env[BUILTIN_TRANSPORTS] = "UDPv4"
    for name in ("ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER", "ROS_LOCALHOST_ONLY"):
        env.pop(name, None)
    if host != "op":
        env["ROS_STATIC_PEERS"] = network.hosts["op"].address
    return env


def _namespace_pids(network: Network) -> set[int]:
    """Every process in the run's namespaces now (``ip netns pids``)."""
    pids: set[int] = set()
    for host in network.hosts.values():
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            listed = subprocess.run(
                ["ip", "netns", "pids", host.netns],
                capture_output=True,
                text=True,
                check=False,
                timeout=5,
            )
            pids.update(int(pid) for pid in listed.stdout.split() if pid.isdigit())
    return pids


class RclpyLayout:
    """Plain rclpy peers, dbml's bridges and optimizer in the namespaces (``TestbedLayout``)."""

    def __init__(self) -> None:
        self._shm: set[Path] = set()
        self._lock = threading.Lock()

    def check(self) -> None:
        """rclpy, for the plain peers (the ``rclpy`` extra)."""
        if importlib.util.find_spec("rclpy") is None:
            raise TestbedError(RCLPY_MISSING)

    def plan(
        self,
        network: Network,
        options: TestbedOptions,
        *,
        run: contextlib.ExitStack,
        folder: Path,
    ) -> Plan:
        """Each role in its host's namespace with :func:`ros_env`'s environment.

        The bridges (managed policies) start before the robots.
        """
        domain_id = run.enter_context(claim_domain())
        log_dir = folder / ROS_LOG_DIR
        envs = {
            host: ros_env(network, host, domain_id=domain_id, log_dir=log_dir)
            for host in network.hosts
        }
        cameras = fleet_cameras(options.robots)
        robots = [camera.robot.lower() for camera in cameras]
        managed = options.policy is not Policy.UNMANAGED
        base = replace(base_spec(options), domain_id=domain_id)
        specs = {"operator": replace(base, host=HOSTS["operator"])}
        if managed:
            specs["optimizer"] = replace(base, host=HOSTS["optimizer"])
        for role in robots:
            specs[role] = replace(base, host=host_of(role))
        launches = {}
        for role, spec in specs.items():
            host = netns_of(role)
            netns, env = network.hosts[host].netns, envs[host]
            if role == "optimizer":
                launches[role] = role_launch(Kind.ROLE, role, spec, env=env, netns=netns)
            else:  # the same protocol, played by plain rclpy nodes
                options_ = ("--sample-info",) if role == "operator" else ()
                launches[role] = role_launch(
                    Kind.RCLPY_PEER, role, spec, *options_, env=env, netns=netns
                )
        helpers = tuple(
            bridge_helper(
                camera,
                transport=options.transport,
                before=robots[0],
                env=envs[role],
                netns=network.hosts[role].netns,
                domain_id=domain_id,
            )
            for role, camera in zip(robots, cameras, strict=True)
            if managed
        )
        return Plan(specs=specs, launches=launches, helpers=helpers)

    def during(self, network: Network, stop: threading.Event) -> None:
        """List the run's processes' Fast DDS shared memory now and then, until ``stop``."""
        while True:
            seen = fastdds_shm_files(_namespace_pids(network))
            with self._lock:
                self._shm.update(seen)
            if stop.wait(SHM_WATCH_S):
                return

    def leftovers(self) -> Leftovers:
        """What a killed ROS 2 process left (one that ended gracefully, nothing), removed."""
        with self._lock:
            seen = tuple(sorted(self._shm))
        return Leftovers(seen, tuple(remove_fastdds_shm(list(seen))))
