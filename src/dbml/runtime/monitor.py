"""What ``dbml monitor`` shows, as data: every live channel with its allocation and state.

The allocation and each channel's share of the budget are the optimizer's, from its newest
``RoundReport`` (``dbml.runtime.rounds``); the rest (hosts, priorities, sizes) from the graph and
the parameters. Before any report is heard a row shows the rate pushed, and no share.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dbml.core.errors import SpecError
from dbml.protocol import schema
from dbml.protocol.ladders import encoding_label
from dbml.protocol.messages import EstimatorState, RoundReport
from dbml.protocol.schema import PARAMETERS, Parameter
from dbml.runtime.graph import summarize
from dbml.runtime.params import read_snapshot
from dbml.transports.base import Transport

__all__ = ["MONITOR_PARAMETERS", "ChannelRow", "MonitorView", "channel_rows", "monitor_view"]

MONITOR_PARAMETERS = tuple(p for p in PARAMETERS if p.column is not None)
"""The parameters a row shows, in the schema's order, each with its header and format."""


@dataclass(frozen=True, slots=True)
class ChannelRow:
    """One live channel; ``share`` is of the budget in use."""

    topic: str
    host: str
    managed: bool
    priority: float
    size_bytes: float | None
    allocated_hz: float | None
    share: float | None
    status: str
    estimate_mbit: float | None = None
    estimator: str | None = None
    preference: str | None = None
    """A laddered channel's preference (None: no ladder)."""
    encoding: str | None = None
    """A laddered channel's rung, as the optimizer reported it; ``size_bytes`` is its bytes."""
    quality: float | None = None

    def value(self, parameter: Parameter) -> float | str | None:
        """The row's value of one of ``MONITOR_PARAMETERS``."""
        values: dict[Parameter, float | str | None] = {
            schema.PRIORITY: self.priority,
            schema.SIZE: self.size_bytes,
            schema.CURRENT: self.allocated_hz,
            schema.PREFERENCE: self.preference,
            schema.ENCODING: self.encoding,
        }
        return values[parameter]

    def as_json(self) -> dict[str, Any]:
        """The row as ``dbml monitor --json`` prints it."""
        return {
            "topic": self.topic,
            "host": self.host,
            "managed": self.managed,
            "priority": self.priority,
            "size_bytes": self.size_bytes,
            "allocated_hz": self.allocated_hz,
            "share": self.share,
            "status": self.status,
            "estimate_mbit": self.estimate_mbit,
            "estimator": self.estimator,
            "preference": self.preference,
            "encoding": self.encoding,
            "quality": self.quality,
        }


@dataclass(frozen=True, slots=True)
class MonitorView:
    """One update of the monitor: the rows and the global state above them."""

    rows: tuple[ChannelRow, ...]
    bandwidth_mbit: float | None
    estimate_mbit: float | None
    estimator: str | None
    status_message: str | None


def monitor_view(transport: Transport, report: RoundReport | None = None) -> MonitorView:
    """Read the graph and the (validated) parameters once, beside the optimizer's ``report``."""
    graph = summarize(transport.graph.entries())
    snapshot = read_snapshot(transport.params.snapshot())
    dbm = snapshot.dbm
    status = snapshot.globals.get(schema.STATUS)
    estimator_text = _estimator_text(snapshot.globals.get(schema.ESTIMATOR_STATE))
    reports = {} if report is None else report.by_topic()
    rows = []
    for topic in sorted(graph.publishers):
        channel = snapshot.channels.get(topic)
        if channel is None or channel.max_rate_hz is None:
            continue  # not a dbml channel (ROS 1's graph lists every topic, /rosout too)
        managed = topic in graph.managed
        reported = reports.get(topic)
        allocated = channel.current_rate_hz if reported is None else reported.rate_hz
        share = None if reported is None else reported.share
        laddered = channel.rungs is not None
        size = channel.size_bytes
        encoding = None
        if laddered and channel.encoding is not None:
            encoding = encoding_label(*channel.encoding)
        quality = None
        if reported is not None and reported.encoding is not None:
            encoding, quality, size = reported.encoding, reported.quality, reported.size_bytes
        if allocated is None:
            state = "no allocation"
        elif not managed:
            state = "unmanaged"
        else:
            state = str(status) if isinstance(status, str) else "managed"
        rows.append(
            ChannelRow(
                topic=topic,
                host=",".join(sorted(graph.hosts.get(topic, ()))),
                managed=managed,
                priority=channel.priority,
                size_bytes=size,
                allocated_hz=allocated,
                share=share,
                status=state,
                estimate_mbit=dbm.estimate_mbit,
                estimator=estimator_text,
                preference=channel.preference.value if laddered else None,
                encoding=encoding,
                quality=quality,
            )
        )
    message = snapshot.globals.get(schema.STATUS_MESSAGE)
    return MonitorView(
        rows=tuple(rows),
        bandwidth_mbit=dbm.bandwidth_mbit,
        estimate_mbit=dbm.estimate_mbit,
        estimator=estimator_text,
        status_message=message if isinstance(message, str) else None,
    )


def _estimator_text(value: object) -> str | None:
    """The estimator's state as a line to read (its JSON is for programs); None if malformed."""
    if not isinstance(value, str):
        return None
    try:
        return EstimatorState.decode(value).text
    except SpecError:
        return None


def channel_rows(transport: Transport, report: RoundReport | None = None) -> list[ChannelRow]:
    """Every live channel as ``dbml monitor`` shows it."""
    return list(monitor_view(transport, report).rows)
