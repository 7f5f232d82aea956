"""The ROS parameter server's half of the store: the master's pushes in, this process's writes out.

The values are a ``Replica`` (``dbml.transports.replica``), ordered by arrival: the master holds
the truth and pushes every change (``subscribeParam``, then ``paramUpdate`` calls to a small
XML-RPC endpoint of this process), so reads are served here and nothing polls the master per
message. A write goes to the master from the replica's sender thread (a write may come from
inside the master's own push): ``set`` never blocks.

The master pushes every write back, this process's own too, in the order it took them. While a
write of ours is queued, every push of its name is older (the replica skips it); once it is
sent, pushes of that name are still older until its echo, the master's push of it back, comes:
those are skipped here, never taking the value back, and the echo itself is no change. An echo
not back within ``ECHO_WAIT_S`` is taken as lost, and pushes apply again.

Nothing here imports rospy: the master's API is XML-RPC (``dbml.transports.ros1.master``).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Final
from xmlrpc.server import SimpleXMLRPCServer

from dbml.core.errors import TransportError
from dbml.protocol.schema import ParamValue
from dbml.transports.replica import MAX_PARAMS, Replica, Write
from dbml.transports.ros1.master import CALL_TIMEOUT_S, MasterClient
from dbml.transports.worker import FLUSH_TIMEOUT_S, BackgroundThread

__all__ = ["ECHO_WAIT_S", "MAX_AWAITED_ECHOES", "MAX_EARLY_PUSHES", "Ros1Params", "flatten"]

log = logging.getLogger("dbml.ros1")

ECHO_WAIT_S = 5.0
"""How long this process's write of a name, once handed to the master, waits for its echo (the
master's push of it back); until then pushes of that name are older than it and skipped. The
master's call lasts at most ``CALL_TIMEOUT_S``, and a live master pushes at once. Past it the
echo is taken as lost: the master's pushes apply."""
MAX_AWAITED_ECHOES = 64
"""The most writes of one name handed to the master whose echoes are awaited: a live master
echoes within milliseconds, so there are a few. Past it the oldest is forgotten (its echo, when
it comes, is skipped as an older push): a name written fast while echoes are lost stays bounded."""
MAX_EARLY_PUSHES = 4096
"""The most pushes kept while the parameter subscription's call runs (they are newer than the
tree it returns, so they are applied after it). That call lasts at most ``CALL_TIMEOUT_S``, and
a fleet's writes in that time are a few per channel: 160 robots with 4 channels write a few
hundred. Anyone can call the push endpoint, so past this a push is not kept: the whole tree is
read again once the subscription is in (what the pushes said is in it), and the flood is
logged once, with a count."""
_SCALARS = (bool, int, float, str)
_OK: Final = [1, "", 0]
"""An XML-RPC API's success: code, message, value."""
_Echo = tuple[ParamValue, float]
"""A value handed to the master, and when its echo counts as lost."""


def flatten(name: str, value: object, out: dict[str, ParamValue]) -> None:
    """Parameter-server values as leaves: ``{'dbm': {'x': 1}}`` at ``/`` is ``/dbm/x = 1``."""
    if isinstance(value, dict):
        for key, sub in value.items():
            flatten(f"{name.rstrip('/')}/{key}", sub, out)
    elif isinstance(value, _SCALARS):
        out[name] = value  # lists and binary values are not dbml parameters


def _same(a: ParamValue, b: ParamValue) -> bool:
    """Equal and of one type: ``True`` and ``1`` are different writes."""
    return type(a) is type(b) and a == b


def _under(name: str, namespace: str) -> bool:
    return namespace in {"/", name} or name.startswith(namespace + "/")


class Ros1Params:
    """The parameter server, mirrored in ``replica`` (this transport's ``ParamStore``).

    ``master`` is the master's API (its calls from the sender thread use that thread's own
    connection, closed when it ends; its timeout is the subscription's too); ``host`` and
    ``bind`` are where the push endpoint listens.
    """

    def __init__(
        self,
        master: MasterClient,
        node_name: str,
        host: str,
        bind: str,
        *,
        clock: Callable[[], float] = time.monotonic,
        max_params: int = MAX_PARAMS,
    ) -> None:
        self._master = master
        self._clock = clock
        self._lock = threading.Lock()
        self._echoes: dict[str, deque[_Echo]] = {}
        """Our writes handed to the master whose echo has not come, by name, oldest first."""
        # Pushes that arrive while the subscription call runs, applied after the tree it returns.
        self._early: list[tuple[str, str, object]] | None = []
        self._early_dropped = 0
        """Pushes not kept in ``_early``, which was full (``MAX_EARLY_PUSHES``)."""
        self.replica = Replica(
            node_name,
            send=self._write,
            log=log,
            batches=False,  # ROS 1 has no multi-set: a name's newest write replaces its older
            max_params=max_params,
            sender_name="dbml-ros1-param-send",
            on_exit=master.close,  # the sender thread's own connection
        )
        self._server = SimpleXMLRPCServer((bind, 0), logRequests=False, allow_none=True)
        self._server.register_function(self._param_update, "paramUpdate")  # type: ignore[arg-type]
        self._server.register_function(lambda _caller: [1, "", os.getpid()], "getPid")
        self._server.register_function(lambda _caller, _msg="": _OK, "shutdown")
        port = self._server.server_address[1]
        self._api = f"http://{host}:{port}/"
        # A caller id of its own: the master would shut down a node re-registered at another URI.
        self._subscriber = MasterClient(
            master.uri, caller_id=f"{node_name}/dbml_params", timeout_s=master.timeout_s
        )
        self._thread = BackgroundThread(
            self._server.serve_forever, name="dbml-ros1-params", log=log
        ).start()
        try:
            tree = self._subscriber.call("subscribeParam", self._api, "/")
        except TransportError:
            self.replica.close(0)
            self._stop_server()
            raise
        self._settle("/", tree)
        if self._early_dropped:
            self._reread()

    def _settle(self, caller: str, tree: object) -> None:
        """Apply a whole tree read from the master, then the pushes kept meanwhile, in order.

        Pushes keep arriving while they are applied: they are kept too, until none is left, and
        from then on each applies as it arrives (on the push endpoint's one thread).
        """
        if tree is not None:
            self._apply(caller, "/", tree)
        while True:
            with self._lock:
                early = self._early or []
                self._early = [] if early else None
            if not early:
                return
            for pusher, key, value in early:
                self._apply(pusher, key, value)

    def _reread(self) -> None:
        """Pushes were dropped while subscribing: read the whole tree again and apply it.

        Pushes that arrive meanwhile are newer than the tree read: kept and applied after it,
        as at the subscription (once: a flood that outlasts it is not chased).
        """
        with self._lock:
            dropped, self._early_dropped = self._early_dropped, 0
            self._early = []
        log.warning(
            "%d parameter pushes arrived while subscribing, more than the %d kept: reading "
            "every parameter again",
            MAX_EARLY_PUSHES + dropped,
            MAX_EARLY_PUSHES,
        )
        try:
            tree: object = self._subscriber.call("getParam", "/")
        except TransportError as err:
            log.warning("reading the parameters again failed: %s", err)
            tree = None
        self._settle("/master", tree)
        with self._lock:
            dropped, self._early_dropped = self._early_dropped, 0
        if dropped:
            log.warning("%d more parameter pushes were not kept while reading again", dropped)

    def _param_update(self, caller: str, key: str, value: object) -> list[object]:
        """The master's push: a key (with a trailing ``/``) and its new value; ``{}`` deletes."""
        with self._lock:
            if self._early is not None:  # newer than a tree read, which is not applied yet
                if len(self._early) < MAX_EARLY_PUSHES:
                    self._early.append((caller, key, value))
                else:
                    self._early_dropped += 1  # read again whole once subscribed
                return _OK
        self._apply(caller, key, value)
        return _OK

    def _apply(self, caller: str, key: str, value: object) -> None:
        """One push: the names under its key that it lacks are deleted, the others set.

        Deletions first, as the master's tree says. Names of our writes still awaiting their
        echo are left as they are (``_awaiting_echo``); the replica skips those still queued.
        """
        namespace = key.rstrip("/") or "/"
        fresh: dict[str, ParamValue] = {}
        flatten(namespace, value, fresh)
        with self._lock:
            awaiting = self._awaiting_echo(namespace, fresh)
        replica = self.replica
        for name, _held in replica.entries():
            if _under(name, namespace) and name not in fresh and name not in awaiting:
                replica.arrived(name, None, writer=caller)
        for name, new in fresh.items():
            if name not in awaiting:
                replica.arrived(name, new, writer=caller)

    def _awaiting_echo(self, namespace: str, fresh: Mapping[str, ParamValue]) -> set[str]:
        """The names under a push's ``namespace`` whose push is older than our write of them.

        The master pushes in the order it took the writes: until the echo of our newest write of
        a name, a push of that name was taken before it. Our writes' echoes (our values, pushed
        at that very name, in the order sent) are counted off; the newest one's ends the wait,
        and so does ``ECHO_WAIT_S``: the push then applies as any other (no change, for an echo).
        """
        now = self._clock()
        awaiting: set[str] = set()
        for name in [n for n in self._echoes if _under(n, namespace)]:
            echoes = self._echoes[name]
            while echoes and now >= echoes[0][1]:
                echoes.popleft()  # lost
            if (
                echoes
                and name == namespace
                and fresh.keys() <= {name}  # a value or a deletion at the name, as we write
                and _same(fresh.get(name), echoes[0][0])
            ):
                echoes.popleft()  # the echo of our oldest write sent
            if echoes:
                awaiting.add(name)
            else:
                del self._echoes[name]
        return awaiting

    def _write(self, write: Write) -> None:
        """One write on the parameter server (on the replica's sender thread)."""
        ((name, value),) = write.values.items()
        awaited = (value, self._clock() + ECHO_WAIT_S)
        with self._lock:
            echoes = self._echoes.setdefault(name, deque())
            if len(echoes) >= MAX_AWAITED_ECHOES:
                echoes.popleft()
            echoes.append(awaited)
        echoed = False
        try:
            if value is None:  # deleting a name the master lacks changes nothing: no push
                echoed = self._master.call("deleteParam", name, missing_ok=True) is not None
            else:
                echoed = self._master.call("setParam", name, value) is not None
        finally:
            if not echoed:  # failed, or nothing to push back: await no echo of it
                with self._lock:
                    left = self._echoes.get(name)
                    if left and left[-1] is awaited:
                        left.pop()
                        if not left:
                            del self._echoes[name]

    def confirm(self, name: str, *, timeout_s: float) -> bool:
        """Whether the master holds what this process holds of ``name``, once it is sent."""
        if not self.replica.flush(timeout_s):
            return False
        try:
            held = self._master.call("getParam", name, missing_ok=True)
        except TransportError as err:
            log.warning("confirming %s: %s", name, err)
            return False
        return bool(held == self.replica.get(name))

    @property
    def alive(self) -> bool:
        """False once the push endpoint's or the sender's thread died."""
        return self._thread.alive and self.replica.alive

    def _stop_server(self) -> None:
        self._subscriber.close()
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(CALL_TIMEOUT_S)

    def close(self) -> None:
        """Send the queued writes (bounded), unsubscribe from the master, stop the endpoint."""
        if not self.replica.close(FLUSH_TIMEOUT_S):
            log.warning("closing with parameter writes unsent after %.1f s", FLUSH_TIMEOUT_S)
        try:
            self._subscriber.call("unsubscribeParam", self._api, "/")
        except TransportError as err:
            log.debug("unsubscribeParam: %s", err)
        self._stop_server()
