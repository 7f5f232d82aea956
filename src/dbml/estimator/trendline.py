"""The ``trendline`` design (after WebRTC GCC): the slope of the delay variation, thresholded.

Per stream the variation is (arrival gap - send gap), immune to clock offsets; the streams'
variations, in arrival order, accumulate into one series whose smoothed slope over the last
``frames`` samples, scaled, is compared to an adaptive threshold. Overuse (above it long enough
and still rising) or frames lost is a cut to ``backoff`` of the receive rate; underuse (below
minus it) holds while the queue drains; otherwise an increase as the ``queue`` design's.

It reads every frame the estimator keeps (its send and arrival times), whether its stream
speaks for the link, the receive rate and the frames lost.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from dbml.core.errors import SpecError
from dbml.estimator.base import (
    Arrival,
    Decision,
    Phase,
    SharedSettings,
    View,
    check_positive,
    check_shares,
    slope,
)
from dbml.estimator.queue import increase

__all__ = ["TrendlineDetector", "TrendlineSettings"]

_MIN_FRAMES = 3
"""A slope needs at least this many samples."""
_TREND_SAMPLES_MAX = 60
"""GCC's cap on the number of samples that scales the slope."""
_OVERUSE_TIME_S = 0.01
"""GCC: the trend must stay above the threshold this long."""
_THRESHOLD_UP_PER_MS = 0.01
_THRESHOLD_DOWN_PER_MS = 0.00018
_THRESHOLD_SPIKE = 15.0
_THRESHOLD_STEP_MAX_MS = 100.0
_THRESHOLD_MIN = 6.0
_THRESHOLD_MAX = 600.0


@dataclass(frozen=True, slots=True, kw_only=True)
class TrendlineSettings:
    """The ``trendline`` design's detector (GCC's values) and increase (the ``queue`` one's)."""

    frames: int = 20
    """The slope is fitted over this many recent delay-variation samples."""
    smoothing: float = 0.9
    """The accumulated delay variation's exponential smoothing."""
    gain: float = 4.0
    """The slope times min(samples, 60) times this is compared to the threshold."""
    threshold: float = 12.5
    """The adaptive threshold's start (GCC: 12.5), kept within [6, 600]."""
    backoff: float = 0.85
    """A cut to this share of the receive rate (GCC: 0.85)."""
    slow_increase_per_s: float = 0.05
    fast_increase_per_s: float = 0.25
    near_band: tuple[float, float] = (0.8, 1.1)
    """Around the capacity last measured under overuse (as fractions), increase slowly."""

    def __post_init__(self) -> None:
        check_positive(
            "estimator", self, ("gain", "threshold", "slow_increase_per_s", "fast_increase_per_s")
        )
        frames = self.frames
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
            raise SpecError(f"estimator frames={frames!r} must be a positive integer")
        if frames < _MIN_FRAMES:
            raise SpecError(f"estimator frames={frames!r} must be >= {_MIN_FRAMES}")
        check_shares("estimator", self, ("smoothing", "backoff"))

    def detector(self, shared: SharedSettings) -> TrendlineDetector:
        """A fresh ``trendline`` detector."""
        return TrendlineDetector(self, shared)


class TrendlineDetector:
    """GCC's delay-gradient detector and AIMD."""

    def __init__(self, settings: TrendlineSettings, shared: SharedSettings) -> None:
        self.settings = settings
        self._shared = shared
        self._frozen_until = -math.inf
        self._capacity_mbit: float | None = None
        self._pending: list[tuple[float, float, str]] = []
        """Frames kept since the last decision, (arrival, send, stream): the variations."""
        self._prev: dict[str, tuple[float, float]] = {}
        """Per stream, its previous frame's (send, arrival) time (at most the streams
        followed: the loop forgets each stream it drops)."""
        self._accumulated_s = 0.0
        self._smoothed_s = 0.0
        self._points: deque[tuple[float, float]] = deque()
        self._count = 0
        self._threshold = 0.0
        self._overusing_s = 0.0
        self._previous_trend = 0.0
        self._seen_s: float | None = None
        self._signal = Phase.INCREASE
        """Overuse (DECREASE), underuse (HOLD) or normal (INCREASE)."""

    def observe(self, arrival: Arrival) -> None:
        """Keep the frame for the next decision's variations."""
        self._pending.append((arrival.arrival_s, arrival.sent_s, arrival.stream))

    def forget(self, stream: str | None) -> None:
        """A stream's next variation starts from its next frame (None: every stream's)."""
        if stream is None:
            self._prev.clear()
            self._pending.clear()
        else:
            self._prev.pop(stream, None)

    def decide(self, view: View) -> Decision:
        """GCC's AIMD: a cut to ``backoff`` of the receive rate on overuse.

        Hold while the queue drains (underuse), increase otherwise.
        """
        signal = self._series(view)
        s = self.settings
        estimate = view.estimate_mbit
        if view.settling:
            return Decision(Phase.HOLD, estimate)
        overuse = signal is Phase.DECREASE
        if signal is Phase.HOLD:
            return Decision(Phase.HOLD, estimate)
        if (overuse or view.lost > 0) and view.now_s >= self._frozen_until:
            rate = view.cut_rate
            if rate > 0:
                self._capacity_mbit = rate
                estimate = min(estimate, s.backoff * rate)
                self._frozen_until = view.now_s + self._shared.response_s
            return Decision(Phase.DECREASE, estimate)
        if overuse or view.now_s < self._frozen_until:
            return Decision(Phase.HOLD, estimate)
        return increase(
            view,
            self._capacity_mbit,
            probe_fraction=self._shared.probe_fraction,
            slow_per_s=s.slow_increase_per_s,
            fast_per_s=s.fast_increase_per_s,
            near_band=s.near_band,
        )

    def _series(self, view: View) -> Phase:
        """Feed the new frames' delay variations to the trendline; what it says now."""
        s = self.settings
        frames, self._pending = sorted(self._pending), []
        for arrival, sent, name in frames:
            speaks = view.speaks(name)
            if speaks is None:
                continue
            prev = self._prev.get(name)
            self._prev[name] = (sent, arrival)
            if prev is None or not speaks or view.settling:
                continue
            variation = (arrival - prev[1]) - (sent - prev[0])
            self._accumulated_s += variation
            self._smoothed_s = (
                s.smoothing * self._smoothed_s + (1 - s.smoothing) * self._accumulated_s
            )
            points = self._points
            points.append((arrival, self._smoothed_s))
            if len(points) > s.frames:
                points.popleft()
            self._count += 1
            if len(points) < s.frames:
                continue
            trend = min(self._count, _TREND_SAMPLES_MAX) * slope(list(points))
            self._detect(arrival, trend * s.gain)
        return self._signal

    def _detect(self, at_s: float, modified: float) -> None:
        """GCC's overuse detector: above the threshold long enough and still rising."""
        if self._threshold == 0.0:
            self._threshold = self.settings.threshold
        gap_s = 0.0 if self._seen_s is None else max(0.0, at_s - self._seen_s)
        self._seen_s = at_s
        if modified > self._threshold:
            self._overusing_s += gap_s
            if self._overusing_s > _OVERUSE_TIME_S and modified >= self._previous_trend:
                self._signal = Phase.DECREASE
        else:
            self._overusing_s = 0.0
            # under: the queue drains, hold (GCC); normal: increase
            self._signal = Phase.HOLD if modified < -self._threshold else Phase.INCREASE
        self._previous_trend = modified
        # adapt: up fast towards a large trend, down slowly; ignore a spike far above it
        excess = abs(modified) - self._threshold
        if excess <= _THRESHOLD_SPIKE:
            k = _THRESHOLD_UP_PER_MS if excess > 0 else _THRESHOLD_DOWN_PER_MS
            step_ms = min(gap_s * 1000.0, _THRESHOLD_STEP_MAX_MS)
            self._threshold += step_ms * k * excess
            self._threshold = min(_THRESHOLD_MAX, max(_THRESHOLD_MIN, self._threshold))
