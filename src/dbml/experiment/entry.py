"""The one entry of a run's child processes: ``python -m dbml.experiment KIND ...``.

Every process a demo or testbed run starts besides the ``dbml`` command line is one of these
kinds, each a body run here with one signal handling (``stop_on_signals``), one reader of
control lines (``harness.child.Control``), one logging set-up and one rule for exit codes:

- ``role ROLE SPEC_JSON``: one of dbml's roles (``roles``: operator, optimizer, robots);
- ``ros2-peer ROLE SPEC_JSON``: a plain ROS 2 peer over rmw_zenoh's format (``ros2peers``);
- ``rclpy-peer ROLE SPEC_JSON [--sample-info]``: a plain rclpy peer (``rclpypeers``);
- ``bridge SPEC_JSON``: a camera's bridge, reporting its publishes (``bridge``);
- ``router --listen EP [--connect EP]``: a zenoh router for one host (``router``).

Exit codes: 0 done or told to stop; 1 a run that failed once it was under way (a dbml thread
died, its control failed: ``RoleError``); 2 what could not start (bad input, a missing package:
``DbmlError``), with one line on stderr. Each kind's module is imported only when it runs, so
a run can name a kind whose middleware this interpreter lacks.
"""

from __future__ import annotations

import argparse
import enum
import importlib
import logging
import sys
import threading
from collections.abc import Sequence

from dbml.core.errors import DbmlError
from dbml.experiment.spec import RoleSpec
from dbml.harness.child import RoleError, stop_on_signals
from dbml.runtime.serve import Lifetime

__all__ = ["ENTRY_MODULE", "EXIT_FAILED", "EXIT_USAGE", "Kind", "child_argv", "main"]

ENTRY_MODULE = "dbml.experiment"
"""What ``python -m`` runs for every kind."""
EXIT_FAILED = 1
EXIT_USAGE = 2


class Kind(enum.StrEnum):
    """The kinds of child process a run starts."""

    ROLE = "role"
    ROS2_PEER = "ros2-peer"
    RCLPY_PEER = "rclpy-peer"
    BRIDGE = "bridge"
    ROUTER = "router"


def child_argv(kind: Kind, *args: str) -> tuple[str, ...]:
    """The argv of a ``kind`` child with ``args``, run by this interpreter."""
    return (sys.executable, "-m", ENTRY_MODULE, kind.value, *args)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"python -m {ENTRY_MODULE}")
    kinds = parser.add_subparsers(dest="kind", required=True)
    for kind, what in (
        (Kind.ROLE, "one of dbml's roles: operator, optimizer, r1..rN"),
        (Kind.ROS2_PEER, "a plain ROS 2 peer (zenoh-ros2-sdk): operator, r1, r2"),
        (Kind.RCLPY_PEER, "a plain rclpy peer: operator, r1..rN"),
    ):
        sub = kinds.add_parser(kind.value, help=what)
        sub.add_argument("role")
        sub.add_argument("spec", help="the RoleSpec as JSON")
        if kind is Kind.RCLPY_PEER:
            sub.add_argument(
                "--sample-info",
                action="store_true",
                help="the operator takes each frame's sequence number and send time from DDS's "
                "sample info (writer sequence number, source timestamp), not a count and "
                "header.stamp",
            )
    bridge = kinds.add_parser(Kind.BRIDGE.value, help="a camera's bridge")
    bridge.add_argument("spec", help="the BridgeSpec as JSON")
    router = kinds.add_parser(Kind.ROUTER.value, help="a zenoh router for one host")
    router.add_argument("--listen", action="append", required=True, metavar="ENDPOINT")
    router.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    return parser


_MODULES = {
    Kind.ROLE: "dbml.experiment.roles",
    Kind.ROS2_PEER: "dbml.experiment.ros2peers",
    Kind.RCLPY_PEER: "dbml.experiment.rclpypeers",
    Kind.BRIDGE: "dbml.experiment.bridge",
    Kind.ROUTER: "dbml.experiment.router",
}
"""Each kind's module: its ``serve`` is the kind's body."""


def _run(args: argparse.Namespace, stop: threading.Event) -> int:
    """Run the kind ``args`` name (its module imported now); its exit code."""
    kind = Kind(args.kind)
    module = importlib.import_module(_MODULES[kind])
    if kind is Kind.ROUTER:
        return int(module.serve(stop, listen=args.listen, connect=args.connect))
    if kind is Kind.BRIDGE:
        return int(module.serve(module.BridgeSpec.from_json(args.spec), stop))
    spec = RoleSpec.from_json(args.spec)
    options = {"sample_info": args.sample_info} if kind is Kind.RCLPY_PEER else {}
    return int(module.serve(args.role, spec, stop, **options))


def main(argv: Sequence[str] | None = None) -> int:
    """Run one child of a run with ``argv`` (default: the process's arguments); its exit code."""
    args = _parser().parse_args(argv)
    name = getattr(args, "role", None) or args.kind
    verbose = args.kind == Kind.BRIDGE  # as ``dbml bridge``: it says what it bridged
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format=f"{name}: %(name)s: %(message)s",
        stream=sys.stderr,
    )
    logging.getLogger("rospy").setLevel(logging.WARNING)
    try:
        with stop_on_signals() as stop:
            life = Lifetime(stop, None)  # the process's: a thread dead before the run counts
            return _run(args, stop) or life.exit_code()
    except RoleError as err:
        sys.stderr.write(f"{name}: {err}\n")
        return EXIT_FAILED
    except DbmlError as err:
        sys.stderr.write(f"{name}: {err}\n")
        return EXIT_USAGE
