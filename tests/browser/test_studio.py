"""Foxglove Studio, a real one in headless Chromium, shows dbml's view with the shipped layout.

Two ways in, one layout: a recording (``ds=remote-file``: Studio reads the MCAP by byte ranges)
and a live server (``ds=foxglove-websocket``). The recording opens at Table 2's first step and
the page must show it (/r1/camera 12.37 Hz, /r2/camera 16 Hz, 11 Mbit/s). The live page loads
while the demo runs, after a moment no test can choose (3.5 s on a quiet machine, 15 s on a busy
one): it must show whichever of Table 2's allocations is in force, then follow the demo to the
next one. Each test checks that nothing left the machine and keeps a screenshot; the live one's
goes to ``$DBML_SCREENSHOT`` when set (the README's docs/foxglove.png, taken at step 6).

The data is the main job's: ``dbml demo teleop --foxglove PORT --record FILE``, watched live,
then its recording.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import socket
import subprocess
import time
from collections.abc import Callable, Iterator, Mapping
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

pytestmark = [pytest.mark.browser, pytest.mark.alone]

READY_TIMEOUT_S = 90.0

BUDGET_MBIT = 11.0
TOPICS = ("/r1/camera", "/r2/camera")


@dataclass(frozen=True, slots=True)
class Shown:
    """One of Table 2's allocations as the view shows it: each camera's rate and floor (Hz).

    The rates are the paper's; the floors are eq. 4's, worked by hand from the step's
    priorities (eq. 2 weighs a priority by its message size: 84,000 and 21,000 bytes).
    """

    name: str
    rates_hz: tuple[float, float]
    floors_hz: tuple[float, float]


STEP1 = Shown("steps 1, 8-10", (12.37, 16.0), (1.0, 16.0))
"""Only R2 has a priority: eq. 2 gives it all the weight, eq. 4 its maximum as its floor."""
STEP2 = Shown("step 2 (and before step 1)", (12.37, 16.0), (1.0, 1.0))
"""No priority: both floors at the minimum."""
STEP3 = Shown("steps 3-5, 7", (16.0, 1.48), (16.0, 1.0))
"""Only R1 has a priority."""
STEP6 = Shown("step 6", (13.0, 13.48), (13.0, 4.0))
"""Equal priorities (tc 15 s): p' is 0.8 and 0.2, so the floors are 15 x p' + 1."""
SEQUENCE = (STEP2, STEP1, STEP2, STEP3, STEP3, STEP3, STEP6, STEP3, STEP1, STEP1, STEP1)
"""What the demo shows, in order: before its first step, then Table 2's ten."""
NEXT: Mapping[Shown, frozenset[Shown]] = {
    shown: frozenset(b for a, b in itertools.pairwise(SEQUENCE) if a == shown and b != a)
    for shown in SEQUENCE
}
"""Which allocation the demo goes to from each (the ones it holds for several steps included)."""


# --- the two data sources: a live demo, then its recording ---------------------------------------

DEMO_STEP_S = 5.0
"""Each allocation holds 5-15 s: long enough for the page to draw one before the next."""
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
            if len(priorities) == len(TOPICS) and any(priorities):
                at = datetime.fromtimestamp(message.log_time / 1e9 + 1.0, tz=UTC)
                return at.isoformat().replace("+00:00", "Z")
    raise AssertionError(f"{record}: no allocation of step 1")


# --- the browser ----------------------------------------------------------------------------------


@pytest.fixture
def browser() -> str:
    return require_browser()


LAYOUT = studio_layout(cameras=DEFAULT_CAMERAS, channels=list(TOPICS))


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


def _shown_rows(page: DevTools) -> tuple[Shown | None, str]:
    """Which of Table 2's allocations the allocation table shows, and what it shows."""
    rows = table_rows(page.panel_texts().get(_panel("Table"), ""))
    cells = [(rows.get(t, {}).get("rate_hz"), rows.get(t, {}).get("floor_hz")) for t in TOPICS]
    for shown in (STEP1, STEP2, STEP3, STEP6):
        pairs = zip(cells, shown.rates_hz, shown.floors_hz, strict=True)
        if all(_near(rate, r) and _near(floor, f) for (rate, floor), r, f in pairs):
            return shown, ""
    return None, f"allocation table: (rate_hz, floor_hz) {cells}, not one of Table 2's"


def missing_allocation(page: DevTools, shown: Shown) -> str | None:
    """What the page does not show yet of allocation ``shown`` (None: all of it).

    The allocation table's rate_hz and floor_hz columns, the rates in the plot's legend, the
    budget panel's budget_mbit, and a frame (its stamp) in each camera's image panel.
    """
    found, gap = _shown_rows(page)
    if found != shown:
        return gap or f"allocation table: {found.name if found else None}, not {shown.name}"
    panels = page.panel_texts()
    legend = panels.get(_panel("Plot"), "").split()
    for rate in shown.rates_hz:
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


def missing_step1(page: DevTools) -> str | None:
    """Table 2's first step, where a recording opens."""
    return missing_allocation(page, STEP1)


class LiveAllocations:
    """The live page's allocations as it follows the demo: any of Table 2's, then the next.

    The first is whichever the page shows once loaded, whole (table, plot, budget, frames and
    the server's parameters in the Parameters panel); the next must be one the demo goes to from
    it, shown whole too: the page follows the live allocation, not one it happened to load on.
    """

    def __init__(self) -> None:
        self.seen: list[Shown] = []

    def missing(self, page: DevTools) -> str | None:
        found, rows = _shown_rows(page)
        if found is None:
            return rows
        if self.seen and found == self.seen[-1]:
            return f"still {found.name}: waiting for the demo's next allocation"
        if self.seen and found not in NEXT[self.seen[-1]]:
            raise AssertionError(f"the page went from {self.seen[-1].name} to {found.name}")
        gap = missing_allocation(page, found)
        if gap is None and "/dbm/max_bandwidth_in_mbit" not in page.panel_texts().get(
            _panel("Parameters"), ""
        ):
            gap = "parameters panel: no /dbm/max_bandwidth_in_mbit"
        if gap is not None:
            return gap
        self.seen.append(found)
        return None if len(self.seen) >= 2 else f"{found.name} shown: waiting for the next"


def _open(
    browser: str,
    mounts: dict[str, Path],
    *,
    ds: str,
    ds_url: str,
    screenshot: Path,
    missing: Callable[[DevTools], str | None] = missing_step1,
    settle_s: float = 1.0,
    time: str | None = None,
    then: Callable[[DevTools], str | None] | None = None,
) -> float:
    """Load the page on ``ds``, wait until nothing is ``missing``, keep a screenshot.

    ``mounts`` are served beside the page (``/run/`` holds layout.json); ``BASE`` in ``ds_url``
    stands for the server's address; ``time`` (RFC 3339) is where a recording opens. The
    screenshot is taken ``settle_s`` after the page showed what it waits for (the plot and images
    draw what the text already shows), after ``then`` shows nothing missing if given. Returns
    the seconds from navigation to nothing ``missing`` (printed too: ``pytest -s``).
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
        page.wait_for(missing, timeout_s=READY_TIMEOUT_S, what="Table 2's allocations")
        ready_s = monotonic() - started
        if then is not None:
            page.wait_for(then, timeout_s=READY_TIMEOUT_S, what="the moment of the screenshot")
        page.pump(settle_s)
        assert is_png(page.screenshot(screenshot)), screenshot
        assert page.outside_requests() == []
    print(f"{ds}: shown {ready_s:.1f} s after navigation; screenshot {screenshot}")
    return ready_s


def test_live_server_in_studio(browser: str, live_url: str, layout_dir: Path) -> None:
    target = os.environ.get("DBML_SCREENSHOT")
    screenshot = Path(target) if target else layout_dir.parent / "live.png"
    live = LiveAllocations()
    _open(
        browser,
        {"/run/": layout_dir},
        ds="foxglove-websocket",
        ds_url=live_url,
        screenshot=screenshot,
        missing=live.missing,
        # The README's picture: step 6, where both cameras share, after the steps before it.
        then=(lambda page: missing_allocation(page, STEP6)) if target else None,
    )
    assert len(live.seen) == 2, live.seen


def test_recording_opens_in_studio(browser: str, recording: Path, layout_dir: Path) -> None:
    _open(
        browser,
        {"/run/": layout_dir, "/data/": recording.parent},
        ds="remote-file",
        ds_url=f"BASE/data/{recording.name}",
        time=step1_time(recording),
        screenshot=layout_dir.parent / "recording.png",
    )
