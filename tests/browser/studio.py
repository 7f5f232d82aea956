"""Drive Foxglove Studio (web/studio's page) in headless Chromium, for the browser tests.

Three pieces, each small enough to read whole: a static HTTP server with byte ranges (Studio
reads a remote MCAP by ranges; the standard library's server has none), Chromium started in a
fresh profile with everything that phones home switched off, and a DevTools-protocol client on
``websockets``: navigate, read the page's text, take a screenshot, watch for requests that leave
the machine. Waits are conditions with deadlines; on a deadline the error says what the page
showed.
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import mimetypes
import os
import re
import shutil
import signal
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, BinaryIO
from urllib.parse import unquote, urlencode, urlsplit

from websockets.sync.client import ClientConnection, connect

from dbml.harness.supervisor import ProcessChild, Supervisor
from tests.conftest import require

ROOT = Path(__file__).resolve().parents[2]
STUDIO = ROOT / "web" / "studio"
DIST = STUDIO / "dist"
BUILD = "cd web/studio && npm ci && npm run build"
INSTALL_CHROMIUM = "apt-get install -y --no-install-recommends chromium"

CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--lang=en-US",
    "--hide-scrollbars",
    "--mute-audio",
)
WINDOW = (1600, 900)
_PANEL_PREFIX = "panel-mouseenter-container "
_PANEL_TEXTS = f"""Object.fromEntries(
    [...document.querySelectorAll('[data-testid^="{_PANEL_PREFIX}"]')]
        .map(e => [e.dataset.testid.slice({len(_PANEL_PREFIX)}), e.innerText]))"""
LOCAL = re.compile(r"^(?:https?|wss?)://(?:127\.0\.0\.1|localhost|\[::1\])(?::\d+)?/")


def chromium_path() -> str | None:
    """The browser: ``DBML_CHROMIUM`` if set, else Debian's ``chromium`` on the PATH."""
    return os.environ.get("DBML_CHROMIUM") or shutil.which("chromium")


def require_browser() -> str:
    """Chromium and the built page, or a skip that says how to get them (a failure under CI).

    CI installs both (.ci/run): there a missing one is a broken setup, not a reason to skip.
    """
    missing = []
    chromium = chromium_path()
    if chromium is None:
        missing.append(f"no chromium on PATH ({INSTALL_CHROMIUM})")
    if not (DIST / "index.html").is_file() or not (DIST / "studio" / "index.js").is_file():
        missing.append(f"web/studio/dist is not built ({BUILD})")
    require("; ".join(missing) or None, what="run the browser tests")
    assert chromium is not None
    return chromium


# --- a static server with byte ranges ----------------------------------------------------------

_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")
_TYPES = {
    ".js": "text/javascript",
    ".wasm": "application/wasm",
    ".mcap": "application/octet-stream",
}


def parse_range(header: str, size: int) -> tuple[int, int] | None:
    """The one range ``header`` asks of ``size`` bytes, as (first, last) inclusive.

    RFC 7233: ``bytes=a-b``, ``bytes=a-`` (to the end) and ``bytes=-n`` (the last n); ``last``
    past the end is cut to it. None where no byte can be served (a start past the end, ``-0``,
    an empty file). A header that is no single byte range raises ``ValueError``: the server then
    ignores it and sends the whole file, as the RFC allows.
    """
    match = _RANGE.match(header.strip())
    if match is None or match.group(1) == match.group(2) == "":
        raise ValueError(f"not a single byte range: {header!r}")
    first_text, last_text = match.groups()
    if first_text == "":
        suffix = int(last_text)
        if suffix == 0 or size == 0:
            return None
        return max(size - suffix, 0), size - 1
    first = int(first_text)
    last = size - 1 if last_text == "" else min(int(last_text), size - 1)
    if first >= size:
        return None
    if last < first:
        raise ValueError(f"range ends before it starts: {header!r}")
    return first, last


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:
        del format, args

    def do_HEAD(self) -> None:
        self._serve(body=False)

    def do_GET(self) -> None:
        self._serve(body=True)

    def _file(self) -> Path | None:
        path = unquote(urlsplit(self.path).path)
        for prefix, root in self.server.mounts:
            if path.startswith(prefix):
                relative = path[len(prefix) :] or "index.html"
                candidate = (root / relative).resolve()
                if candidate.is_dir():
                    candidate = candidate / "index.html"
                if candidate.is_relative_to(root) and candidate.is_file():
                    return candidate
                return None
        return None

    def _serve(self, *, body: bool) -> None:
        file = self._file()
        if file is None:
            self._status(HTTPStatus.NOT_FOUND)
            return
        size = file.stat().st_size
        first, last, status = 0, size - 1, HTTPStatus.OK
        header = self.headers.get("Range")
        if header is not None:
            try:
                wanted = parse_range(header, size)
            except ValueError:
                wanted = (0, size - 1)
            else:
                if wanted is None:
                    self._status(
                        HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE,
                        {"Content-Range": f"bytes */{size}"},
                    )
                    return
                status = HTTPStatus.PARTIAL_CONTENT
            first, last = wanted
        length = max(last - first + 1, 0)
        self.send_response(status)
        kind = _TYPES.get(file.suffix) or mimetypes.guess_type(file.name)[0]
        self.send_header("Content-Type", kind or "application/octet-stream")
        self.send_header("Content-Length", str(length))
        self.send_header("Accept-Ranges", "bytes")
        self.send_header("Cache-Control", "no-store")
        if status == HTTPStatus.PARTIAL_CONTENT:
            self.send_header("Content-Range", f"bytes {first}-{last}/{size}")
        self.end_headers()
        if body:
            with file.open("rb") as source:
                source.seek(first)
                self._copy(source, length)

    def _copy(self, source: BinaryIO, length: int) -> None:
        # Studio opens a file with a GET it cancels at once: a client gone is no error.
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            while length > 0:
                chunk = source.read(min(length, 1 << 20))
                if not chunk:
                    break
                self.wfile.write(chunk)
                length -= len(chunk)

    def _status(self, status: HTTPStatus, headers: Mapping[str, str] | None = None) -> None:
        self.send_response(status)
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.send_header("Content-Length", "0")
        self.end_headers()


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, mounts: Mapping[str, Path]) -> None:
        # The longest prefix first, so "/run/" wins over "/".
        self.mounts = sorted(
            ((prefix, root.resolve()) for prefix, root in mounts.items()),
            key=lambda item: -len(item[0]),
        )
        super().__init__(("127.0.0.1", 0), _Handler)


@contextlib.contextmanager
def static_server(mounts: Mapping[str, Path]) -> Iterator[str]:
    """Serve directories under URL prefixes (``{"/": dist, "/run/": data}``) on loopback.

    Yields the base URL (``http://127.0.0.1:PORT``); the server thread ends with the block.
    """
    server = _Server(mounts)
    thread = threading.Thread(target=server.serve_forever, name="static-server", daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


# --- Chromium and the DevTools protocol ----------------------------------------------------------


class PageTimeoutError(AssertionError):
    """The page did not get there in time; the message carries what it showed."""


@dataclass
class DevTools:
    """A DevTools-protocol session with one page: commands answered in order, events kept."""

    socket: ClientConnection
    events: list[dict[str, Any]] = field(default_factory=list)
    _ids: Iterator[int] = field(default_factory=lambda: itertools.count(1))

    def call(self, method: str, timeout_s: float = 30.0, **params: Any) -> dict[str, Any]:
        """Send one command and wait for its answer; events that arrive meanwhile are kept."""
        ident = next(self._ids)
        self.socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise PageTimeoutError(f"{method}: no answer in {timeout_s} s")
            message = json.loads(self.socket.recv(timeout=left))
            if message.get("id") == ident:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                result: dict[str, Any] = message.get("result", {})
                return result
            if "method" in message:
                self.events.append(message)

    def pump(self, duration_s: float) -> None:
        """Keep the events that arrive within ``duration_s`` (the pause between two checks)."""
        deadline = time.monotonic() + duration_s
        with contextlib.suppress(TimeoutError):
            while (left := deadline - time.monotonic()) > 0:
                message = json.loads(self.socket.recv(timeout=left))
                if "method" in message:
                    self.events.append(message)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-serialisable values only)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def text(self) -> str:
        """What the page shows as text (``document.body.innerText``)."""
        value = self.evaluate("document.body ? document.body.innerText : ''")
        return value if isinstance(value, str) else ""

    def navigate(self, url: str) -> None:
        """Open ``url`` (its load is not awaited: wait for what it should show)."""
        result = self.call("Page.navigate", url=url)
        if result.get("errorText"):
            raise RuntimeError(f"{url}: {result['errorText']}")

    def panel_texts(self) -> dict[str, str]:
        """Each panel's text by its layout id (Studio tags a panel's box with the id)."""
        value = self.evaluate(_PANEL_TEXTS)
        return {str(k): str(v) for k, v in value.items()} if isinstance(value, dict) else {}

    def wait_for(
        self,
        missing: Callable[[DevTools], str | None],
        *,
        timeout_s: float,
        what: str,
        poll_s: float = 0.25,
    ) -> None:
        """Until ``missing(self)`` names nothing missing; else ``PageTimeoutError`` saying what.

        The error carries what was missing last and the page's text. The page's own failure
        (web/studio/page.js sets ``window.dbmlStudio.state``) ends the wait at once.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            gap = missing(self)
            if gap is None:
                return
            state = self.evaluate("window.dbmlStudio && window.dbmlStudio.state")
            if state == "error":
                error = self.evaluate("window.dbmlStudio.error")
                raise PageTimeoutError(f"{what}: the page failed: {error}")
            if time.monotonic() >= deadline:
                raise PageTimeoutError(
                    f"{what}: not shown in {timeout_s} s ({gap}); the page showed:\n{self.text()}"
                )
            self.pump(poll_s)

    def screenshot(self, path: Path) -> bytes:
        """The viewport as PNG, written to ``path`` too."""
        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        return data

    def requests(self) -> list[str]:
        """Every URL the page asked for so far (with ``Network.enable``)."""
        return [
            e["params"]["request"]["url"]
            for e in self.events
            if e["method"] == "Network.requestWillBeSent"
        ]

    def outside_requests(self) -> list[str]:
        """Requests to anywhere but this machine (data: and blob: URLs stay in the page)."""
        return [
            url
            for url in self.requests()
            if not LOCAL.match(url) and not url.startswith(("data:", "blob:", "about:"))
        ]


def _devtools_port(profile: Path, process: ProcessChild, timeout_s: float) -> int:
    """The port Chromium picked for ``--remote-debugging-port=0``: it writes it in the profile."""
    marker = profile / "DevToolsActivePort"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (code := process.poll()) is not None:
            raise RuntimeError(f"chromium exited with {code} before it listened")
        with contextlib.suppress(FileNotFoundError, ValueError, IndexError):
            return int(marker.read_text().splitlines()[0])
        time.sleep(0.05)
    raise PageTimeoutError(f"chromium wrote no {marker.name} in {timeout_s} s")


def _page_socket_url(port: int, timeout_s: float) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as reply:
            targets = json.load(reply)
        for target in targets:
            if target.get("type") == "page" and "webSocketDebuggerUrl" in target:
                url: str = target["webSocketDebuggerUrl"]
                return url
        time.sleep(0.05)
    raise PageTimeoutError(f"chromium showed no page target in {timeout_s} s")


@contextlib.contextmanager
def chromium(executable: str, *, start_timeout_s: float = 30.0) -> Iterator[DevTools]:
    """Headless Chromium in a fresh profile, with a DevTools session on its page.

    The browser, its helpers and its profile are gone when the block ends, however it ends.
    """
    profile = Path(tempfile.mkdtemp(prefix="dbml-chromium-"))
    command = [
        executable,
        *CHROMIUM_FLAGS,
        f"--window-size={WINDOW[0]},{WINDOW[1]}",
        f"--user-data-dir={profile}",
        "--remote-debugging-address=127.0.0.1",
        "--remote-debugging-port=0",
        "about:blank",
    ]
    children = Supervisor()
    process = children.start("chromium", command, stdin=False, read_stdout=False, new_session=True)
    try:
        try:
            port = _devtools_port(profile, process, start_timeout_s)
            url = _page_socket_url(port, start_timeout_s)
        except (RuntimeError, PageTimeoutError) as err:
            raise RuntimeError(f"{err}; chromium said:\n{process.log_tail()}") from err
        with connect(url, max_size=None, open_timeout=start_timeout_s) as socket:
            tools = DevTools(socket)
            tools.call("Page.enable")
            tools.call("Runtime.enable")
            tools.call("Network.enable")
            tools.call(
                "Emulation.setDeviceMetricsOverride",
                width=WINDOW[0],
                height=WINDOW[1],
                deviceScaleFactor=1,
                mobile=False,
            )
            yield tools
    finally:
        children.close()  # SIGTERM, then SIGKILL, by its PID
        # Its helpers (zygote, renderers) share the group it leads, whose id is its own.
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(process.pid, signal.SIGKILL)
        shutil.rmtree(profile, ignore_errors=True)


def studio_url(base: str, *, layout: str, ds: str, ds_url: str, time: str | None = None) -> str:
    """The page's URL: its layout and a data source (``foxglove-websocket``, ``remote-file``).

    ``time`` (RFC 3339): where Studio opens a recording (its own ``time`` parameter).
    """
    params = {"layout": layout, "ds": ds, "ds.url": ds_url}
    if time is not None:
        params["time"] = time
    query = urlencode(params)
    return f"{base}/index.html?{query}"


def is_png(data: bytes, *, min_bytes: int = 20_000) -> bool:
    """A PNG of some substance: the signature, a 1600 x 900 header and more than a blank page."""
    if len(data) < min_bytes or not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return False
    width = int.from_bytes(data[16:20], "big")
    height = int.from_bytes(data[20:24], "big")
    return (width, height) == WINDOW
