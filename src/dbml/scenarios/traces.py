"""A link's capacity over time, recorded: what ``--link-trace`` replays on the testbed's link.

Two formats, both read from untrusted files and checked entry by entry:

- OpenNetLab's gym (``alphartc_gym/tests/data/*.json``): ``{"uplink": {"trace_pattern":
  [{"capacity": kbps, "duration": ms, "loss": fraction, "rtt": ms, "jitter": ms}, ...]}}``, in
  steps of about 200 ms, each lasting its ``duration`` after the one before;
- plain text: ``SECONDS:MBIT`` entries (as ``--link-schedule``), one a line or comma-separated,
  ``#`` comments, each rate in force from its time until the next.

A capacity of 0 (or below tc's 1 kbit/s) takes the link down until the next entry. Recorded
traces carry outliers (OpenNetLab's 4G_3mbps, of median 2.76 Mbit/s, has 200-ms steps of 80.1
and 8,040 Mbit/s): in a gym trace a capacity above ``OUTLIER_FACTOR`` times the trace's
median is clamped to the largest one that is not, and any above ``MAX_TRACE_MBIT`` to that; each
clamp is counted (``LinkTrace.clamped``). A plain trace is taken as written (but the bound).
"""

from __future__ import annotations

import bisect
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from dbml.core.errors import ConfigError
from dbml.core.spec import short_repr

__all__ = [
    "DOWN_BELOW_MBIT",
    "MAX_DELAY_MS",
    "MAX_TRACE_BYTES",
    "MAX_TRACE_ENTRIES",
    "MAX_TRACE_MBIT",
    "MAX_TRACE_S",
    "OUTLIER_FACTOR",
    "LinkTrace",
    "TraceEntry",
    "load_trace",
    "parse_gym_trace",
    "parse_plain_trace",
]

MAX_TRACE_ENTRIES = 100_000
"""The most entries a trace holds: 5.5 hours at OpenNetLab's 200-ms steps."""
MAX_TRACE_BYTES = 16 * 1024 * 1024
"""The largest trace file read."""
MAX_TRACE_S = 24 * 3600.0
"""The longest trace."""
OUTLIER_FACTOR = 10.0
"""In a recorded trace, a capacity this many times its median is a recording's outlier."""
MAX_TRACE_MBIT = 1_000.0
"""Above this a capacity is an outlier of the recording; clamped here (the testbed's links are
software: nothing it runs comes near)."""
DOWN_BELOW_MBIT = 0.001
"""tc's resolution, 1 kbit/s: a capacity under it takes the link down."""
MAX_DELAY_MS = 10_000.0
"""The longest round trip or jitter an entry may ask for."""
_KBIT_PER_MBIT = 1_000.0
_MS_PER_S = 1_000.0


@dataclass(frozen=True, slots=True)
class TraceEntry:
    """From ``at_s`` on, until the next entry: ``mbit`` of capacity (0: down), and impairments.

    ``loss`` is a fraction of packets in [0, 1]; ``delay_ms`` one-way (half the gym's rtt),
    ``jitter_ms`` its variation.
    """

    at_s: float
    mbit: float
    loss: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0


@dataclass(frozen=True, slots=True)
class LinkTrace:
    """A recorded link: its entries in time order, from 0 s, for ``duration_s``."""

    name: str
    entries: tuple[TraceEntry, ...]
    duration_s: float
    clamped: int = 0
    """Entries whose capacity was clamped: above ``MAX_TRACE_MBIT``, or a recording's outlier."""
    _times: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_times", tuple(e.at_s for e in self.entries))

    @property
    def schedule(self) -> tuple[tuple[float, float], ...]:
        """``(seconds, Mbit/s)`` at every change of capacity (as ``--link-schedule``'s)."""
        out: list[tuple[float, float]] = []
        for entry in self.entries:
            if not out or entry.mbit != out[-1][1]:
                out.append((entry.at_s, entry.mbit))
        return tuple(out)

    @property
    def impaired(self) -> bool:
        """Whether any entry asks for loss, delay or jitter besides the capacity."""
        return any(e.loss or e.delay_ms or e.jitter_ms for e in self.entries)

    @property
    def first_up_mbit(self) -> float | None:
        """The first capacity above 0 (what the link is built at); None if it is never up."""
        return next((e.mbit for e in self.entries if e.mbit > 0), None)

    @property
    def median_up_mbit(self) -> float | None:
        """The capacity the link has half its up time or more (None if it is never up).

        A radio's usual rate: what its buffer is sized for, and what a frame's transmission
        takes on it, where the trace's slowest steps are fades.
        """
        ends = [e.at_s for e in self.entries[1:]] + [max(self.duration_s, self.entries[-1].at_s)]
        up = sorted(
            (entry.mbit, until - entry.at_s)
            for entry, until in zip(self.entries, ends, strict=True)
            if entry.mbit > 0 and until > entry.at_s
        )
        half, total = sum(d for _, d in up) / 2, 0.0
        for mbit, seconds in up:
            total += seconds
            if total >= half:
                return mbit
        return None

    def mbit_at(self, t_s: float) -> float:
        """The capacity in force ``t_s`` seconds after the start (the last one past the end)."""
        index = bisect.bisect_right(self._times, t_s) - 1
        return self.entries[max(index, 0)].mbit

    def megabits(self, start_s: float, end_s: float) -> float:
        """The capacity integrated over ``[start_s, end_s)``: Mbit the link could carry."""
        total = 0.0
        ends = [e.at_s for e in self.entries[1:]] + [max(self.duration_s, end_s)]
        for entry, until in zip(self.entries, ends, strict=True):
            lo, hi = max(entry.at_s, start_s), min(until, end_s)
            if hi > lo:
                total += entry.mbit * (hi - lo)
        return total


def parse_gym_trace(text: str, *, name: str) -> LinkTrace:
    """OpenNetLab gym's JSON (module docstring); ``ConfigError`` naming the entry and value."""
    try:
        document = json.loads(text)
    except (ValueError, RecursionError) as exc:  # ValueError: also an integer of 4,300 digits
        raise ConfigError(f"trace {name!r}: not JSON ({str(exc)[:80]})") from None
    pattern = _field(document, "uplink", name=name, where="")
    pattern = _field(pattern, "trace_pattern", name=name, where="uplink.")
    if not isinstance(pattern, list) or not pattern:
        raise ConfigError(
            f"trace {name!r}: uplink.trace_pattern={short_repr(pattern)} must be a non-empty list"
        )
    _check_count(len(pattern), name)
    entries: list[TraceEntry] = []
    raw: list[float] = []
    at_s = 0.0
    for k, step in enumerate(pattern):
        where = f"uplink.trace_pattern[{k}]"
        if not isinstance(step, dict):
            raise ConfigError(f"trace {name!r}: {where}={short_repr(step)} must be an object")
        kbps = _number(step, "capacity", name=name, where=where, maximum=math.inf)
        duration_ms = _number(step, "duration", name=name, where=where, positive=True)
        loss = _number(step, "loss", name=name, where=where, maximum=1.0, default=0.0)
        rtt_ms = _number(step, "rtt", name=name, where=where, maximum=MAX_DELAY_MS, default=0.0)
        jitter_ms = _number(
            step, "jitter", name=name, where=where, maximum=MAX_DELAY_MS, default=0.0
        )
        mbit, _ = _capacity(kbps / _KBIT_PER_MBIT)
        entries.append(TraceEntry(at_s, mbit, loss, rtt_ms / 2, jitter_ms))
        raw.append(kbps / _KBIT_PER_MBIT)
        at_s += duration_ms / _MS_PER_S
        _check_duration(at_s, name)
    kept = _without_outliers(entries)
    clamped = sum(1 for e, mbit in zip(kept, raw, strict=True) if e.mbit < mbit and e.mbit > 0)
    return LinkTrace(name, kept, at_s, clamped)


def parse_plain_trace(text: str, *, name: str) -> LinkTrace:
    """``SECONDS:MBIT`` entries (module docstring); ``ConfigError`` naming the entry."""
    parts = [
        part.strip()
        for line in text.splitlines()
        for part in line.split("#", 1)[0].split(",")
        if part.strip()
    ]
    if not parts:
        raise ConfigError(f"trace {name!r}: no SECONDS:MBIT entry")
    _check_count(len(parts), name)
    entries: list[TraceEntry] = []
    clamped = 0
    for part in parts:
        at, sep, rate = part.partition(":")
        try:
            if not sep:
                raise ValueError(part)
            t_s, value = float(at), float(rate)
        except ValueError:
            raise ConfigError(f"trace {name!r}: {part!r} must be SECONDS:MBIT") from None
        if not (math.isfinite(t_s) and t_s >= 0):
            raise ConfigError(f"trace {name!r}: time {at.strip()!r} must be a number >= 0")
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"trace {name!r}: rate {rate.strip()!r} must be a number >= 0")
        if entries and t_s <= entries[-1].at_s:
            raise ConfigError(f"trace {name!r}: times must increase ({part!r})")
        if not entries and t_s != 0:
            raise ConfigError(f"trace {name!r}: the first entry must be at 0 s ({part!r})")
        _check_duration(t_s, name)
        mbit, over = _capacity(value)
        clamped += over
        entries.append(TraceEntry(t_s, mbit))
    # The last rate lasts as long as the one before it did (at least a second).
    last = entries[-1].at_s - entries[-2].at_s if len(entries) > 1 else 1.0
    return LinkTrace(name, tuple(entries), entries[-1].at_s + max(last, 1.0), clamped)


def load_trace(path: Path | str) -> LinkTrace:
    """A trace file: OpenNetLab's JSON if it parses as JSON, else ``SECONDS:MBIT`` text."""
    path = Path(path)
    try:
        with path.open("rb") as file:  # bounded: a FIFO or a device tells no size
            data = file.read(MAX_TRACE_BYTES + 1)
        if len(data) > MAX_TRACE_BYTES:
            raise ConfigError(f"trace {str(path)!r}: more than {MAX_TRACE_BYTES:,} bytes")
        text = data.decode("utf-8-sig")  # a byte-order mark is not content
    except OSError as exc:
        raise ConfigError(f"trace {str(path)!r}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"trace {str(path)!r}: not UTF-8 text") from None
    name = path.stem
    if text.lstrip().startswith(("{", "[")):
        return parse_gym_trace(text, name=name)
    return parse_plain_trace(text, name=name)


def _without_outliers(entries: list[TraceEntry]) -> tuple[TraceEntry, ...]:
    """``entries`` with each capacity above ``OUTLIER_FACTOR`` x the median clamped."""
    up = sorted(e.mbit for e in entries if e.mbit > 0)
    if not up:
        return tuple(entries)
    bound = OUTLIER_FACTOR * up[len(up) // 2]
    ceiling = max(m for m in up if m <= bound)
    return tuple(replace(e, mbit=ceiling) if e.mbit > bound else e for e in entries)


def _capacity(mbit: float) -> tuple[float, int]:
    """``mbit`` clamped to ``MAX_TRACE_MBIT`` (and 1 if it was), 0 below tc's resolution."""
    if mbit > MAX_TRACE_MBIT:
        return MAX_TRACE_MBIT, 1
    return (0.0 if mbit < DOWN_BELOW_MBIT else mbit), 0


def _field(document: Any, key: str, *, name: str, where: str) -> Any:
    if not isinstance(document, dict) or key not in document:
        raise ConfigError(f"trace {name!r}: {where}{key} is missing")
    return document[key]


def _number(
    step: dict[str, Any],
    key: str,
    *,
    name: str,
    where: str,
    maximum: float = math.inf,
    positive: bool = False,
    default: float | None = None,
) -> float:
    if key not in step and default is None:
        raise ConfigError(f"trace {name!r}: {where}.{key} is missing")
    value: object = step.get(key, default)
    number = math.nan
    if isinstance(value, int | float) and not isinstance(value, bool):
        try:
            number = float(value)
        except OverflowError:  # an integer past any float
            number = math.inf
    ok = math.isfinite(number) and (number > 0 if positive else number >= 0)
    if not (ok and number <= maximum):
        bound = "> 0" if positive else ">= 0"
        if maximum < math.inf:
            bound += f" and <= {maximum:g}"
        raise ConfigError(f"trace {name!r}: {where}.{key}={short_repr(value)} must be {bound}")
    return number


def _check_count(count: int, name: str) -> None:
    if count > MAX_TRACE_ENTRIES:
        raise ConfigError(f"trace {name!r}: {count:,} entries, more than {MAX_TRACE_ENTRIES:,}")


def _check_duration(t_s: float, name: str) -> None:
    if t_s > MAX_TRACE_S:
        raise ConfigError(f"trace {name!r}: it lasts past {MAX_TRACE_S:g} s ({t_s:g} s)")
