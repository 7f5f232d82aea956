"""The ROS master, without rospy: its XML-RPC client, and a master of our own when none runs.

The master API is plain XML-RPC, so parameters and the graph can be read and written from any
Python; only topics need rospy. ``RosMaster`` starts ``rosmaster --core`` (Debian's
``python3-rosmaster``) on a free port for a demo or a test, and ends it by PID.
"""

from __future__ import annotations

import http.client
import os
import shutil
import socket
import subprocess
import tempfile
import threading
import time
import xmlrpc.client
from typing import IO, Any

from dbml.core.errors import TransportError

__all__ = ["DEFAULT_MASTER_URI", "MasterClient", "RosMaster", "free_port"]

DEFAULT_MASTER_URI = "http://localhost:11311/"
CALL_TIMEOUT_S = 2.0


class _TimeoutTransport(xmlrpc.client.Transport):
    def __init__(self, timeout_s: float) -> None:
        super().__init__()
        self._timeout_s = timeout_s

    def make_connection(self, host: Any) -> http.client.HTTPConnection:
        connection = super().make_connection(host)
        connection.timeout = self._timeout_s
        return connection


class MasterClient:
    """An XML-RPC API of the ROS master (or of a node), one connection per thread.

    Calls return the value of ``[code, message, value]``; failures raise ``TransportError``.
    """

    def __init__(
        self, uri: str | None = None, *, caller_id: str = "/dbml", timeout_s: float = CALL_TIMEOUT_S
    ) -> None:
        self.uri = uri or os.environ.get("ROS_MASTER_URI") or DEFAULT_MASTER_URI
        self.caller_id = caller_id
        self._timeout_s = timeout_s
        self._local = threading.local()

    def _proxy(self) -> xmlrpc.client.ServerProxy:
        proxy = getattr(self._local, "proxy", None)
        if proxy is None:
            proxy = xmlrpc.client.ServerProxy(
                self.uri, transport=_TimeoutTransport(self._timeout_s), allow_none=True
            )
            self._local.proxy = proxy
        return proxy

    def call(self, method: str, *args: Any, missing_ok: bool = False) -> Any:
        """The call's value; with ``missing_ok`` a code of -1 (unknown key or node) is None."""
        try:
            code, message, value = getattr(self._proxy(), method)(self.caller_id, *args)
        except (OSError, xmlrpc.client.Error, http.client.HTTPException) as err:
            self._local.proxy = None
            raise TransportError(f"ROS API {self.uri}: {method} failed: {err}") from err
        if code != 1:
            if missing_ok and code == -1:
                return None
            raise TransportError(f"ROS API {self.uri}: {method}{args!r}: {message}")
        return value

    def reachable(self) -> bool:
        try:
            self.call("getPid")
        except TransportError:
            return False
        return True

    def close(self) -> None:
        """Close this thread's connection (each thread's closes when the thread ends)."""
        proxy = getattr(self._local, "proxy", None)
        self._local.proxy = None
        if proxy is not None:
            proxy("close")()

    def __enter__(self) -> MasterClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def _answers(uri: str) -> bool:
    with MasterClient(uri, timeout_s=0.5) as client:
        return client.reachable()


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


class RosMaster:
    """``rosmaster --core`` on a free loopback port: ``with RosMaster() as master: master.uri``.

    ``RosMaster.reuse_or_start()`` takes the master at ``ROS_MASTER_URI`` when one answers.
    """

    def __init__(self, *, port: int | None = None, ready_timeout_s: float = 15.0) -> None:
        self.port = port or free_port()
        self.uri = f"http://127.0.0.1:{self.port}/"
        self._ready_timeout_s = ready_timeout_s
        self.process: subprocess.Popen[bytes] | None = None
        self.reused = False
        self._log: IO[bytes] | None = None

    @classmethod
    def reuse_or_start(cls) -> RosMaster:
        """The running master at ``ROS_MASTER_URI`` (not ours to stop), else a new one."""
        existing = os.environ.get("ROS_MASTER_URI")
        if existing and _answers(existing):
            master = cls()
            master.uri, master.reused = existing, True
            return master
        return cls().start()

    @property
    def started_here(self) -> bool:
        return self.process is not None

    def start(self) -> RosMaster:
        executable = shutil.which("rosmaster")
        if executable is None:
            raise TransportError(
                "rosmaster not found: install Debian's ROS 1 packages (scripts/install-ros1)"
            )
        log = self._log = tempfile.TemporaryFile()  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen(
            [executable, "--core", "-p", str(self.port)],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + self._ready_timeout_s
        while not _answers(self.uri):
            if self.process.poll() is not None or time.monotonic() > deadline:
                log.seek(0)
                output = log.read()[-500:].decode(errors="replace")
                self.stop()
                raise TransportError(f"rosmaster on port {self.port} did not start: {output}")
            time.sleep(0.05)
        return self

    def stop(self) -> None:
        """End the master this object started (by PID); a reused one is left running."""
        process, self.process = self.process, None
        if process is not None and process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=5.0)
        log, self._log = self._log, None
        if log is not None:
            log.close()

    def __enter__(self) -> RosMaster:
        return self if self.process is not None or self.reused else self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()
