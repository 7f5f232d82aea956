"""A secure fleet: one certificate authority, and a certificate and a zenoh config per node.

Out of the box dbml authenticates nobody: any process that reaches the loopback mesh (or an
endpoint) may write any parameter, including the budget. A fleet across machines needs more, so
``dbml secure init`` makes:

- a fleet CA (``ca.key``, ``ca.pem``) that signs every node's certificate;
- per node a key and a certificate whose common name is the node's name (the optimizer, each
  robot, each operator), valid for the node's name, ``localhost``, 127.0.0.1, the address of its
  endpoint and any extra names given;
- per node a zenoh config (``<name>.json5``): peer mode over TLS with mutual authentication, so a
  peer without a certificate from the CA cannot even connect, and access control that lets a
  connected peer write only what its role owns.

One module per concern: ``fleet`` (the plan and its checks), ``flags`` (the plan from the
command line), ``rules`` (the access rules, from the wire schema), ``config`` (a node's zenoh
config), ``pki`` (keys and certificates) and ``files`` (writing them). Nothing here opens a
session.
"""

from dbml.secure.config import NodeFiles, zenoh_config
from dbml.secure.files import CA_CERTIFICATE, CA_KEY, WrittenFile, init_fleet
from dbml.secure.flags import fleet_from_flags
from dbml.secure.fleet import DEFAULT_BASE_PORT, Fleet, FleetNode, NodeRole, SecureError, plan_fleet
from dbml.secure.pki import DEFAULT_DAYS
from dbml.secure.rules import access_control

__all__ = [
    "CA_CERTIFICATE",
    "CA_KEY",
    "DEFAULT_BASE_PORT",
    "DEFAULT_DAYS",
    "Fleet",
    "FleetNode",
    "NodeFiles",
    "NodeRole",
    "SecureError",
    "WrittenFile",
    "access_control",
    "fleet_from_flags",
    "init_fleet",
    "plan_fleet",
    "zenoh_config",
]
