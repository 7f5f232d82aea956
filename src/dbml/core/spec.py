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

__all__ = ["BYTES_PER_S_PER_MBIT", "ChannelSpec", "LinkSpec", "Problem"]

BYTES_PER_S_PER_MBIT = 125_000.0
"""1 Mbit/s = 10**6 bit/s = 125,000 bytes/s (the paper's 11 Mbit is 1,375,000 B/s)."""

FloatArray = npt.NDArray[np.float64]


def _finite_number(owner: str, name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise SpecError(f"{owner}: {name}={value!r} is not a number")
    number = float(value)
    if not math.isfinite(number):
        raise SpecError(f"{owner}: {name}={value!r} is not finite")
    return number


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
        fmin = _finite_number(owner, "frequency.min", self.min_rate_hz)
        fmax = _finite_number(owner, "frequency.max", self.max_rate_hz)
        size = _finite_number(owner, "message_size_in_bytes", self.size_bytes)
        priority = _finite_number(owner, "priority", self.priority)
        if fmin <= 0:
            raise SpecError(f"{owner}: frequency.min={self.min_rate_hz!r} must be > 0")
        if fmin > fmax:
            raise SpecError(
                f"{owner}: frequency.min={self.min_rate_hz!r} exceeds "
                f"frequency.max={self.max_rate_hz!r}"
            )
        if size <= 0:
            raise SpecError(f"{owner}: message_size_in_bytes={self.size_bytes!r} must be > 0")
        if not 0.0 <= priority <= 1.0:
            raise SpecError(f"{owner}: priority={self.priority!r} must be within [0, 1]")
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
        capacity = _finite_number(owner, "max_bandwidth_in_mbit", self.capacity_mbit)
        if capacity <= 0:
            raise SpecError(f"{owner}: max_bandwidth_in_mbit={self.capacity_mbit!r} must be > 0")
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
    """

    channels: tuple[ChannelSpec, ...]
    bandwidth_mbit: float
    utilization: float = 1.0
    links: tuple[LinkSpec, ...] = ()
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
        bandwidth = _finite_number("problem", "max_bandwidth_in_mbit", self.bandwidth_mbit)
        if bandwidth <= 0:
            raise SpecError(f"problem: max_bandwidth_in_mbit={self.bandwidth_mbit!r} must be > 0")
        utilization = _finite_number("problem", "max_bandwidth_utilization", self.utilization)
        if not 0.0 < utilization <= 1.0:
            raise SpecError(
                f"problem: max_bandwidth_utilization={self.utilization!r} must be within (0, 1]"
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
        return self.bandwidth_mbit * BYTES_PER_S_PER_MBIT

    @property
    def budget_bytes_per_s(self) -> float:
        """What the managed channels may use together."""
        return self.link_bytes_per_s * self.utilization
