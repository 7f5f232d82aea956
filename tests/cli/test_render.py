"""The rich tables: what a person reads in the terminal."""

from __future__ import annotations

from dbml.cli.render import monitor_table
from dbml.runtime.monitor import ChannelRow, MonitorView


def test_the_monitor_shows_the_schemas_columns_and_a_rows_values() -> None:
    row = ChannelRow(
        topic="/r1/camera",
        host="r1",
        managed=True,
        priority=0.5,
        size_bytes=84_000.0,
        allocated_hz=12.37,
        share=0.7556,
        status="optimal",
    )
    view = MonitorView(
        rows=(row,), bandwidth_mbit=11.0, estimate_mbit=None, estimator=None, status_message=None
    )
    table = monitor_table(view)
    headers = [str(column.header) for column in table.columns]
    assert headers == [
        "topic",
        "host",
        "managed",
        "priority",
        "size B",
        "allocated Hz",
        "share",
        "status",
    ]
    cells = [next(iter(column.cells)) for column in table.columns]
    assert cells == ["/r1/camera", "r1", "yes", "0.50", "84,000", "12.37", "75.6%", "optimal"]
    assert table.title == "dbml monitor — budget 11 Mbit/s"


def test_the_monitor_shows_a_laddered_channels_preference_and_rung() -> None:
    plain = ChannelRow("/r1/scan", "r1", True, 0.0, 2_000.0, 5.0, 0.01, "optimal")
    laddered = ChannelRow(
        "/r1/camera",
        "r1",
        True,
        1.0,
        41_227.0,
        16.0,
        0.48,
        "optimal",
        preference="keep_rate",
        encoding="x1 q50",
        quality=0.95,
    )
    view = MonitorView(
        rows=(plain, laddered),
        bandwidth_mbit=11.0,
        estimate_mbit=None,
        estimator=None,
        status_message=None,
    )
    table = monitor_table(view)
    headers = [str(column.header) for column in table.columns]
    assert headers[5:8] == ["allocated Hz", "prefer", "encoding"]
    cells = {str(c.header): list(c.cells) for c in table.columns}
    assert cells["encoding"] == ["-", "x1 q50"]
    assert cells["prefer"] == ["-", "keep_rate"]
