"""A TCP port of this machine that leads into a testbed namespace: the operator's live view.

The testbed's namespaces have no link to the root one (nothing is placed there), so a server
inside the operator's namespace, such as its Foxglove view, cannot be reached from a browser on
the machine. ``NetnsForward`` listens in the caller's namespace and joins every connection to a
port inside a namespace: its outgoing sockets are created there (a socket belongs to the
namespace it was created in, whatever thread uses it), by a short-lived thread that enters the
namespace with ``setns(2)`` and leaves it. The bytes never cross the shaped links.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import socket
import threading
from collections.abc import Callable

from dbml.testbed.netns import TestbedError
from dbml.transports.worker import BackgroundThread

__all__ = ["MAX_CONNECTIONS", "NetnsForward", "socket_in"]

log = logging.getLogger("dbml.testbed")

CLONE_NEWNET = 0x40000000
"""``setns(2)``'s namespace type of a network namespace."""
MAX_CONNECTIONS = 16
"""Connections forwarded at once (a browser opens one per tab); past it, new ones are closed."""
_CHUNK = 65536
_CONNECT_TIMEOUT_S = 5.0


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))


def socket_in(netns_path: str) -> socket.socket:
    """A TCP socket of the network namespace at ``netns_path`` (``/run/netns/NAME``)."""
    made: list[socket.socket] = []
    failed: list[BaseException] = []

    def enter_make_leave() -> None:
        try:
            with contextlib.ExitStack() as files:
                home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
                files.callback(os.close, home)
                target = os.open(netns_path, os.O_RDONLY)
                files.callback(os.close, target)
                _setns(target)
                try:
                    made.append(socket.socket(socket.AF_INET, socket.SOCK_STREAM))
                finally:
                    _setns(home)
        except BaseException as err:  # handed to the caller, raised there
            failed.append(err)

    thread = threading.Thread(target=enter_make_leave, name="dbml-netns-socket", daemon=True)
    thread.start()
    thread.join()
    if failed or not made:
        raise TestbedError(f"netns={netns_path!r}: no socket there: {failed[:1]}")
    return made[0]


class NetnsForward:
    """Listen on ``host:port`` here; each connection joined to ``127.0.0.1:target_port`` there."""

    def __init__(self, netns_path: str, *, host: str, port: int, target_port: int) -> None:
        self._netns_path = netns_path
        self._target_port = target_port
        self._listener = socket.create_server((host, port))
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()
        self._closed = threading.Event()
        self._accept = BackgroundThread(self._serve, name="dbml-forward", log=log)

    @property
    def port(self) -> int:
        """The port it listens on (the one picked for port 0)."""
        return int(self._listener.getsockname()[1])

    def start(self) -> NetnsForward:
        """Accept connections on a thread of its own."""
        self._accept.start()
        return self

    def _serve(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:
                return  # closed
            try:
                inner = socket_in(self._netns_path)
            except TestbedError as err:
                log.warning("%s", err)
                client.close()
                continue
            try:
                inner.settimeout(_CONNECT_TIMEOUT_S)
                inner.connect(("127.0.0.1", self._target_port))
                inner.settimeout(None)
            except OSError as err:
                log.debug("forward to port %d: %s", self._target_port, err)  # not up yet
                inner.close()
                client.close()
                continue
            with self._lock:
                if len(self._open) >= 2 * MAX_CONNECTIONS:
                    client.close()
                    inner.close()
                    continue
                self._open |= {client, inner}
            for source, sink in ((client, inner), (inner, client)):
                BackgroundThread(
                    self._pump(source, sink), name="dbml-forward-pump", log=log
                ).start()

    def _pump(self, source: socket.socket, sink: socket.socket) -> Callable[[], None]:
        def pump() -> None:
            try:
                with contextlib.suppress(OSError):  # one side closed: end both
                    while chunk := source.recv(_CHUNK):
                        sink.sendall(chunk)
            finally:  # shutdown wakes the other direction's recv; close alone would not
                for end in (source, sink):
                    with self._lock:
                        self._open.discard(end)
                    with contextlib.suppress(OSError):
                        end.shutdown(socket.SHUT_RDWR)
                    end.close()

        return pump

    def close(self) -> None:
        """Stop listening and end every forwarded connection."""
        self._closed.set()
        with contextlib.suppress(OSError):  # wakes the accept in progress (Linux)
            self._listener.shutdown(socket.SHUT_RDWR)
        self._listener.close()
        with self._lock:
            ends, self._open = set(self._open), set()
        for end in ends:
            with contextlib.suppress(OSError):
                end.shutdown(socket.SHUT_RDWR)
            end.close()
        self._accept.join()
