"""Specifications of the allocation problem: channels, links and the problem itself.

Values are validated once, here, so strategies can assume well-formed input.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from dbml.core.errors import SpecError

__all__ = [
    "BYTES_PER_S_PER_MBIT",
    "MAX_BANDWIDTH_MBIT",
    "MAX_HEADROOM_SHARE",
    "MAX_PERIOD_S",
    "MAX_RATE_HZ",
    "MAX_SIZE_BYTES",
    "MIN_PERIOD_S",
    "SHORT_REPR_CHARS",
    "ChannelSpec",
    "LinkSpec",
    "Problem",
    "bytes_per_s_to_mbit",
    "check_number",
    "check_priority",
    "mbit_to_bytes_per_s",
    "short_repr",
]

BYTES_PER_S_PER_MBIT = 125_000.0
"""1 Mbit/s = 10**6 bit/s = 125,000 bytes/s (the paper's 11 Mbit is 1,375,000 B/s)."""


def mbit_to_bytes_per_s(mbit: float) -> float:
    """Mbit/s to bytes/s, the unit dbml computes in."""
    return mbit * BYTES_PER_S_PER_MBIT


def bytes_per_s_to_mbit(bytes_per_s: float) -> float:
    """Bytes/s to Mbit/s, the unit people and the paper's parameters use."""
    return bytes_per_s / BYTES_PER_S_PER_MBIT


FloatArray = npt.NDArray[np.float64]

MAX_BANDWIDTH_MBIT = 1e6
"""1 Tbit/s: above any link a fleet shares; a larger budget is a mistake or an attack."""
MAX_RATE_HZ = 1e6
"""1 MHz: far above any stream's rate (and above what one publisher can send), yet it refuses
the 1e12 or infinity that would turn off the rate limit."""
MAX_SIZE_BYTES = 1e9
"""1 GB: above any single message; a larger size would starve every other channel."""
MIN_PERIOD_S = 0.01
"""The shortest optimisation period: shorter ones only flood the store with heartbeats."""
MAX_PERIOD_S = 3600.0
"""The longest optimisation period: an hour without a heartbeat leaves no fail-safe."""
MAX_HEADROOM_SHARE = 0.5
"""The most of a budget that ``frame_headroom`` keeps back."""


SHORT_REPR_CHARS = 80
"""Values are cut to this many characters in messages: a 400-digit number is no one-liner."""


def short_repr(value: object) -> str:
    """``repr(value)``, cut to ``SHORT_REPR_CHARS`` with ``...``."""
    text = repr(value)
    return text if len(text) <= SHORT_REPR_CHARS else f"{text[: SHORT_REPR_CHARS - 3]}..."


def check_number(
    value: object,
    *,
    field: str,
    owner: str | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
    finite: bool = True,
) -> float:
    """The one validation of a number: ``value`` as a float, or a ``SpecError`` naming it.

    Booleans are not numbers; NaN never passes; infinities pass only with ``finite=False``.
    The range is ``[minimum, maximum]`` (``(minimum, maximum]`` with ``exclusive_minimum``),
    either end optional. Messages read ``owner: field=value must be ...``.
    """
    where = f"{owner}: " if owner else ""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise SpecError(f"{where}{field}={short_repr(value)} is not a number")
    try:
        number = float(value)
    except OverflowError:  # an int too large for a float (10**400)
        raise SpecError(f"{where}{field}={short_repr(value)} is not finite") from None
    if math.isnan(number):
        raise SpecError(
            f"{where}{field}={short_repr(value)} is {'not finite' if finite else 'not a number'}"
        )
    if finite and math.isinf(number):
        raise SpecError(f"{where}{field}={short_repr(value)} is not finite")
    low_ok = minimum is None or (number > minimum if exclusive_minimum else number >= minimum)
    high_ok = maximum is None or number <= maximum
    if not (low_ok and high_ok):
        bounds = _range(minimum, maximum, exclusive_minimum=exclusive_minimum)
        raise SpecError(f"{where}{field}={short_repr(value)} must be {bounds}")
    return number


def check_priority(value: object, *, field: str = "priority", owner: str | None = None) -> float:
    """A raw priority: a number in [0, 1] (the one rule, wherever a priority enters)."""
    return check_number(value, field=field, owner=owner, minimum=0, maximum=1)


def _range(minimum: float | None, maximum: float | None, *, exclusive_minimum: bool) -> str:
    if minimum is not None and maximum is not None:
        return f"within {'(' if exclusive_minimum else '['}{minimum:g}, {maximum:g}]"
    if minimum is not None:
        return f"{'>' if exclusive_minimum else '>='} {minimum:g}"
    return f"<= {maximum:g}"


@dataclass(frozen=True, slots=True)
class ChannelSpec:
    """One stream: its rate bounds, its message size and its raw priority in [0, 1]."""

    topic: str
    min_rate_hz: float
    max_rate_hz: float
    size_bytes: float
    priority: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.topic, str) or not self.topic:
            raise SpecError(f"channel topic={self.topic!r} must be a non-empty string")
        owner = f"channel {self.topic!r}"
        fmin = check_number(self.min_rate_hz, field="frequency.min", owner=owner)
        fmax = check_number(self.max_rate_hz, field="frequency.max", owner=owner)
        size = check_number(self.size_bytes, field="message_size_in_bytes", owner=owner)
        check_number(fmin, field="frequency.min", owner=owner, minimum=0, exclusive_minimum=True)
        check_number(fmax, field="frequency.max", owner=owner, maximum=MAX_RATE_HZ)
        if fmin > fmax:
            raise SpecError(
                f"{owner}: frequency.min={self.min_rate_hz!r} exceeds "
                f"frequency.max={self.max_rate_hz!r}"
            )
        check_number(
            size, field="message_size_in_bytes", owner=owner, minimum=0, exclusive_minimum=True
        )
        check_number(size, field="message_size_in_bytes", owner=owner, maximum=MAX_SIZE_BYTES)
        priority = check_priority(self.priority, owner=owner)
        object.__setattr__(self, "min_rate_hz", fmin)
        object.__setattr__(self, "max_rate_hz", fmax)
        object.__setattr__(self, "size_bytes", size)
        object.__setattr__(self, "priority", priority)


@dataclass(frozen=True, slots=True)
class LinkSpec:
    """A capacity constraint shared by the channels that cross it (a robot's uplink, a radio)."""

    name: str
    capacity_mbit: float
    topics: tuple[str, ...]

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise SpecError(f"link name={self.name!r} must be a non-empty string")
        owner = f"link {self.name!r}"
        capacity = check_number(
            self.capacity_mbit,
            field="max_bandwidth_in_mbit",
            owner=owner,
            minimum=0,
            exclusive_minimum=True,
        )
        topics = tuple(self.topics)
        if not topics:
            raise SpecError(f"{owner}: channels=[] must name at least one channel")
        if len(set(topics)) != len(topics):
            raise SpecError(f"{owner}: channels={list(topics)!r} lists a channel twice")
        object.__setattr__(self, "capacity_mbit", capacity)
        object.__setattr__(self, "topics", topics)


@dataclass(frozen=True, slots=True)
class _Arrays:
    """Column view of the channels, built once per problem for the vectorised strategies."""

    size_bytes: FloatArray
    min_rate_hz: FloatArray
    max_rate_hz: FloatArray
    priority: FloatArray
    size_order: npt.NDArray[np.intp]
    """Channels by ascending size, ties in declaration order: the tie-break's order. It depends
    on sizes only, so it is computed once per problem rather than per allocation."""


def _column(values: list[float]) -> FloatArray:
    array = np.array(values, dtype=float)
    array.flags.writeable = False
    return array


@dataclass(frozen=True, slots=True)
class Problem:
    """Channels sharing a link of ``bandwidth_mbit``, of which ``utilization`` may be used.

    ``budget_bytes_per_s`` is ``bandwidth_mbit * 125000 * utilization``; utilization below 1
    reserves bandwidth for unmanaged traffic such as commands. ``links`` add per-link limits
    (strategy ``lp`` only); the same utilization applies to each link's capacity.

    ``frame_headroom`` keeps one message of every channel but the largest out of the budget:
    frames go out whole, so in a 1-s window a channel at rate ``f`` sends up to ``f + 1``
    messages; with the headroom every window on the wire stays within the budget plus one
    message, whatever the phases. Off by default (it changes the paper's Table 2).
    """

    channels: tuple[ChannelSpec, ...]
    bandwidth_mbit: float
    utilization: float = 1.0
    links: tuple[LinkSpec, ...] = ()
    frame_headroom: bool = False
    arrays: _Arrays = field(init=False, repr=False, compare=False)
    topics: tuple[str, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        channels = tuple(self.channels)
        if not channels:
            raise SpecError("problem: channels=[] must hold at least one channel")
        topics = [channel.topic for channel in channels]
        duplicates = [topic for topic, count in Counter(topics).items() if count > 1]
        if duplicates:
            raise SpecError(f"channel {duplicates[0]!r}: topic={duplicates[0]!r} is declared twice")
        bandwidth = check_number(
            self.bandwidth_mbit,
            field="max_bandwidth_in_mbit",
            owner="problem",
            minimum=0,
            exclusive_minimum=True,
        )
        utilization = check_number(
            self.utilization,
            field="max_bandwidth_utilization",
            owner="problem",
            minimum=0,
            maximum=1,
            exclusive_minimum=True,
        )
        links = tuple(self.links)
        known = set(topics)
        names: set[str] = set()
        for link in links:
            if link.name in names:
                raise SpecError(f"link {link.name!r}: name={link.name!r} is declared twice")
            names.add(link.name)
            for topic in link.topics:
                if topic not in known:
                    raise SpecError(f"link {link.name!r}: channels lists unknown topic {topic!r}")
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "bandwidth_mbit", bandwidth)
        object.__setattr__(self, "utilization", utilization)
        object.__setattr__(self, "links", links)
        sizes = _column([c.size_bytes for c in channels])
        order = np.argsort(sizes, kind="stable")
        order.flags.writeable = False
        object.__setattr__(self, "topics", tuple(topics))
        object.__setattr__(
            self,
            "arrays",
            _Arrays(
                size_bytes=sizes,
                min_rate_hz=_column([c.min_rate_hz for c in channels]),
                max_rate_hz=_column([c.max_rate_hz for c in channels]),
                priority=_column([c.priority for c in channels]),
                size_order=order,
            ),
        )

    @property
    def link_bytes_per_s(self) -> float:
        """The link's full bandwidth, the reference of the paper's "Bandwidth (%)" column."""
        return mbit_to_bytes_per_s(self.bandwidth_mbit)

    @property
    def headroom_bytes_per_s(self) -> float:
        """What ``frame_headroom`` keeps back: one message per channel but the largest.

        At most ``MAX_HEADROOM_SHARE`` of the configured budget, so a budget smaller than the
        messages themselves still allocates something (and its windows are over, as any are).
        """
        if not self.frame_headroom:
            return 0.0
        sizes = self.arrays.size_bytes
        headroom = float(sizes.sum() - sizes.max())
        return min(headroom, MAX_HEADROOM_SHARE * self.link_bytes_per_s * self.utilization)

    @property
    def budget_bytes_per_s(self) -> float:
        """What the managed channels may use together (less any frame headroom)."""
        return self.link_bytes_per_s * self.utilization - self.headroom_bytes_per_s
