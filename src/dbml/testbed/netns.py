"""A real, shaped test network: Linux network namespaces joined through a router namespace.

Each robot and the operator get their own namespace, linked to a router namespace by a veth pair::

    r1 (10.200.1.2) ──┐
    r2 (10.200.2.2) ──┼── rt ══ tbf ══> op (10.200.100.2)
    ...             ──┘

The bottleneck is the router's egress toward the operator, shaped by ``tc`` tbf, so every robot's
traffic to the operator shares one link of ``link_mbit``, as in the paper's experiment. A robot can
also get its own slower uplink (tbf on its egress). Processes run inside with ``ip netns exec``
(:meth:`Network.exec_argv`), so they talk over real TCP/UDP through the kernel and its queues.

Veth pairs are created directly inside their namespaces, so nothing is ever placed in the root
namespace, and deleting a run's namespaces deletes all of it, even after a crash of the builder.
Every name carries a random run id, so runs never collide and cleanup only touches its own run.
"""

from __future__ import annotations

import math
import os
import re
import secrets
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType

from dbml.core.errors import DbmlError

__all__ = [
    "MAX_QUEUE_BYTES",
    "MIN_QUEUE_BYTES",
    "NETNS_DIR",
    "OPERATOR",
    "Host",
    "Network",
    "TestbedError",
    "leftover_namespaces",
    "privilege_problem",
    "shaper_queue_bytes",
]

_PREFIX = "dbml-"
NETNS_DIR = "/run/netns"
"""Where ``ip netns add`` keeps a namespace's file."""
OPERATOR = "op"
"""The operator's host: its link is the shared one, the bottleneck every robot crosses."""
_ROUTER = "rt"
_ROBOT_NAME = re.compile(r"^[a-z][a-z0-9]{0,5}$")
_RUN_ID = re.compile(r"^[0-9a-f]{6}$")
_OPERATOR_SUBNET = 100  # 10.200.100.0/24; robots use 10.200.1.0/24 .. 10.200.99.0/24
_BURST_BYTES = 4_000
_BURST = f"{_BURST_BYTES * 8 // 1_000}kbit"
_LATENCY_S = 0.2
"""The longest a packet waits in a shaped link's queue at its rate; tbf drops what would wait
longer (a ``Network(queue_bytes=...)`` link holds those bytes whatever its rate instead)."""
_LATENCY = f"{round(_LATENCY_S * 1_000)}ms"
MIN_QUEUE_BYTES = 1_514
"""The smallest queue a link may be given: one full Ethernet frame (a smaller one carries none)."""
MAX_QUEUE_BYTES = 64 * 1024 * 1024
"""The largest: seconds of any rate the testbed's software links reach."""
_TBF_HANDLE = "1:"
_CLASSES_HANDLE = "10:"
_EXPEDITED_CLASS = "10:1"
_BULK_CLASS = "10:2"
_BULK_HANDLE = "20:"
_CLASS_RATE = "10gbit"
"""A DSCP-aware link's classes never limit: the tbf above them does; they only order."""
_DSCP_MASK = 0xFC
"""The TOS byte's DSCP bits (the low two are ECN)."""
_COMMAND_TIMEOUT_S = 10.0
_DOWN_RULE_PRIORITY = 100
"""The first ``ip rule`` priority of a down link's blackhole rules: two per host (from it, to
it), the operator's first, then each robot's."""
_CAP_NET_ADMIN = 12
_CAP_SYS_ADMIN = 21


class TestbedError(DbmlError):
    """The testbed cannot be built, changed or removed, or was given a bad value."""

    __test__ = False  # not a pytest test class despite the name


@dataclass(frozen=True, slots=True)
class Host:
    """One endpoint of the testbed: what a runner needs to start a process there and reach it."""

    name: str
    """Role name given by the caller (``"r1"``) or ``"op"`` for the operator."""
    netns: str
    """The real namespace name, for ``ip netns exec``."""
    address: str
    """Its IPv4 address inside the testbed, reachable from every other host."""


def privilege_problem() -> str | None:
    """None if this process can build namespaces, else a one-line reason (tests skip on it)."""
    if not hasattr(os, "geteuid"):
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return f"network namespaces need root (euid={os.geteuid()})"
    for tool in ("ip", "tc", "sysctl"):
        if shutil.which(tool) is None:
            return f"'{tool}' is not on PATH (PATH={os.environ.get('PATH', '')})"
    caps = _effective_capabilities()
    if caps is None:
        return "cannot read CapEff from /proc/self/status (not Linux?)"
    for bit, name in ((_CAP_SYS_ADMIN, "CAP_SYS_ADMIN"), (_CAP_NET_ADMIN, "CAP_NET_ADMIN")):
        if not caps >> bit & 1:
            return f"root without {name} (CapEff={caps:#x}), e.g. an unprivileged container"
    return None


def leftover_namespaces(prefix: str = _PREFIX) -> list[str]:
    """Names from ``ip netns list`` starting with ``prefix``: proves cleanup, finds crashed runs."""
    names = (line.split()[0] for line in _run(["ip", "netns", "list"]).splitlines() if line)
    return sorted(name for name in names if name.startswith(prefix))


class Network:
    """Robots and an operator in namespaces behind one shaped router; a context manager.

    Nothing exists until :meth:`build` (or ``with``); :meth:`close` removes everything this run
    created and is safe to call more than once.
    """

    run_id: str
    """Six lowercase hex characters in every namespace and interface name of this run."""
    hosts: dict[str, Host]
    """Every robot and ``"op"``; the router is internal."""
    robots: tuple[str, ...]
    link_mbit: float
    """The current bottleneck rate (router toward operator)."""
    uplinks_mbit: dict[str, float]
    """Robots whose own uplink is shaped, and at what rate."""
    expedited_tos: int | None
    """The shared link forwards packets with this TOS byte's DSCP first (strict priority, as a
    Wi-Fi access point's WMM or a DSCP-aware router does); None: one FIFO, the paper's link."""
    queue_bytes: int | None
    """The shared link's queue, in bytes, whatever its rate: a radio's buffer, which a fade
    does not shrink (OpenNetLab's gym sizes its drop-tail queue once, as bytes, and its traces
    change only the rate). None: what ``_LATENCY_S`` holds at the link's current rate, a
    shaper's (``shaper_queue_bytes``)."""

    def __init__(
        self,
        *,
        robots: Sequence[str] = ("r1", "r2"),
        link_mbit: float,
        uplinks_mbit: Mapping[str, float] | None = None,
        expedited_tos: int | None = None,
        queue_bytes: int | None = None,
        run_id: str | None = None,
    ) -> None:
        self.robots = _check_robots(robots)
        if queue_bytes is not None and (
            isinstance(queue_bytes, bool)
            or not isinstance(queue_bytes, int)
            or not MIN_QUEUE_BYTES <= queue_bytes <= MAX_QUEUE_BYTES
        ):
            raise TestbedError(
                f"queue_bytes={queue_bytes!r} must be an integer in "
                f"{MIN_QUEUE_BYTES}..{MAX_QUEUE_BYTES}"
            )
        self.queue_bytes = queue_bytes
        if expedited_tos is not None and (
            isinstance(expedited_tos, bool)
            or not isinstance(expedited_tos, int)
            or not 0 < expedited_tos <= _DSCP_MASK
            or expedited_tos & ~_DSCP_MASK
        ):
            raise TestbedError(
                f"expedited_tos={expedited_tos!r} must be a TOS byte with a DSCP and no ECN bits"
            )
        self.expedited_tos = expedited_tos
        self.link_mbit = _check_mbit("link_mbit", link_mbit)
        uplinks = dict(uplinks_mbit or {})
        for robot, mbit in uplinks.items():
            if robot not in self.robots:
                raise TestbedError(
                    f"uplink {robot!r} is not a robot (robots: {', '.join(self.robots)})"
                )
            _check_mbit(f"uplinks_mbit[{robot!r}]", mbit)
        self.uplinks_mbit = {robot: float(mbit) for robot, mbit in uplinks.items()}
        if run_id is None:
            run_id = secrets.token_hex(3)
        elif not isinstance(run_id, str) or not _RUN_ID.match(run_id):
            raise TestbedError(f"run_id={run_id!r} must be 6 lowercase hex characters")
        self.run_id = run_id
        self.hosts = {
            robot: Host(robot, self._netns(robot), f"10.200.{index + 1}.2")
            for index, robot in enumerate(self.robots)
        }
        self.hosts[OPERATOR] = Host(OPERATOR, self._netns(OPERATOR), f"10.200.{_OPERATOR_SUBNET}.2")
        self._created: list[str] = []
        self._built = False
        self._down: set[str] = set()

    @property
    def namespaces(self) -> list[str]:
        """All namespace names of this run, router included (whether built or not)."""
        return [*(host.netns for host in self.hosts.values()), self._netns(_ROUTER)]

    def build(self) -> Network:
        """Create namespaces, links, addresses, routes and shaping; on failure remove them all."""
        if self._built:
            raise TestbedError(f"network run_id={self.run_id} is already built")
        try:
            self._build()
        except BaseException as exc:
            problems = self._delete_namespaces()
            if problems and isinstance(exc, TestbedError):
                raise TestbedError(f"{exc}; cleanup also failed: {'; '.join(problems)}") from exc
            raise
        self._built = True
        return self

    def exec_argv(self, host: str, argv: Sequence[str]) -> list[str]:
        """The argv that runs ``argv`` inside ``host``'s namespace (needs root)."""
        if host not in self.hosts:
            raise TestbedError(
                f"host {host!r} is not in the testbed (hosts: {', '.join(self.hosts)})"
            )
        if isinstance(argv, str):
            raise TestbedError(f"argv={argv!r} must be a list of arguments, not a string")
        return ["ip", "netns", "exec", self.hosts[host].netns, *argv]

    def netns_path(self, host: str) -> str:
        """The file of ``host``'s namespace, for ``setns(2)`` (``ip netns`` keeps it there)."""
        if host not in self.hosts:
            raise TestbedError(
                f"host {host!r} is not in the testbed (hosts: {', '.join(self.hosts)})"
            )
        return f"{NETNS_DIR}/{self.hosts[host].netns}"

    def set_link_rate(self, mbit: float, *, host: str = OPERATOR) -> None:
        """Change a link's rate live (and bring it up if it was down); queued packets drain.

        ``host``: the operator's (the shared bottleneck, shaped at the router) or a robot's own
        uplink (shaped where it leaves the robot; the first change shapes it).
        """
        rate = _check_mbit("link_mbit" if host == OPERATOR else f"uplink_mbit[{host!r}]", mbit)
        self._check_built()
        if host == OPERATOR:
            router = self._netns(_ROUTER)
            tbf = self._tbf(self._router_if(OPERATOR), rate, self.queue_bytes)
            _run(["tc", "-n", router, "qdisc", "change", *tbf])
            if self.expedited_tos is not None:  # the bulk queue keeps its bound
                bulk = self._bulk_fifo(self._router_if(OPERATOR), rate, self.queue_bytes)
                _run(["tc", "-n", router, "qdisc", "change", *bulk])
            self.link_mbit = rate
        else:
            self._check_robot(host)
            verb = "change" if host in self.uplinks_mbit else "add"
            tbf = self._tbf(self._host_if(host), rate)
            _run(["tc", "-n", self._netns(host), "qdisc", verb, *tbf])
            self.uplinks_mbit[host] = rate
        if host in self._down:  # the rate first: what was queued drains at the new one
            self._bring_link_up(host)

    def take_link_down(self, *, host: str = OPERATOR) -> None:
        """Drop everything on ``host``'s link, both ways, until its next ``set_link_rate``.

        A radio out of range carries nothing either way: the router discards (silently, as
        a lost packet) what comes from the host and what goes to it, so TCP sees pure loss.
        The operator's link is the shared one (every robot loses it); a robot's is its own
        radio (the others go on). Policy rules rather than netem, which this kernel may lack;
        the tbf stays.
        """
        self._check_built()
        if host != OPERATOR:
            self._check_robot(host)
        if host in self._down:
            return
        router = self._netns(_ROUTER)
        matches = (["iif", self._router_if(host)], ["to", self._subnet(host)])
        for priority, match in zip(self._rule_priorities(host), matches, strict=True):
            _run(
                ["ip", "-n", router, "rule", "add", "priority", str(priority), *match, "blackhole"]
            )
        self._down.add(host)

    @property
    def down_hosts(self) -> frozenset[str]:
        """Hosts whose link is down: ``take_link_down`` adds one, ``set_link_rate`` removes it."""
        return frozenset(self._down)

    @property
    def link_down(self) -> bool:
        """Whether the operator's (shared) link is down."""
        return OPERATOR in self._down

    def _bring_link_up(self, host: str) -> None:
        router = self._netns(_ROUTER)
        for priority in self._rule_priorities(host):
            _run(["ip", "-n", router, "rule", "del", "priority", str(priority)])
        self._down.discard(host)

    def _check_built(self) -> None:
        if not self._built:
            raise TestbedError(f"network run_id={self.run_id} is not built")

    def _check_robot(self, host: str) -> None:
        if host not in self.robots:
            raise TestbedError(f"host={host!r} is not a robot (robots: {', '.join(self.robots)})")

    def _subnet(self, host: str) -> str:
        """``host``'s /24 (the router is .1 in it, the host .2)."""
        return f"{self.hosts[host].address.rsplit('.', 1)[0]}.0/24"

    def _rule_priorities(self, host: str) -> tuple[int, int]:
        """The ``ip rule`` priorities of ``host``'s two blackhole rules (from it, to it)."""
        index = 0 if host == OPERATOR else 1 + self.robots.index(host)
        return _DOWN_RULE_PRIORITY + 2 * index, _DOWN_RULE_PRIORITY + 2 * index + 1

    def close(self) -> None:
        """Delete every namespace this run created (their veth ends go with them); idempotent."""
        self._built = False
        problems = self._delete_namespaces()
        if problems:
            raise TestbedError(f"close of run_id={self.run_id} failed: {'; '.join(problems)}")

    def __enter__(self) -> Network:
        return self.build()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"Network(run_id={self.run_id!r}, robots={self.robots!r}, "
            f"link_mbit={self.link_mbit}, uplinks_mbit={self.uplinks_mbit!r})"
        )

    def _build(self) -> None:
        router = self._netns(_ROUTER)
        for netns in [router, *(host.netns for host in self.hosts.values())]:
            _run(["ip", "netns", "add", netns])
            self._created.append(netns)  # only what we made: a clash never deletes another run
            _run(["ip", "-n", netns, "link", "set", "lo", "up"])
        _run(["ip", "netns", "exec", router, "sysctl", "-qw", "net.ipv4.ip_forward=1"])
        for index, role in enumerate([*self.robots, OPERATOR]):
            subnet = _OPERATOR_SUBNET if role == OPERATOR else index + 1
            self._link(role, subnet)
        self._shape(router, self._router_if(OPERATOR), self.link_mbit, self.queue_bytes)
        if self.expedited_tos is not None:
            self._expedite(router, self._router_if(OPERATOR), self.expedited_tos)
        for robot, mbit in self.uplinks_mbit.items():
            self._shape(self._netns(robot), self._host_if(robot), mbit)

    def _link(self, role: str, subnet: int) -> None:
        """One veth pair host <-> router on 10.200.{subnet}.0/24, router .1, host .2."""
        netns, router = self._netns(role), self._netns(_ROUTER)
        host_if, router_if = self._host_if(role), self._router_if(role)
        veth = ["type", "veth", "peer", "name", router_if, "netns", router]
        _run(["ip", "link", "add", host_if, "netns", netns, *veth])
        _run(["ip", "-n", netns, "addr", "add", f"10.200.{subnet}.2/24", "dev", host_if])
        _run(["ip", "-n", router, "addr", "add", f"10.200.{subnet}.1/24", "dev", router_if])
        _run(["ip", "-n", netns, "link", "set", host_if, "up"])
        _run(["ip", "-n", router, "link", "set", router_if, "up"])
        _run(["ip", "-n", netns, "route", "add", "default", "via", f"10.200.{subnet}.1"])

    def _shape(
        self, netns: str, interface: str, mbit: float, queue_bytes: int | None = None
    ) -> None:
        _run(["tc", "-n", netns, "qdisc", "add", *self._tbf(interface, mbit, queue_bytes)])

    def _expedite(self, netns: str, interface: str, tos: int) -> None:
        """Under the link's tbf, two classes in strict priority: ``tos`` first, the rest after.

        The bulk class keeps the tbf's own queue bound (``queue_bytes``, or ``_LATENCY_S`` at the
        link's rate); an expedited packet waits at most for the one being sent.
        """
        tc, dev = ["tc", "-n", netns], ["dev", interface]
        default = ["default", _BULK_CLASS.partition(":")[2]]  # what no filter matches
        classes = [*dev, "parent", f"{_TBF_HANDLE}1", "handle", _CLASSES_HANDLE, "htb", *default]
        _run([*tc, "qdisc", "add", *classes])
        under = [*dev, "parent", _CLASSES_HANDLE]
        for classid, prio in ((_EXPEDITED_CLASS, "0"), (_BULK_CLASS, "1")):
            shape = ["htb", "rate", _CLASS_RATE, "ceil", _CLASS_RATE, "prio", prio]
            _run([*tc, "class", "add", *under, "classid", classid, *shape])
        _run([*tc, "qdisc", "add", *self._bulk_fifo(interface, self.link_mbit, self.queue_bytes)])
        match = ["u32", "match", "ip", "dsfield", f"{tos:#x}", f"{_DSCP_MASK:#x}"]
        rule = ["protocol", "ip", "prio", "1", *match, "flowid", _EXPEDITED_CLASS]
        _run([*tc, "filter", "add", *under, *rule])

    @staticmethod
    def _bulk_fifo(interface: str, mbit: float, queue_bytes: int | None) -> list[str]:
        limit = shaper_queue_bytes(mbit) if queue_bytes is None else queue_bytes
        where = ["dev", interface, "parent", _BULK_CLASS, "handle", _BULK_HANDLE]
        return [*where, "bfifo", "limit", str(limit)]

    @staticmethod
    def _tbf(interface: str, mbit: float, queue_bytes: int | None = None) -> list[str]:
        rate = f"{round(mbit * 1000)}kbit"  # kbit keeps fractional Mbit exact to 1 kbit/s
        bound = ["latency", _LATENCY] if queue_bytes is None else ["limit", str(queue_bytes)]
        shape = ["rate", rate, "burst", _BURST, *bound]
        return ["dev", interface, "root", "handle", _TBF_HANDLE, "tbf", *shape]

    def _delete_namespaces(self) -> list[str]:
        """Delete what this run created, newest first; return problems instead of stopping."""
        problems: list[str] = []
        for netns in reversed(list(self._created)):
            try:
                _run(["ip", "netns", "delete", netns])
            except TestbedError as exc:
                if netns in leftover_namespaces(netns):
                    problems.append(str(exc))
                    continue  # still there: keep it listed so a later close() retries
            self._created.remove(netns)
        return problems

    def _netns(self, role: str) -> str:
        return f"{_PREFIX}{self.run_id}-{role}"

    def _host_if(self, role: str) -> str:
        return f"d{self.run_id}{role}"  # <= 1 + 6 + 6 = 13 characters (IFNAMSIZ allows 15)

    def _router_if(self, role: str) -> str:
        return f"r{self.run_id}{role}"


def _check_robots(robots: Sequence[str]) -> tuple[str, ...]:
    if isinstance(robots, str):
        raise TestbedError(f"robots={robots!r} must be a sequence of names, not one string")
    names = tuple(robots)
    if not names:
        raise TestbedError("robots=() must name at least one robot")
    if len(names) >= _OPERATOR_SUBNET:
        raise TestbedError(f"robots has {len(names)} names; at most {_OPERATOR_SUBNET - 1}")
    seen: set[str] = set()
    for name in names:
        if not isinstance(name, str) or not _ROBOT_NAME.match(name):
            raise TestbedError(
                f"robot name {name!r} must match {_ROBOT_NAME.pattern} "
                "(it goes into 15-character interface names)"
            )
        if name in (OPERATOR, _ROUTER):
            raise TestbedError(f"robot name {name!r} is reserved (op, rt)")
        if name in seen:
            raise TestbedError(f"robot name {name!r} appears twice in robots")
        seen.add(name)
    return names


def shaper_queue_bytes(mbit: float) -> int:
    """The bytes a link shaped at ``mbit`` queues: ``_LATENCY_S`` of its rate and its burst.

    What tbf computes from its ``latency``; a ``Network(queue_bytes=...)`` of this at a
    radio's usual rate keeps that queue through the radio's fades.
    """
    return round(_check_mbit("mbit", mbit) * 1e6 / 8 * _LATENCY_S) + _BURST_BYTES


def _check_mbit(field: str, mbit: float) -> float:
    if isinstance(mbit, bool) or not isinstance(mbit, int | float):
        raise TestbedError(f"{field}={mbit!r} must be a number of Mbit/s")
    if not math.isfinite(mbit) or mbit <= 0:
        raise TestbedError(f"{field}={mbit!r} must be a finite number > 0")
    if round(mbit * 1000) < 1:
        raise TestbedError(f"{field}={mbit!r} is below tc's 1 kbit/s resolution")
    return float(mbit)


def _run(argv: Sequence[str]) -> str:
    """Run one command; the only place the testbed starts processes, so failures read alike."""
    command = " ".join(argv)
    try:
        done = subprocess.run(
            list(argv),
            check=False,
            capture_output=True,
            text=True,
            timeout=_COMMAND_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired as exc:
        raise TestbedError(f"command '{command}' timed out after {_COMMAND_TIMEOUT_S} s") from exc
    except OSError as exc:
        raise TestbedError(f"command '{command}' could not start: {exc}") from exc
    if done.returncode != 0:
        stderr = " ".join(done.stderr.split()) or "(no stderr)"
        raise TestbedError(f"command '{command}' failed (exit {done.returncode}): {stderr}")
    return done.stdout


def _effective_capabilities() -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("CapEff:"):
                    return int(line.split()[1], 16)
    except (OSError, ValueError):
        return None
    return None
