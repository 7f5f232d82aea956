"""Small process plumbing: a free port, and the environment of another interpreter's child.

Starting, reading and ending processes is the supervisor's (``dbml.harness.supervisor``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import random
import socket
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

__all__ = ["exit_process", "foreign_interpreter_env", "free_port"]

_ROS_WHEELS_GUARD = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
"""Set by the ROS 2 wheels' ``.pth`` bootstrap once it has re-executed with its library path."""


EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
"""Where Linux says which ports it hands out itself (``bind`` to port 0, a connection's own)."""
LOWEST_PORT = 10_000
"""The lowest port ``free_port`` offers: above the well-known and most services' ports."""
PORT_TRIES = 64


def _ephemeral_low() -> int | None:
    """The first port the kernel hands out itself, where it says (Linux)."""
    try:
        return int(EPHEMERAL_RANGE_FILE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (for a rendezvous or a master of a run's own).

    Chosen below the kernel's ephemeral range where it can: the kernel never gives such a port
    to another socket (a zenoh session listening on port 0, a connection's own end) between this
    call and the caller's bind, as it may one of its own range; two runs side by side (a
    parallel test suite) would then meet at one rendezvous.
    """
    low = _ephemeral_low()
    if low is not None and low > LOWEST_PORT:
        pick = random.SystemRandom()
        for _ in range(PORT_TRIES):
            port = pick.randrange(LOWEST_PORT, low)
            with socket.socket() as sock:
                try:
                    sock.bind((host, port))
                except OSError:
                    continue
                return port
    with socket.socket() as sock:
        sock.bind((host, 0))
        bound: int = sock.getsockname()[1]
        return bound


def foreign_interpreter_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """``base`` (default ``os.environ``) for a child that another interpreter than ours runs.

    The ROS 2 wheels' ``.pth`` bootstrap re-executes every interpreter of their environment with
    ``LD_LIBRARY_PATH`` extended and a guard variable set, and children inherit both. Another
    interpreter (Debian's ``/usr/bin/python3`` running ``rosmaster``, the ROS 1 venv's) would load
    ROS 2's libraries, and its own environment's bootstrap, seeing the guard, would not run. So
    the guard goes, and so do the directories the bootstrap adds (an environment's ``lib``, the
    wheels' ``ros_*.libs``); the user's own stay (the variable goes if nothing is left), and so
    does every other variable.
    """
    env = dict(os.environ if base is None else base)
    env.pop(_ROS_WHEELS_GUARD, None)
    kept = [
        entry
        for entry in env.pop("LD_LIBRARY_PATH", "").split(os.pathsep)
        if entry and not _wheels_library_dir(Path(entry))
    ]
    if kept:
        env["LD_LIBRARY_PATH"] = os.pathsep.join(kept)
    return env


def _wheels_library_dir(path: Path) -> bool:
    """Whether the wheels' bootstrap adds ``path``: its ``sys.prefix/lib``, or a ``ros_*.libs``."""
    if path.name.startswith("ros_") and path.name.endswith(".libs"):
        return True
    if path.name != "lib":
        return False
    prefix = path.parent  # ours, or another virtual environment's (a child of one of them)
    return prefix.resolve() == Path(sys.prefix).resolve() or (prefix / "pyvenv.cfg").is_file()


def exit_process(main: Callable[[], int]) -> None:
    """Run a process's ``main``; end the process with its code, without the interpreter's teardown.

    ``main`` closes what it opened (sessions, nodes, files) before it returns; what is left to
    the interpreter's finalization is its threads. There a middleware's own thread (zenoh's,
    Fast DDS's) that calls into Python is ended by CPython 3.11 with ``pthread_exit``, and the
    unwinding through its native frames can abort the process after its work is done (``FATAL:
    exception not rethrown``, exit -6: a CI run of ``dbml priority`` over mTLS). So the output
    and the logs are flushed and the process ends at once.
    """
    try:
        code = main()
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # closed, or its reader gone
            stream.flush()
    os._exit(code)
