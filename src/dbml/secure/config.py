"""A node's zenoh config: a TLS peer of the fleet's full mesh, with the fleet's access rules."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dbml.secure.fleet import Fleet
from dbml.secure.rules import access_control
from dbml.transports.zenoh.transport import (
    KEEP_ALIVES_PER_LEASE,
    LEASE_MS,
    OPEN_TIMEOUT_MS,
    RETRY_MAX_MS,
)

__all__ = ["NodeFiles", "zenoh_config"]


@dataclass(frozen=True, slots=True)
class NodeFiles:
    """Where a node finds its TLS files: the paths its zenoh config names."""

    ca_certificate: Path
    certificate: Path
    private_key: Path


def zenoh_config(fleet: Fleet, name: str, files: NodeFiles) -> dict[str, Any]:
    """The zenoh config of node ``name``: a TLS peer of the mesh with the fleet's access control.

    It listens on its endpoint and connects to every other node's, retrying forever in the
    background, so nodes start in any order. It also listens on a free port of the same address:
    a second process of the node (an operator's ``dbml priority`` beside its ``dbml monitor``)
    finds the endpoint taken (not fatal) and is reached there instead, its peers learning the
    port by gossip, so every process still meets every other directly.
    """
    node = fleet.node(name)
    spare = node.endpoint.rpartition(":")[0] + ":0"
    others = [other.endpoint for other in fleet.nodes if other.name != name]
    return {
        "mode": "peer",
        "listen": {
            "endpoints": [node.endpoint, spare],
            "timeout_ms": 0,  # a taken endpoint is not retried: close() would wait for it
            "exit_on_failure": False,
        },
        "connect": {
            "endpoints": others,
            "timeout_ms": -1,
            "exit_on_failure": False,
            "retry": {
                "period_init_ms": 100,
                "period_max_ms": RETRY_MAX_MS,
                "period_increase_factor": 2,
            },
        },
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}, "delay": 0},
        "transport": {
            "shared_memory": {"enabled": False},
            "unicast": {"open_timeout": OPEN_TIMEOUT_MS},  # as every dbml session's
            "link": {
                "tx": {"lease": LEASE_MS, "keep_alive": KEEP_ALIVES_PER_LEASE},
                "tls": {
                    "root_ca_certificate": str(files.ca_certificate),
                    "listen_certificate": str(files.certificate),
                    "listen_private_key": str(files.private_key),
                    "connect_certificate": str(files.certificate),
                    "connect_private_key": str(files.private_key),
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                },
            },
        },
        "access_control": access_control(fleet),
    }
