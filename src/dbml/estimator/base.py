"""What every part of the estimator speaks: frames, results, one update's view, the detector.

The shared loop (:mod:`dbml.estimator.shared`) keeps the streams and reads outages; a design is
a :class:`Detector` that reads overuse from a :class:`View` of one update and moves the
estimate. This module holds the words both sides use and the measurements more than one of
them takes (rates, packet pairs, slopes), so that a design is a module of its own that imports
only this one. Pure: every time is an argument.
"""

from __future__ import annotations

import enum
import itertools
import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from dbml.core.errors import SpecError
from dbml.core.spec import bytes_per_s_to_mbit

__all__ = [
    "BURST_FACTOR",
    "PATH_S",
    "RATE_FRAMES",
    "Arrival",
    "Decision",
    "Detector",
    "DetectorSettings",
    "Estimate",
    "Judged",
    "Phase",
    "Sample",
    "SharedSettings",
    "View",
    "behind",
    "bunched",
    "busy_rate_mbit",
    "check_positive",
    "check_shares",
    "receive_rate_mbit",
    "slope",
]

RATE_FRAMES = 4
"""A rate needs this many frames: fewer in a window, and the last few stand in for it."""
_MIN_SLOPE_POINTS = 3
"""A trend needs at least this many points."""
_MIN_SPREAD_S2 = 1e-6
"""Below this variance of times (s^2), points are simultaneous: no slope."""

Sample = tuple[float, float, int]
"""One kept frame: (arrival time, one-way or queueing delay, size in bytes)."""


class Phase(enum.StrEnum):
    """What the estimator is doing: probing up, holding, or cutting after overuse."""

    INCREASE = "increase"
    HOLD = "hold"
    DECREASE = "decrease"
    OUTAGE = "outage"


@dataclass(frozen=True, slots=True)
class Arrival:
    """One frame received from a stream (one publisher's topic as one receiver gets it)."""

    stream: str
    seq: int
    sent_s: float
    """The sender's clock; it may differ from the receiver's by a constant offset."""
    arrival_s: float
    """The estimator's clock."""
    size_bytes: int


@dataclass(frozen=True, slots=True)
class Estimate:
    """The estimator's state after an update."""

    t_s: float
    estimate_mbit: float
    phase: Phase
    received_mbit: float
    """What arrived over the last window, in Mbit/s."""
    queue_delay_s: float
    delay_trend: float
    """Seconds of queueing delay gained per second (negative while the queue drains)."""
    lost: int
    """Frames lost (sequence gaps) since the previous update."""
    reason: str = ""
    """Why the design decided as it did, for a person (``dbml monitor``); may be empty."""


@dataclass(frozen=True, slots=True)
class Judged:
    """One stream whose delays speak for the link at this update."""

    latest_s: float
    """Its newest frame's queueing delay (over its least delay in ``base_window_s``)."""
    least_s: float
    """The least queueing in the trend window: a frame that waited behind another's is not a
    standing queue, the least one is."""
    slope: float
    """Seconds of queueing gained per second over the trend window."""
    samples: deque[Sample]
    """Its kept frames with their one-way delays, oldest first (read only)."""
    window: list[Sample]
    """Its frames of the trend window (or its last few, if slow), with queueing delays."""


@dataclass(frozen=True, slots=True)
class View:
    """What one update measured, for the detector that decides on it."""

    now_s: float
    dt_s: float
    settling: bool
    """After an outage: the backlog drains, nothing is judged yet."""
    lost: int
    recent: list[Sample]
    """(arrival, queueing delay, size) of all streams' kept frames, in arrival order."""
    judged: list[Judged]
    """The streams that speak for the link, each judged on its own: a publisher's backlog sits
    in its own connection's buffers."""
    received: float
    cut_rate: float
    """The receive rate, with a silent stream's share as before its silence."""
    estimate_mbit: float
    """The estimate before this update."""
    max_mbit: float
    speaks: Callable[[str], bool | None]
    """Whether a stream's delays speak for the link now (None: the stream is not followed)."""

    def pairs(self, window_s: float) -> list[Sample]:
        """The frames of the last window (and the one before them): the packet pairs."""
        window = [r for r in self.recent if r[0] > self.now_s - window_s]
        return self.recent[-len(window) - 1 :] if len(window) >= RATE_FRAMES else self.recent[-5:]


@dataclass(frozen=True, slots=True)
class Decision:
    """What a detector decided: the phase and the estimate (the loop keeps it in bounds)."""

    phase: Phase
    estimate_mbit: float
    reason: str = ""
    """Why, in a few words with the figures that decided (``Estimate.reason``)."""


class Detector(Protocol):
    """One design: how overuse is read and what a cut and an increase are.

    The shared loop tells it each frame it kept and each stream whose history restarts, and
    asks it for a decision once an update has measured the streams (not during an outage).
    """

    def observe(self, arrival: Arrival) -> None:
        """A frame the loop kept (its delay is in its stream's history)."""

    def forget(self, stream: str | None) -> None:
        """``stream``'s history restarts.

        None: every stream's, and the frames not yet decided on (the link is down).
        """

    def decide(self, view: View) -> Decision:
        """The phase and the estimate after ``view``."""


class SharedSettings(Protocol):
    """What a design reads of the settings every design shares (``EstimatorSettings``).

    A protocol, so a design needs nothing of the shared loop's module (which makes the default
    design, and would import it back).
    """

    @property
    def window_s(self) -> float:
        """The delay trend is measured over this much recent time."""

    @property
    def rate_window_s(self) -> float:
        """The receive rate is measured over this much recent time."""

    @property
    def response_s(self) -> float:
        """After a decrease, how long the senders take to act on it."""

    @property
    def probe_fraction(self) -> float:
        """Below this share of the estimate received, more would not show: no increase."""


@runtime_checkable
class DetectorSettings(Protocol):
    """A design's own settings (a frozen dataclass): they make its detector."""

    def detector(self, shared: SharedSettings) -> Detector:
        """A fresh detector (it keeps state: one per estimator)."""


def check_positive(owner: str, settings: object, names: Iterable[str]) -> None:
    """Each of ``names`` is a finite number above 0; ``SpecError`` naming it if not."""
    for name in names:
        value = getattr(settings, name)
        if not (math.isfinite(value) and value > 0):
            raise SpecError(f"{owner} {name}={value!r} must be a positive number")


def check_shares(owner: str, settings: object, names: Iterable[str]) -> None:
    """Each of ``names`` is in (0, 1]; ``SpecError`` naming it if not."""
    for name in names:
        value = getattr(settings, name)
        if not 0 < value <= 1:
            raise SpecError(f"{owner} {name}={value!r} must be in (0, 1]")


def slope(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of y over t; 0 without enough spread."""
    if len(points) < _MIN_SLOPE_POINTS:
        return 0.0
    n = len(points)
    mean_t = sum(t for t, _ in points) / n
    mean_y = sum(y for _, y in points) / n
    var = sum((t - mean_t) ** 2 for t, _ in points)
    if var < _MIN_SPREAD_S2:
        return 0.0
    return sum((t - mean_t) * (y - mean_y) for t, y in points) / var


PATH_S = 0.05
"""A path's own delay beyond a frame's transmission (propagation, the hops, the stacks) is
below this."""


BURST_FACTOR = 4.0
"""Frames that arrive this many times faster than the link could be came out together after a
stall (a link faster than the configured budget is not one: a fade's backlog on a 14-Mbit/s
radio under a 10-Mbit/s budget crosses at the radio's rate, and reads it)."""


def behind(
    previous: Sample,
    frame: Sample,
    queued_s: float,
    fastest_mbit: float | None,
    *,
    same_instant: bool = False,
) -> bool:
    """Whether ``frame`` crossed right behind ``previous``: it queued, and the link did not idle.

    ``fastest_mbit`` (the fastest the link could be): the link idled before ``frame`` if it
    arrived longer after ``previous`` than its one-way delay could be, its queueing plus its
    own transmission at that rate plus ``PATH_S``: it was sent after ``previous`` arrived, and
    its delay is a fade's or its own transmission on a link slower than its stream's fastest (a
    radio's rate moves), not a wait for ``previous``. None: every frame that queued counts.
    ``same_instant``: one that arrived with ``previous`` counts too (a burst, read with its stall).
    """
    (t_prev, _, _), (t, queue, size) = previous, frame
    return (
        queue > queued_s
        and (t >= t_prev if same_instant else t > t_prev)
        and (fastest_mbit is None or t - t_prev <= queue + size * 8e-6 / fastest_mbit + PATH_S)
    )


def bunched(previous: Sample, frame: Sample, fastest_mbit: float) -> bool:
    """Whether ``frame`` came out with ``previous`` after a stall.

    It arrived ``BURST_FACTOR`` times faster than ``fastest_mbit`` could carry it.
    """
    return frame[2] * 8e-6 > BURST_FACTOR * fastest_mbit * (frame[0] - previous[0])


def busy_rate_mbit(
    ordered: list[Sample],
    queued_s: float,
    *,
    least: int = 1,
    fastest_mbit: float | None = None,
) -> float | None:
    """Delivery rate while the link was busy; None from fewer than ``least`` packet pairs.

    A frame that waited in the queue (:func:`behind` the one before it) arrived as soon as that
    one had, so its size over that gap is the link's rate (packet pairs). The median pair: one
    that spans a fade (its gap the fade's length) says nothing of the rate after it. A frame
    sent after the link went idle measures what was offered, not the link. Given
    ``fastest_mbit``, frames that arrive ``BURST_FACTOR`` times faster than it are one reading
    with the pair before them.
    """
    readings: list[list[float]] = []  # [bytes, seconds]: a pair, or a stall and its burst
    last: Sample | None = None  # the frame the last reading ends with
    burst = False  # the last reading ends with a burst
    for previous, frame in itertools.pairwise(ordered):
        if not behind(
            previous, frame, queued_s, fastest_mbit, same_instant=fastest_mbit is not None
        ):
            continue
        size, gap_s = frame[2], frame[0] - previous[0]
        together = fastest_mbit is not None and bunched(previous, frame, fastest_mbit)
        if (together or burst) and last is previous:
            # Far faster than the link could be: the frames came out together after a stall (TCP
            # holding them behind a retransmission, or the receiver's process) and crossed
            # during the gap before them, as did part of the frame after them. One reading.
            readings[-1][0] += size
            readings[-1][1] += gap_s
            burst, last = together, frame
            continue
        burst = False
        if together or gap_s <= 0:
            continue  # a burst with no gap before it here (or empty frames): nothing to read
        readings.append([size, gap_s])
        last = frame
    rates = sorted(size / gap_s for size, gap_s in readings)
    return bytes_per_s_to_mbit(rates[len(rates) // 2]) if rates and len(rates) >= least else None


def receive_rate_mbit(ordered: list[Sample], now_s: float, window_s: float) -> float:
    """Mbit/s received over the window, or over the last few frames when they are sparse."""
    start = now_s - window_s
    inside = [r for r in ordered if r[0] > start]
    if len(inside) < RATE_FRAMES and len(ordered) > len(inside):
        keep = min(RATE_FRAMES, len(ordered) - 1)
        inside = ordered[len(ordered) - keep :] if keep else []
        start = ordered[len(ordered) - keep - 1][0]
    span = now_s - start
    return bytes_per_s_to_mbit(sum(size for *_, size in inside) / span) if span > 0 else 0.0
