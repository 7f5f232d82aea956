"""The browser tests' static server: byte ranges as Studio reads a remote MCAP (RFC 7233)."""

from __future__ import annotations

import urllib.request
from pathlib import Path
from urllib.error import HTTPError

import pytest

from tests.browser.studio import parse_range, static_server


@pytest.mark.parametrize(
    ("header", "size", "expected"),
    [
        ("bytes=0-9", 100, (0, 9)),
        ("bytes=90-", 100, (90, 99)),
        ("bytes=90-200", 100, (90, 99)),
        ("bytes=-10", 100, (90, 99)),
        ("bytes=-200", 100, (0, 99)),
        ("bytes=100-", 100, None),
        ("bytes=-0", 100, None),
        ("bytes=0-0", 0, None),
    ],
)
def test_parse_range(header: str, size: int, expected: tuple[int, int] | None) -> None:
    assert parse_range(header, size) == expected


@pytest.mark.parametrize("header", ["bytes=0-1,5-6", "items=0-1", "bytes=-", "bytes=9-3"])
def test_parse_range_refuses(header: str) -> None:
    with pytest.raises(ValueError, match="range"):
        parse_range(header, 100)


def _get(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=10) as reply:
            return reply.status, dict(reply.headers), reply.read()
    except HTTPError as err:
        return err.code, dict(err.headers), err.read()


def test_serves_ranges_under_mounts(tmp_path: Path) -> None:
    page, data = tmp_path / "page", tmp_path / "data"
    page.mkdir()
    data.mkdir()
    (page / "index.html").write_text("<p>page</p>")
    body = bytes(range(256)) * 4
    (data / "run.mcap").write_bytes(body)
    (tmp_path / "secret").write_text("outside")
    with static_server({"/": page, "/data/": data}) as base:
        status, headers, content = _get(f"{base}/data/run.mcap")
        assert (status, content) == (200, body)
        assert headers["Accept-Ranges"] == "bytes"
        assert headers["Content-Length"] == str(len(body))

        status, headers, content = _get(f"{base}/data/run.mcap", {"Range": "bytes=10-19"})
        assert (status, content) == (206, body[10:20])
        assert headers["Content-Range"] == f"bytes 10-19/{len(body)}"

        status, _, content = _get(f"{base}/data/run.mcap", {"Range": "bytes=-4"})
        assert (status, content) == (206, body[-4:])

        status, headers, _ = _get(f"{base}/data/run.mcap", {"Range": "bytes=5000-"})
        assert status == 416
        assert headers["Content-Range"] == f"bytes */{len(body)}"

        status, _, content = _get(f"{base}/data/run.mcap", {"Range": "bytes=0-1,4-5"})
        assert (status, content) == (200, body)

        assert _get(f"{base}/")[2] == b"<p>page</p>"
        assert _get(f"{base}/data/../secret")[0] == 404
        assert _get(f"{base}/data/%2e%2e/secret")[0] == 404
        assert _get(f"{base}/missing.js")[0] == 404
