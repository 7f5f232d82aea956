"""Foxglove Studio, in headless Chromium, shows a camera's JPEG: the ladder's compressed copy.

The recording is dbml's live view (``--record``) of what an operator receives from two cameras
moving over the photographs, JPEG as a ladder's run sends it, opened with the layout of ``dbml
foxglove layout --compressed``. Each camera's
image panel must show a frame of ``[topic]/optimized/compressed`` (``sensor_msgs/msg/
CompressedImage``, decoded by Studio itself) and no error; nothing may leave the machine.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import pytest

from dbml.view.layout import DEFAULT_CAMERAS, studio_layout
from tests.browser.studio import (
    DIST,
    DevTools,
    chromium,
    is_png,
    require_browser,
    static_server,
    studio_url,
)
from tests.integration.procs import ROOT

pytest.importorskip("simplejpeg")

pytestmark = [pytest.mark.browser, pytest.mark.alone]  # Chromium and a run: CPU for two

READY_TIMEOUT_S = 90.0
RUN_TIMEOUT_S = 60.0
LAYOUT = studio_layout(cameras=DEFAULT_CAMERAS, channels=list(DEFAULT_CAMERAS), compressed=True)
PANEL_IDS = {
    camera: next(
        panel_id
        for panel_id, config in LAYOUT["configById"].items()
        if config.get("cameraTopic") == f"{camera}/optimized/compressed"
    )
    for camera in DEFAULT_CAMERAS
}
_RECORD = """
import sys, time
from pathlib import Path
from dbml.media.images import Frame, encode_compressed
from dbml.media.jpeg import compressed_format, encode_jpeg
from dbml.media.photos import PanCamera, position_frame_id
from dbml.protocol.schema import Writer
from dbml.transports.memory import MemoryNetwork, MemoryTransport
from dbml.view.live import open_view
from dbml.view.target import ViewTarget

# dbml's own live view records what an operator receives: each camera's JPEG copy, as the
# ladder's run sends it (a rung of each camera's ladder).
transport = MemoryTransport(MemoryNetwork(), host="operator")
target = ViewTarget.from_flags(None, sys.argv[1])
view = open_view(transport, target, writers=frozenset({Writer.OPERATOR}))
cameras = {"/r1/camera": (PanCamera(640, 480), 80), "/r2/camera": (PanCamera(160, 120), 95)}
for _ in range(8):
    for topic, (eye, quality) in cameras.items():
        pixels = eye.frame()
        frame = Frame(pixels, "rgb8", time.time_ns(), position_frame_id(0))
        data = encode_jpeg(pixels, encoding="rgb8", quality=quality)
        message = encode_compressed(frame, data, format=compressed_format("rgb8"))
        view.frame(topic, message, compressed=True)
view.close()
transport.close()
"""


def _recording(folder: Path) -> Path:
    record = folder / "photos.mcap"
    result = subprocess.run(
        [sys.executable, "-c", _RECORD, str(record)],
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
        env=dict(os.environ, PYTHONPATH=str(ROOT / "src")),
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return record


def _frames_at(record: Path) -> str:
    """Just after the first JPEG of each camera was recorded (RFC 3339)."""
    from mcap.reader import make_reader

    topics = [f"{camera}/optimized/compressed" for camera in DEFAULT_CAMERAS]
    first: dict[str, int] = {}
    with record.open("rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(topics=topics):
            first.setdefault(channel.topic, message.log_time)
            if len(first) == len(topics):
                break
    assert len(first) == len(topics), f"{record}: JPEG of {sorted(first)} only"
    at = datetime.fromtimestamp(max(first.values()) / 1e9 + 0.001, tz=UTC)
    return at.isoformat().replace("+00:00", "Z")


def _missing_images(page: DevTools) -> str | None:
    panels = page.panel_texts()
    for camera, panel_id in PANEL_IDS.items():
        text = panels.get(panel_id, "")
        if re.search(r"error|failed|unsupported", text, flags=re.IGNORECASE):
            raise AssertionError(f"{camera}'s image panel says: {text!r}")
        if re.search(r"^\d+\.\d{9}$", text, flags=re.MULTILINE) is None:
            return f"{camera}: no frame yet (the panel shows {text[:80]!r})"
    return None


def test_a_cameras_jpeg_shows_in_studio(tmp_path: Path) -> None:
    browser = require_browser()
    data = tmp_path / "data"
    data.mkdir()
    record = _recording(data)
    run = tmp_path / "run"
    run.mkdir()
    (run / "layout.json").write_text(json.dumps(LAYOUT))
    with (
        static_server({"/": DIST, "/run/": run, "/data/": data}) as base,
        chromium(browser) as page,
    ):
        page.navigate(
            studio_url(
                base,
                layout=f"{base}/run/layout.json",
                ds="remote-file",
                ds_url=f"{base}/data/{record.name}",
                time=_frames_at(record),
            )
        )
        page.wait_for(_missing_images, timeout_s=READY_TIMEOUT_S, what="both cameras' JPEG")
        page.pump(1.0)
        assert is_png(page.screenshot(tmp_path / "compressed.png"))
        assert page.outside_requests() == []
