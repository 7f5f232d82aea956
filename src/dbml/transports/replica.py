"""One process's replica of the parameter values: the store every transport is built on.

It knows no middleware. It holds each name's newest value with the order of that write (its
stamp) and its writer; takes this process's writes at once (read-your-writes: ``get`` sees a
write before ``set`` returns) and hands them to its sync through an
``OrderedSender`` (one slot per name: a name's newer write replaces its older one still queued),
so ``set`` never waits for the network; holds at most ``MAX_PARAMS`` names from the network
(a flood is refused and logged once); and tells its watchers of every change outside its lock,
one thread at a time, in the order the changes were made.

What each middleware adds is its sync: how a write goes out (``send``) and what arrives.
Values arrive in one of two orders:

- **by stamp** (``merge``): the writer's stamp travels with the value (zenoh, memory), and the
  newest (stamp, writer) wins everywhere, whatever the order of arrival;
- **by arrival** (``arrived``): the network holds the truth and pushes it in its own order (the
  ROS master, a ROS 2 node's events), so what arrives is newer than what is held, except while
  this process's own write of that name is still pending: the network has not seen it yet, and
  what it says of the name is older. A question's answer (``asked_at``) is older than anything
  written or heard since it was asked. A deletion arriving so forgets the name (the network
  keeps the truth); a deletion by stamp is held, so a newcomer does not revive the name.

What ``set`` refuses is the same on every transport (``ParamStore``): ``check_write`` below.
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from dbml.core.errors import TransportError
from dbml.core.spec import short_repr
from dbml.protocol.keys import is_host_name
from dbml.protocol.schema import ParamValue, check_param_value, lookup
from dbml.transports.base import Handle, check_topic
from dbml.transports.callbacks import CallbackList
from dbml.transports.overflow import Overflow
from dbml.transports.worker import DEFAULT_SENDER_CAPACITY, FLUSH_TIMEOUT_S, OrderedSender

__all__ = [
    "EVICTION_LOOKS",
    "MAX_PARAMS",
    "MAX_QUEUED_WRITES",
    "Entry",
    "Replica",
    "Write",
    "check_write",
]

MAX_PARAMS = 65_536
"""The most parameter names held from the network (deletions held by stamp included: a deleted
name is kept, so a newcomer does not revive it). A fleet of 160 robots with 4 channels writes 7
names per channel and a dozen global ones, about 4,500: this is 14 times that (the optimizer
tracks up to 4,096 channels, 28,672 names). Any peer can write, so past this a new name from
the network is refused (or, where the sync says which may go, the oldest of those is given up),
and logged once per flood; names held are still updated. This process's
own names are counted apart, against the same bound, so no flood can refuse them: past it,
``set`` of a new name raises. A name costs a few hundred bytes: tens of MB at most."""
EVICTION_LOOKS = 64
"""How many of the oldest names a full store looks at to find one to give up, per new name."""
MAX_QUEUED_WRITES = DEFAULT_SENDER_CAPACITY
"""The most writes waiting for the network: a name's newer write replaces its queued one, so
this bounds batches and distinct names; past it the oldest is dropped (``OrderedSender``)."""


def check_write(name: str, value: object) -> ParamValue:
    """``value`` if a store may take ``name=value`` from this process; else why not.

    ``TransportError`` for a value that is not a bool, number, string or None, and for a name
    outside the wire schema (``dbml.protocol.schema``); ``ParamError`` for a value outside the
    schema's range. Each message names the name and the value.
    """
    try:
        checked = check_param_value(value)
    except TransportError:
        raise TransportError(
            f"{name}={short_repr(value)} is not a parameter value: a bool, number, string or None"
        ) from None
    try:
        found = lookup(check_topic(name))
    except TransportError:
        found = None
    if found is None:
        raise TransportError(
            f"{name}={short_repr(value)}: {short_repr(name)} is not a parameter of dbml's "
            "schema (/dbm/<field> or [topic]/dbm/<field>)"
        )
    if checked is not None:
        found[0].check(checked, name=name)  # the schema's range (one parse of the name)
    return checked


@dataclass(frozen=True, slots=True)
class Entry:
    """A name's newest write held here: its value (None: deleted), order and writer."""

    value: ParamValue
    stamp: int
    writer: str


@dataclass(frozen=True, slots=True)
class Write:
    """A write of this process, as the replica hands it to its sync (on the sender thread).

    One name (``set``) or several at once (``set_many``, ``batch``), under one stamp; ``host``
    is ``set_many``'s: the values concern that host's channels only.
    """

    values: Mapping[str, ParamValue]
    stamp: int
    writer: str
    host: str | None = None
    batch: bool = False


def _same(a: ParamValue, b: ParamValue) -> bool:
    """Equal and of one type: ``True`` and ``1`` are different writes."""
    return type(a) is type(b) and a == b


class Replica:
    """One process's parameter values (a ``ParamStore``); ``writer`` names its writes.

    ``send`` hands one ``Write`` to the network; it runs on the replica's sender thread, in
    order, and may block. ``threaded=False`` calls it on the writer's thread instead, after the
    write is applied and told here (the in-process network, whose delivery is synchronous).
    ``batches=False`` queues a ``set_many`` as one write per name, each in its name's slot (a
    middleware without a multi-set). ``check_name`` adds the middleware's own rule for a name
    (ROS 2 allows fewer characters) to ``check_write``. ``clock_ns`` stamps writes: stamps only
    grow, and a write's is newer than every held write of its names. ``on_exit`` runs on the
    sender thread when it ends (to release what ``send`` holds per thread).
    """

    def __init__(
        self,
        writer: str,
        *,
        send: Callable[[Write], None],
        log: logging.Logger,
        clock_ns: Callable[[], int] = time.time_ns,
        threaded: bool = True,
        batches: bool = True,
        check_name: Callable[[str], object] | None = None,
        max_params: int = MAX_PARAMS,
        sender_name: str = "dbml-param-send",
        on_exit: Callable[[], object] | None = None,
    ) -> None:
        self.writer = writer
        self._send = send
        self._clock_ns = clock_ns
        self._batches = batches
        self._check_name = check_name
        self._max_params = max_params
        self._lock = threading.Lock()
        self._entries: dict[str, Entry] = {}
        """The newest write of each name: up to ``max_params`` from the network, and ours."""
        self._names: list[str] = []
        """``_entries``' names, sorted: a prefix's names without a look at every other (a
        session answers a robot's question about its channel from a fleet's names)."""
        self._own: set[str] = set()
        """Names this process wrote (``max_params`` at most), whoever wrote them last."""
        self._heard: OrderedDict[str, None] = OrderedDict()
        """Names only the network wrote, oldest first: what a full store may give up."""
        self.keep: Callable[[str], bool] | None = None
        """Which names the network wrote must stay when the store is full: the sync's rule (a
        live channel's, the globals); None keeps every one, and a new name is refused. Called
        under the replica's lock: it must be a quick local read."""
        self._pending: dict[str, int] = {}
        """Names whose write of ours the network has not taken yet, with that write's stamp."""
        self._last = 0
        """The newest stamp given out here."""
        self._full = Overflow("parameter names", max_params, log=log)
        self.watchers: CallbackList[[str, ParamValue]] = CallbackList()
        self._outbox: dict[str, ParamValue] = {}
        """Changes committed and not told yet, in the order they were committed (a name's newer
        change replaces its older one and moves to the end): at most one per name held."""
        self._telling = False
        """Whether a thread is telling the watchers now: the others leave their changes to it."""
        self._sender: OrderedSender[Write] | None = None
        if threaded:
            self._sender = OrderedSender(
                self._send_one,
                name=sender_name,
                log=log,
                capacity=MAX_QUEUED_WRITES,
                describe=lambda write: f"parameter write {', '.join(write.values)}",
                on_exit=on_exit,
            )

    # -- this process's writes ----------------------------------------------------------------

    def set(self, name: str, value: ParamValue) -> None:
        """Write ``name`` here, queue it for the network, then tell the watchers."""
        self._write({name: value}, host=None, batch=False)

    def set_many(self, values: Mapping[str, ParamValue], *, host: str | None = None) -> None:
        """Write every value as one update (one stamp); all are checked before any is taken."""
        if values:
            self._write(dict(values), host=host, batch=True)

    def _check(self, name: str, value: ParamValue) -> None:
        check_write(name, value)
        if self._check_name is not None:
            self._check_name(name)

    def _write(self, values: dict[str, ParamValue], *, host: str | None, batch: bool) -> None:
        for name, value in values.items():
            self._check(name, value)
        if host is not None and not is_host_name(host):
            raise TransportError(f"host={host!r} must be letters, digits and _-.~ only")
        with self._lock:
            fresh = [name for name in values if name not in self._own]
            if len(self._own) + len(fresh) > self._max_params:
                name = fresh[max(0, self._max_params - len(self._own))]
                raise TransportError(
                    f"{name}={short_repr(values[name])}: this process wrote "
                    f"{len(self._own)} parameter names, and {self._max_params} is the most"
                )
            stamp = self._stamp_locked(values)
            for name, value in values.items():
                self._put_locked(name, Entry(value, stamp, self.writer))
                self._own.add(name)
                self._heard.pop(name, None)
                self._pending[name] = stamp
            if batch and not self._batches:
                writes = [Write({n: v}, stamp, self.writer, host) for n, v in values.items()]
            else:
                writes = [Write(values, stamp, self.writer, host, batch)]
            if self._sender is not None:
                # Queued under the lock: no older stamp of a name is queued after a newer one.
                for write in writes:
                    slot = None if write.batch else next(iter(write.values))
                    dropped = self._sender.put(write, slot=slot)
                    if dropped is not None:
                        self._settle_locked(dropped)
            self._told_locked(values.items())
        self._tell()
        if self._sender is None:
            for write in writes:
                self._send_one(write)

    def _stamp_locked(self, names: Iterable[str]) -> int:
        """A stamp newer than every one given out here and than every held write of ``names``."""
        stamp = max(self._clock_ns(), self._last + 1)
        for name in names:
            held = self._entries.get(name)
            if held is not None:
                stamp = max(stamp, held.stamp + 1)
        self._last = stamp
        return stamp

    def _send_one(self, write: Write) -> None:
        try:
            self._send(write)
        finally:
            with self._lock:
                self._settle_locked(write)

    def _settle_locked(self, write: Write) -> None:
        """``write`` left the queue (sent, failed or dropped): its names are pending no more."""
        for name in write.values:
            if self._pending.get(name) == write.stamp:
                del self._pending[name]

    def pending(self, name: str) -> bool:
        """Whether a write of ``name`` by this process is still waiting for the network."""
        with self._lock:
            return name in self._pending

    def unsent(self) -> int:
        """How many names have a write of this process waiting for the network."""
        with self._lock:
            return len(self._pending)

    def wrote(self, name: str) -> bool:
        """Whether this process ever wrote ``name``."""
        with self._lock:
            return name in self._own

    def current(self, write: Write) -> dict[str, ParamValue]:
        """What of ``write`` is still the newest here (nothing newer was written or heard)."""
        with self._lock:
            return {
                name: value
                for name, value in write.values.items()
                if (held := self._entries.get(name)) is not None and held.stamp == write.stamp
            }

    def flush(self, timeout_s: float = FLUSH_TIMEOUT_S) -> bool:
        """Wait until every queued write was handed to the network; False after ``timeout_s``."""
        return True if self._sender is None else self._sender.flush(timeout_s)

    def close(self, timeout_s: float = FLUSH_TIMEOUT_S) -> bool:
        """Send what is queued (bounded), then stop the sender; False if some was left unsent."""
        return True if self._sender is None else self._sender.close(timeout_s)

    @property
    def alive(self) -> bool:
        """False once the sender thread died (a failed send does not end it)."""
        return self._sender is None or self._sender.alive

    # -- reading ------------------------------------------------------------------------------

    def get(self, name: str) -> ParamValue:
        """The newest value known of ``name``; None when unset or deleted."""
        with self._lock:
            held = self._entries.get(name)
        return None if held is None else held.value

    def entry(self, name: str) -> Entry | None:
        """The newest write of ``name`` held here, deletions included."""
        with self._lock:
            return self._entries.get(name)

    def entries(self, prefix: str = "") -> list[tuple[str, Entry]]:
        """Every write held here whose name starts with ``prefix``, deletions included."""
        with self._lock:
            return [(name, self._entries[name]) for name in self._names_locked(prefix)]

    def snapshot(self, prefix: str = "/") -> dict[str, ParamValue]:
        """Every set value whose name starts with ``prefix``."""
        with self._lock:
            return {
                name: held.value
                for name in self._names_locked(prefix)
                if (held := self._entries[name]).value is not None
            }

    def _names_locked(self, prefix: str) -> list[str]:
        """The names held that start with ``prefix``, in order (lock held)."""
        names = self._names
        if not prefix:
            return list(names)
        start = end = bisect.bisect_left(names, prefix)
        while end < len(names) and names[end].startswith(prefix):
            end += 1
        return names[start:end]

    def _put_locked(self, name: str, entry: Entry) -> None:
        """Hold ``entry`` as ``name``'s newest write (lock held)."""
        if name not in self._entries:
            bisect.insort(self._names, name)
        self._entries[name] = entry

    def _drop_locked(self, name: str) -> None:
        """Forget ``name`` (lock held; it is held)."""
        del self._entries[name]
        del self._names[bisect.bisect_left(self._names, name)]

    def watch(self, callback: Callable[[str, ParamValue], None]) -> Handle:
        """Call ``callback(name, value)`` on every change, this process's or the network's."""
        return self.watchers.add(callback)

    def __len__(self) -> int:
        """How many names are held, deletions held by stamp included."""
        with self._lock:
            return len(self._entries)

    # -- what arrives -------------------------------------------------------------------------

    def mark(self) -> int:
        """A stamp for a question asked now: its answer is ``arrived(..., asked_at=mark)``."""
        with self._lock:
            self._last = max(self._clock_ns(), self._last + 1)
            return self._last

    def merge(self, name: str, value: ParamValue, *, stamp: int, writer: str) -> bool:
        """A write from the network ordered by its stamp: held if newer; True if it was."""
        if writer == self.writer:
            return False  # ours, applied when it was made
        with self._lock:
            held = self._entries.get(name)
            if held is not None and (held.stamp, held.writer) >= (stamp, writer):
                return False
            if held is None:
                if not self._room_locked():
                    return False
                self._heard[name] = None
            self._put_locked(name, Entry(value, stamp, writer))
            self._told_locked([(name, value)])
        self._tell()
        return True

    def arrived(
        self,
        name: str,
        value: ParamValue,
        *,
        writer: str,
        asked_at: int | None = None,
        supersede: bool = False,
    ) -> bool:
        """A value the network pushed, newer than what is held: True if it changed anything.

        Not while this process's write of ``name`` is pending (the network has not seen it
        yet), unless ``supersede`` (the network took a newer one: the pending write is
        obsolete and will not be sent). ``asked_at``: an answer to a question asked then, older
        than anything written or heard since. ``None`` forgets the name.
        """
        with self._lock:
            if supersede:
                self._pending.pop(name, None)
            elif name in self._pending:
                return False
            held = self._entries.get(name)
            if asked_at is not None and held is not None and held.stamp > asked_at:
                return False
            if value is None:
                if held is None:
                    return False
                self._drop_locked(name)
                self._heard.pop(name, None)
                size = len(self._entries)
                changed = held.value is not None  # a deletion held here already is none
            else:
                if held is not None and _same(held.value, value):
                    return False
                if held is None:
                    if not self._room_locked():
                        return False
                    if name not in self._own:
                        self._heard[name] = None
                self._put_locked(name, Entry(value, self._stamp_locked([name]), writer))
                size, changed = -1, True
            if changed:
                self._told_locked([(name, value)])
        if size >= 0:
            self._full.room(size)
        self._tell()
        return changed

    def forget(self, prefix: str) -> list[str]:
        """Forget the names under ``prefix`` that the network gave (their source left).

        Names this process wrote stay: it may write them again, or hand them on.
        """
        with self._lock:
            gone = [
                name
                for name in self._entries
                if name.startswith(prefix) and name not in self._own and name not in self._pending
            ]
            for name in gone:
                del self._entries[name]
                self._heard.pop(name, None)
            if gone:
                self._names = sorted(self._entries)
            size = len(self._entries)
            self._told_locked((name, None) for name in gone)
        self._full.room(size)
        self._tell()
        return gone

    # -- telling the watchers -----------------------------------------------------------------

    def _told_locked(self, changes: Iterable[tuple[str, ParamValue]]) -> None:
        """Queue committed changes for the watchers (lock held: in the order they were made)."""
        for name, value in changes:
            self._outbox.pop(name, None)
            self._outbox[name] = value

    def _tell(self) -> None:
        """Tell the watchers every queued change, in order, outside the lock.

        One thread tells at a time: two threads that each told their own change could tell it
        in the other order than they made it, and a reader would keep the older value for good
        (a network merge told after a newer local write). A thread that finds another telling
        leaves its change to it, so ``set`` may return before its watchers ran while another
        thread tells; a watcher that writes has its change told after its own returns.
        """
        while True:
            with self._lock:
                if self._telling or not self._outbox:
                    return
                self._telling = True
                changes, self._outbox = self._outbox, {}
            try:
                for name, value in changes.items():
                    self.watchers.fire(name, value)
            finally:
                with self._lock:
                    self._telling = False

    def _room_locked(self) -> bool:
        """Whether a new name from the network fits; a refusal is counted (logged per flood).

        A full store gives up the oldest name the network wrote that ``keep`` lets go (a
        flood's, for a channel nobody publishes): told as deleted, and served no more.
        """
        if len(self._entries) < self._max_params:
            return True
        if self.keep is not None and self._evict_locked(self.keep):
            return True
        self._full.refuse()
        return False

    def _evict_locked(self, keep: Callable[[str], bool]) -> bool:
        """Give up the oldest name the network wrote that ``keep`` lets go; False if none.

        At most ``EVICTION_LOOKS`` names are looked at; those kept go to the end, so the next
        look starts further on.
        """
        for _ in range(min(EVICTION_LOOKS, len(self._heard))):
            name = next(iter(self._heard))
            if name in self._own or keep(name):
                self._heard.move_to_end(name)
                continue
            del self._heard[name]
            self._drop_locked(name)
            self._told_locked([(name, None)])
            self._full.refuse()  # counted as a refusal: a flood is logged once either way
            return True
        return False

    @property
    def refused(self) -> int:
        """New names from the network refused so far (the store was full)."""
        return self._full.total
