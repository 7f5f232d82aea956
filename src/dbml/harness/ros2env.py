"""ROS 2 processes run hygienically: a domain of their own, logs and shared memory kept in check.

Processes in one ``ROS_DOMAIN_ID`` see each other, whoever started them, so each run (a test
session, a demo, a testbed) claims a domain exclusively (:func:`claim_domain`). Each child gets
that domain, a log directory (rclpy otherwise writes ``~/.ros/log/python_<pid>_*.log``) and the
fast-discovery Fast DDS profile (:func:`ros2_child_env`).

A SIGKILLed Fast DDS process leaves its shared-memory files in ``/dev/shm``: its segment
(``fastdds_<random 16 hex>``) and ports (``fastdds_port<port>``, with a
``sem.fastdds_port<port>_mutex``), each with an ``_el`` lock file. So do, without their lock
files, the ports of the processes it talked to when they end, however cleanly: the killed one
still counts as their user. The names carry no PID, but each owner holds an exclusive ``flock``
on its ``_el`` files, and ``/proc/locks`` names the holder's PID. So :func:`fastdds_shm_files`
lists what live processes own (take it once they are up: children, and this process if it has
a context of its own); after they are gone :func:`remove_fastdds_shm` removes those files, only
while no process holds their lock (Fast DDS's own test of a dead owner), never a live
process's. ``/dev/shm/lttng-ust-wait-*`` (LTTng tracing, created on ``import rclpy``) is per
user, not per process, and meant to stay: it is left alone.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

from dbml.core.errors import DbmlError
from dbml.transports.rclpy.fastdds import apply_discovery_profile

__all__ = [
    "DOMAIN_IDS",
    "DOMAIN_LOCK_DIR",
    "PROC_LOCKS",
    "SHM_DIR",
    "claim_domain",
    "fastdds_shm_files",
    "flock_holders",
    "remove_fastdds_shm",
    "ros2_child_env",
]

DOMAIN_IDS = range(1, 102)
"""The domains :func:`claim_domain` hands out: not 0 (everyone's default), at most 101 (ROS 2's
safe range on Linux: above it, DDS ports run into the ephemeral ports)."""
DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "dbml-ros-domains"
"""Where :func:`claim_domain` keeps its lock files: one place for every dbml run of the host."""
SHM_DIR = Path("/dev/shm")
"""Where Fast DDS keeps its shared memory on Linux."""
PROC_LOCKS = Path("/proc/locks")
"""The kernel's table of file locks, with each holder's PID."""

_SHM_NAME = re.compile(r"^fastdds_(port\d+|[0-9a-f]{16})$")
"""A Fast DDS segment's (random id) or port's name, that of its group of files."""
_SHM_LOCK = re.compile(r"^fastdds_(port\d+|[0-9a-f]{16})_(el|sl)$")
"""A Fast DDS lock file: a segment's or a port's; the owner holds a flock on it."""
_PROC_LOCK = re.compile(
    r"^\d+:\s+FLOCK\s+\S+\s+\S+\s+(?P<pid>\d+)\s+"
    r"(?P<major>[0-9a-f]+):(?P<minor>[0-9a-f]+):(?P<inode>\d+)\s"
)
"""A held flock in ``/proc/locks``: ``1: FLOCK  ADVISORY  WRITE 19232 00:1b:193 0 EOF`` (a
waiter's line has ``->`` after the number, and is not a holder)."""


@contextlib.contextmanager
def claim_domain(lock_dir: Path = DOMAIN_LOCK_DIR) -> Iterator[int]:
    """A ``ROS_DOMAIN_ID`` from :data:`DOMAIN_IDS` that no other claim holds, for the block.

    Each domain is an ``flock`` on ``lock_dir/<id>.lock``, so a claim ends with its process,
    however it ends; the lock files stay (removing them would race with a new claim).
    """
    lock_dir.mkdir(parents=True, exist_ok=True)
    for domain in DOMAIN_IDS:
        try:  # read-only: another user's lock file locks as well
            fd = os.open(lock_dir / f"{domain}.lock", os.O_RDONLY | os.O_CREAT, 0o644)
        except PermissionError:
            continue  # no lock file, and none may be made here: not a domain to hand out
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        try:
            yield domain
        finally:
            os.close(fd)  # closing releases the lock
        return
    raise DbmlError(
        f"every ROS 2 domain {DOMAIN_IDS.start}..{DOMAIN_IDS.stop - 1} is claimed (in {lock_dir})"
    )


def ros2_child_env(
    *, domain_id: int, log_dir: Path, base: Mapping[str, str] | None = None
) -> dict[str, str]:
    """The environment of a child ROS 2 process: its domain, logs and discovery profile.

    ``base`` (default: this process's environment) with ``ROS_DOMAIN_ID``, ``ROS_LOG_DIR`` and
    the fast-discovery Fast DDS profile, written into ``log_dir``. A profile the user set, or
    another RMW, is kept as it is; so is ``ROS_AUTOMATIC_DISCOVERY_RANGE``.
    """
    env = dict(os.environ if base is None else base)
    log_dir.mkdir(parents=True, exist_ok=True)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_LOG_DIR"] = str(log_dir)
    apply_discovery_profile(log_dir, env)
    return env


def _locked_inodes(pids: Iterable[int], proc_locks: Path) -> set[tuple[int, int, int]]:
    """(major, minor, inode) of every file that one of ``pids`` holds a ``flock`` on."""
    wanted = {str(pid) for pid in pids}
    held: set[tuple[int, int, int]] = set()
    for line in proc_locks.read_text().splitlines():
        found = _PROC_LOCK.match(line)
        if found and found["pid"] in wanted:
            held.add((int(found["major"], 16), int(found["minor"], 16), int(found["inode"])))
    return held


def flock_holders(path: Path, proc_locks: Path = PROC_LOCKS) -> set[int]:
    """The PIDs that hold a ``flock`` on ``path`` (waiters are not holders)."""
    stat = path.stat()
    wanted = (os.major(stat.st_dev), os.minor(stat.st_dev), stat.st_ino)
    return {
        int(found["pid"])
        for line in proc_locks.read_text().splitlines()
        if (found := _PROC_LOCK.match(line))
        and (int(found["major"], 16), int(found["minor"], 16), int(found["inode"])) == wanted
    }


def _companions(lock: Path) -> list[Path]:
    """A lock file's group: the lock, its segment and, for a port, the port's semaphore."""
    base = lock.name[: -len("_el")]
    return [lock, lock.with_name(base), lock.with_name(f"sem.{base}_mutex")]


def fastdds_shm_files(
    pids: Iterable[int], *, shm_dir: Path = SHM_DIR, proc_locks: Path = PROC_LOCKS
) -> list[Path]:
    """The Fast DDS shared-memory files that the live processes ``pids`` own, sorted.

    Ownership is the ``flock`` a process holds on a file's ``_el`` lock, so take this while the
    processes run (once their ROS 2 context is up); a process that is gone owns nothing here.
    """
    held = _locked_inodes(pids, proc_locks)
    if not held:
        return []
    found: set[Path] = set()
    for lock in shm_dir.iterdir():
        if not _SHM_LOCK.match(lock.name):
            continue
        try:
            stat = lock.stat()
        except FileNotFoundError:
            continue  # its owner ended and removed it meanwhile
        if (os.major(stat.st_dev), os.minor(stat.st_dev), stat.st_ino) in held:
            found.update(path for path in _companions(lock) if path.exists())
    return sorted(found)


def _hold_name(base: Path) -> tuple[int, Path, bool] | None:
    """Hold a group's lock exclusively: (descriptor, lock file, made here?); None if held.

    A group left without its lock file (an owner that ended cleanly while a killed peer still
    counted on its port keeps the port's segment and semaphore) gets one, made and locked here as
    Fast DDS would, so no process can take the name up while it goes.
    """
    made = False
    for lock in (base.with_name(f"{base.name}_el"), base.with_name(f"{base.name}_sl")):
        try:
            fd = os.open(lock, os.O_RDONLY)
        except FileNotFoundError:
            continue
        break
    else:
        lock = base.with_name(f"{base.name}_el")
        try:
            fd = os.open(lock, os.O_RDONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return None  # a process is taking the name up right now
        made = True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd, lock, made


def _unlink(path: Path) -> bool:
    """Remove ``path``; whether it was there."""
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    return True


def remove_fastdds_shm(files: Iterable[Path]) -> list[Path]:
    """Remove those of ``files`` (from :func:`fastdds_shm_files`) whose owner is gone; them.

    A file goes only while this function holds its group's lock exclusively, the test Fast DDS
    itself makes: a group that a process holds (its owner, or a new process that took the name
    over) stays, and none can take a name up while it goes. The group's lock file goes last.
    """
    groups: dict[Path, set[Path]] = {}
    for path in files:
        name = path.name.removeprefix("sem.").removesuffix("_mutex")
        name = name.removesuffix("_el").removesuffix("_sl")
        if _SHM_NAME.match(name):  # anything else is not Fast DDS's to remove
            groups.setdefault(path.with_name(name), set()).add(path)
    removed: list[Path] = []
    for base, paths in sorted(groups.items()):
        if not any(path.exists() for path in paths):
            continue  # gone already (its owner ended cleanly)
        held = _hold_name(base)
        if held is None:
            continue
        fd, lock, made = held
        try:
            removed.extend(path for path in sorted(paths - {lock}) if _unlink(path))
            if _unlink(lock) and not made and lock in paths:
                removed.append(lock)
        finally:
            os.close(fd)
    return removed
