"""Foxglove Studio, a real one in headless Chromium, shows dbml's view with the shipped layout.

Two ways in, one layout: a recording (``ds=remote-file``: Studio reads the MCAP by byte ranges)
and a live server (``ds=foxglove-websocket``). Each test waits until the page shows the
allocation of Table 2's first step (/r1/camera 12.37 Hz, /r2/camera 16 Hz, 11 Mbit/s), checks
that nothing left the machine, and keeps a screenshot; the live one's goes to
``$DBML_SCREENSHOT`` when set (the README's docs/foxglove.png).

The data is the main job's: ``dbml demo teleop --foxglove PORT --record FILE``, watched live
(its steps 1-2 and 8-10 are Table 2's 12.37 / 16 Hz), then its recording, opened at step 1.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from time import monotonic
from typing import Any

import pytest

from dbml.harness.processes import free_port
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
from tests.integration.procs import ROOT, Proc

pytestmark = pytest.mark.browser

READY_TIMEOUT_S = 90.0

# Table 2, step 1: what the optimizer gave each camera under an 11 Mbit/s budget.
BUDGET_MBIT = 11.0
RATES_HZ = {"/r1/camera": 12.37, "/r2/camera": 16.0}
STEP1_R2_FLOOR_HZ = 16.0
"""R2 alone has a priority in step 1 (tc 10 s): eq. 2 gives it all the weight, eq. 3 its maximum."""


# --- the two data sources: a live demo, then its recording ---------------------------------------

DEMO_STEP_S = 5.0
"""Long enough that step 1 (and the moments before it, whose rates are the same) outlasts the
page's load: it shows Table 2's step 1 live."""
DEMO_START_S = 60.0
DEMO_END_S = 120.0
"""The demo's 10 steps, its start and its end, after the live test."""


@dataclass(frozen=True, slots=True)
class Demo:
    proc: Proc
    url: str
    record: Path


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Demo]:
    """``dbml demo teleop --foxglove PORT --record FILE``, running for this module's tests."""
    require_browser()
    port = free_port()
    record = tmp_path_factory.mktemp("demo") / "demo.mcap"
    argv = ["demo", "teleop", "--step-seconds", f"{DEMO_STEP_S:g}", "--json"]
    argv += ["--foxglove", f"127.0.0.1:{port}", "--record", str(record)]
    proc = Proc(argv, dict(os.environ, PYTHONPATH=str(ROOT / "src")))
    try:
        deadline = time.monotonic() + DEMO_START_S
        while not _accepts(port):
            assert proc.poll() is None, proc.stderr()
            assert time.monotonic() < deadline, f"no view on port {port}: {proc.stderr()}"
            time.sleep(0.1)
        yield Demo(proc, f"ws://127.0.0.1:{port}", record)
    finally:
        proc.stop()


def _accepts(port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
        return True
    return False


@pytest.fixture
def live_url(demo: Demo) -> str:
    """The running demo's view."""
    return demo.url


@pytest.fixture
def recording(demo: Demo) -> Path:
    """The demo's recording, once the demo ended (it held Table 2)."""
    try:
        code = demo.proc.wait(DEMO_END_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the demo did not end within {DEMO_END_S:g} s")
    lines = list(demo.proc.json_lines(timeout_s=1))
    assert code == 0, demo.proc.stderr()
    assert lines
    assert lines[-1]["ok"] is True
    return demo.record


def step1_time(record: Path) -> str:
    """When the recording shows step 1 (RFC 3339): its first allocation of it, plus a second."""
    from mcap.reader import make_reader

    with record.open("rb") as stream:
        for _, _channel, message in make_reader(stream).iter_messages(topics=["/dbm/allocation"]):
            allocation = json.loads(message.data)
            priorities = [c["priority"] for c in allocation["channels"]]
            if len(priorities) == len(RATES_HZ) and any(priorities):
                at = datetime.fromtimestamp(message.log_time / 1e9 + 1.0, tz=UTC)
                return at.isoformat().replace("+00:00", "Z")
    raise AssertionError(f"{record}: no allocation of step 1")


# --- the browser ----------------------------------------------------------------------------------


@pytest.fixture
def browser() -> str:
    return require_browser()


LAYOUT = studio_layout(cameras=DEFAULT_CAMERAS, channels=list(RATES_HZ))


@pytest.fixture
def layout_dir(tmp_path: Path) -> Path:
    """The shipped layout, where the page fetches it."""
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "layout.json").write_text(json.dumps(LAYOUT))
    return folder


def _panel(kind: str, **config: Any) -> str:
    """The layout's id of the panel of type ``kind`` whose config has ``config``."""
    for panel_id, panel_config in LAYOUT["configById"].items():
        if panel_id.split("!")[0] == kind and config.items() <= panel_config.items():
            return str(panel_id)
    raise AssertionError(f"no {kind} panel with {config} in the layout")


def table_rows(text: str) -> dict[str, dict[str, str]]:
    """A Table panel's rows by their first column: its text is one tab-separated line a row."""
    lines = [line.split("\t") for line in text.splitlines() if "\t" in line]
    if not lines:
        return {}
    header = [cell.strip() for cell in lines[0]]
    rows = [dict(zip(header, (cell.strip() for cell in line), strict=False)) for line in lines[1:]]
    return {row[header[1]]: row for row in rows if len(header) > 1 and header[1] in row}


def message_fields(text: str) -> dict[str, str]:
    """A Raw Messages panel's top-level fields: each name is on a line, its value on the next."""
    return dict(re.findall(r"^(\w+)\s*\n([^\n]*)$", text, flags=re.MULTILINE))


def _near(shown: str | None, value: float) -> bool:
    """A number the page shows is ``value`` (to the 0.01 a person reads)."""
    try:
        return shown is not None and abs(float(shown) - value) < 0.005
    except ValueError:
        return False


def missing_step(page: DevTools) -> str | None:
    """What the page does not show yet of Table 2's step 1 (None: all of it).

    The allocation table's rate_hz column, R2's priority floor (step 1's event: before it both
    priorities are 0, with the same rates), the rates in the plot's legend, the budget panel's
    budget_mbit, and a frame (its stamp) in each camera's image panel.
    """
    panels = page.panel_texts()
    rows = table_rows(panels.get(_panel("Table"), ""))
    legend = panels.get(_panel("Plot"), "").split()
    floor = rows.get("/r2/camera", {}).get("floor_hz")
    if not _near(floor, STEP1_R2_FLOOR_HZ):
        return f"allocation table: /r2/camera floor_hz {floor!r}, not {STEP1_R2_FLOOR_HZ:g}"
    for topic, rate in RATES_HZ.items():
        shown = rows.get(topic, {}).get("rate_hz")
        if not _near(shown, rate):
            return f"allocation table: {topic} rate_hz {shown!r}, not {rate:g}"
        if not any(_near(word, rate) for word in legend):
            return f"plot legend: no {rate:g}"
    budget = message_fields(panels.get(_panel("RawMessages", topicPath="/dbm/budget"), ""))
    if not _near(budget.get("budget_mbit"), BUDGET_MBIT):
        return f"budget panel: budget_mbit {budget.get('budget_mbit')!r}, not {BUDGET_MBIT:g}"
    if "estimate_mbit" not in budget:
        return "budget panel: no estimate_mbit"
    for camera in DEFAULT_CAMERAS:
        image = panels.get(_panel("ImageViewPanel", cameraTopic=f"{camera}/optimized"), "")
        if re.search(r"^\d+\.\d{9}$", image, flags=re.MULTILINE) is None:
            return f"{camera}: no frame yet"
    return None


def missing_live(page: DevTools) -> str | None:
    """The step, and the server's parameters in the Parameters panel (a recording has none)."""
    gap = missing_step(page)
    if gap is not None:
        return gap
    parameters = page.panel_texts().get(_panel("Parameters"), "")
    if "/dbm/max_bandwidth_in_mbit" not in parameters:
        return "parameters panel: no /dbm/max_bandwidth_in_mbit"
    return None


def _open(
    browser: str,
    mounts: dict[str, Path],
    *,
    ds: str,
    ds_url: str,
    screenshot: Path,
    missing: Callable[[DevTools], str | None] = missing_step,
    settle_s: float = 1.0,
    time: str | None = None,
    then: Callable[[DevTools], str | None] | None = None,
) -> float:
    """Load the page on ``ds``, wait until nothing is ``missing``, keep a screenshot.

    ``mounts`` are served beside the page (``/run/`` holds layout.json); ``BASE`` in ``ds_url``
    stands for the server's address; ``time`` (RFC 3339) is where a recording opens. The
    screenshot is taken ``settle_s`` after the page showed the step (the plot and images draw
    what the text already shows), after ``then`` shows nothing missing if given. Returns the
    page-ready time in seconds, from navigation to the step shown (printed too: ``pytest -s``).
    """
    with (
        static_server({"/": DIST, **mounts}) as base,
        chromium(browser) as page,
    ):
        url = studio_url(
            base,
            layout=f"{base}/run/layout.json",
            ds=ds,
            ds_url=ds_url.replace("BASE", base),
            time=time,
        )
        started = monotonic()
        page.navigate(url)
        page.wait_for(missing, timeout_s=READY_TIMEOUT_S, what="Table 2's step 1")
        ready_s = monotonic() - started
        if then is not None:
            page.wait_for(then, timeout_s=READY_TIMEOUT_S, what="the moment of the screenshot")
        page.pump(settle_s)
        assert is_png(page.screenshot(screenshot)), screenshot
        assert page.outside_requests() == []
    print(f"{ds}: page ready in {ready_s:.1f} s; screenshot {screenshot}")
    return ready_s


STEP6_HZ = {"/r1/camera": 13.0, "/r2/camera": 13.48}
"""Table 2's step 6, where both cameras share: the screenshot waits for it, so its plot shows the
steps before it."""


def missing_step6(page: DevTools) -> str | None:
    rows = table_rows(page.panel_texts().get(_panel("Table"), ""))
    for topic, rate in STEP6_HZ.items():
        shown = rows.get(topic, {}).get("rate_hz")
        if not _near(shown, rate):
            return f"allocation table: {topic} rate_hz {shown!r}, not {rate:g}"
    return None


def test_live_server_in_studio(browser: str, live_url: str, layout_dir: Path) -> None:
    target = os.environ.get("DBML_SCREENSHOT")
    screenshot = Path(target) if target else layout_dir.parent / "live.png"
    _open(
        browser,
        {"/run/": layout_dir},
        ds="foxglove-websocket",
        ds_url=live_url,
        screenshot=screenshot,
        missing=missing_live,
        then=missing_step6,
    )


def test_recording_opens_in_studio(browser: str, recording: Path, layout_dir: Path) -> None:
    _open(
        browser,
        {"/run/": layout_dir, "/data/": recording.parent},
        ds="remote-file",
        ds_url=f"BASE/data/{recording.name}",
        time=step1_time(recording),
        screenshot=layout_dir.parent / "recording.png",
    )
