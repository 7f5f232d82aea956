"""Estimate a shared link's usable capacity from what the receivers get.

The paper assumes the budget is known; real radio links are not. The estimator watches the
frames that cross the link (receive time, size, sequence number and the sender's send time) and
moves its estimate like a delay-based congestion controller:

- **overuse**, the link carries less than is sent: queueing delay above ``overuse_delay_s`` and
  rising, or above ``max_queue_delay_s``, or frames lost (sequence gaps). The estimate drops to
  what the link delivered (``backoff`` of the receive rate) minus what drains the queue within
  ``drain_s``.
- **hold** while the queue drains or just after a decrease.
- **outage** when nothing at all arrives for ``outage_s`` (or ``outage_gaps`` of the recent
  inter-arrival gaps, for slow streams): the link is down. The estimate is kept, not cut:
  nothing was measured, and a cut would slow the restoration. When frames arrive again, what
  comes first is the backlog the senders queued before they noticed (seconds of queueing) and
  sequence gaps are what the middleware dropped meanwhile: neither is congestion, so for
  ``after_outage_s`` the stream history is restarted, losses are not counted and the
  estimate holds.
- **increase** otherwise, if the link is actually used (receive rate at least ``probe_fraction``
  of the estimate): slowly near the capacity last measured under overuse, fast away from it, and
  never above the configured maximum.

Queueing delay is the one-way delay minus its minimum over ``base_window_s``, per stream, so a
constant clock offset between sender and receiver cancels; the trend is a least-squares slope of
those delays. Pure: every time is an argument, so it runs in a simulation as in a node.

What the estimator tells others is an :class:`EstimatorState`: its phase, what it measured and,
for a decrease, when it was decided, carried as JSON so a reader takes the fields as they are.

Streams and frames come from the network, so what is kept of them is bounded: ``MAX_STREAMS``
streams (one more evicts the one silent the longest) and ``MAX_SAMPLES`` frames over all of
them (past it a frame's delay is not kept, its sequence number still counts); the estimator
counts both, and its node (``dbml.runtime.estimator``) logs them once per flood.
"""

from __future__ import annotations

import enum
import itertools
import json
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dbml.core.errors import SpecError
from dbml.core.spec import bytes_per_s_to_mbit, check_number, short_repr

__all__ = [
    "MAX_SAMPLES",
    "MAX_STREAMS",
    "Arrival",
    "BandwidthEstimator",
    "Estimate",
    "EstimatorSettings",
    "EstimatorState",
    "Phase",
]

_TREND_FRAMES = 3
_RATE_FRAMES = 4
_RHYTHM_FRAMES = 3
"""Frames needed before a silence can be judged against the streams' usual gaps."""
_SPARSE_WINDOWS = 4
"""A slow stream's trend may reach this many windows back for its last few frames."""
MAX_STREAMS = 4096
"""The most streams (a publisher's topic as one receiver gets it) followed at once. A fleet of
160 robots with 4 channels, received by a base station and an operator each, has 1,280: this is
three times that. Stream names come from reception reports, which any peer can send, so one
more evicts the stream silent the longest (its history restarts if it returns, as after a
pause): the active ones stay. A stream costs its frames (``MAX_SAMPLES``) and a few hundred
bytes."""
MAX_SAMPLES = 1 << 21
"""The most frames kept over all streams (each for ``base_window_s``). The fleet above at 30 Hz
holds 1,280 x 30 x 15 = 576,000 over the default 15 s; this is 3.6 times that, and a frame is
about 150 bytes (300 MB at most; a smaller ``base_window_s`` keeps fewer). Any peer can report
frames, so past this a frame's delay is not kept (its sequence number still counts losses)
until older frames leave the window."""


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


@dataclass(frozen=True, slots=True, kw_only=True)
class EstimatorSettings:
    """The estimator's thresholds and rates; the defaults were tuned on the testbed."""

    window_s: float = 0.5
    """The delay trend is measured over this much recent time."""
    rate_window_s: float = 1.0
    """The receive rate is measured over this much recent time."""
    base_window_s: float = 15.0
    """A stream's base delay is its minimum one-way delay over this much time."""
    overuse_delay_s: float = 0.04
    """Queueing delay above this, while rising faster than ``overuse_trend``, is overuse."""
    overuse_trend: float = 0.05
    """Seconds of queueing delay gained per second."""
    max_queue_delay_s: float = 0.15
    """Queueing delay above this is overuse unless it is already falling."""
    backoff: float = 0.95
    drain_s: float = 1.0
    response_s: float = 0.4
    """After a decrease, how long the senders take to act on it (push, apply, first frame)."""
    probe_fraction: float = 0.6
    slow_increase_per_s: float = 0.05
    fast_increase_per_s: float = 0.25
    near_band: tuple[float, float] = (0.8, 1.1)
    """Around the capacity last measured under overuse (as fractions), increase slowly."""
    floor_fraction: float = 0.02
    """The estimate never falls below this fraction of the maximum."""
    outage_s: float = 0.5
    """Nothing received for this long (after frames came) is an outage: the link is down."""
    outage_gaps: float = 3.0
    """...or for this many of the recent mean inter-arrival gaps, whichever is longer."""
    after_outage_s: float = 2.0
    """After an outage, the backlog and the drops it caused are not judged for this long."""

    def __post_init__(self) -> None:
        for name in (
            "window_s",
            "rate_window_s",
            "base_window_s",
            "overuse_delay_s",
            "max_queue_delay_s",
            "drain_s",
            "response_s",
            "slow_increase_per_s",
            "fast_increase_per_s",
            "outage_s",
            "outage_gaps",
            "after_outage_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SpecError(f"estimator {name}={value!r} must be a positive number")
        for name in ("backoff", "probe_fraction", "floor_fraction"):
            value = getattr(self, name)
            if not 0 < value <= 1:
                raise SpecError(f"estimator {name}={value!r} must be in (0, 1]")


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


@dataclass(frozen=True, slots=True, kw_only=True)
class EstimatorState:
    """What the estimator tells others (``/dbm/estimator_state``): its phase and what it measured.

    It travels as JSON (``encode``/``decode``) so that a reader takes fields instead of taking
    text apart; ``text`` is the line a person reads (``dbml monitor``).
    """

    phase: Phase
    received_mbit: float
    queue_delay_s: float
    lost: int
    decided_at_s: float | None = None
    """A decrease's wall-clock time (s) of decision: the testbed times a cut by it to the
    millisecond, where a reader that polls the parameter sees it only as often as it polls."""

    @classmethod
    def of(cls, estimate: Estimate, *, decided_at_s: float | None = None) -> EstimatorState:
        """The state of ``estimate``, decided at ``decided_at_s`` (wall clock) if given."""
        return cls(
            phase=estimate.phase,
            received_mbit=estimate.received_mbit,
            queue_delay_s=estimate.queue_delay_s,
            lost=estimate.lost,
            decided_at_s=decided_at_s,
        )

    @property
    def text(self) -> str:
        """One readable line: ``decrease: received 3.20 Mbit/s, queueing 40 ms, lost 0 @<s>``."""
        line = (
            f"{self.phase.value}: received {self.received_mbit:.2f} Mbit/s, "
            f"queueing {self.queue_delay_s * 1000:.0f} ms, lost {self.lost}"
        )
        return line if self.decided_at_s is None else f"{line} @{self.decided_at_s:.3f}"

    def as_json(self) -> dict[str, Any]:
        """The state as a JSON object (rounded: a state is for reading, not for arithmetic)."""
        return {
            "phase": self.phase.value,
            "received_mbit": round(self.received_mbit, 4),
            "queue_delay_s": round(self.queue_delay_s, 4),
            "lost": self.lost,
            "decided_at_s": None if self.decided_at_s is None else round(self.decided_at_s, 3),
        }

    def encode(self) -> str:
        """The state as the parameter's value: compact JSON."""
        return json.dumps(self.as_json(), separators=(",", ":"))

    @classmethod
    def from_json(cls, document: object) -> EstimatorState:
        """The state ``as_json`` made; ``SpecError`` naming the field and the value if not."""
        if not isinstance(document, Mapping):
            raise SpecError(f"estimator state={short_repr(document)} is not a JSON object")
        phase = document.get("phase")
        known = _PHASES.get(phase) if isinstance(phase, str) else None
        if known is None:
            raise SpecError(
                f"estimator state: phase={short_repr(phase)} is not one of "
                f"{', '.join(p.value for p in Phase)}"
            )
        lost = document.get("lost")
        if isinstance(lost, bool) or not isinstance(lost, int) or lost < 0:
            raise SpecError(f"estimator state: lost={short_repr(lost)} is not a count")
        decided = document.get("decided_at_s")
        return cls(
            phase=known,
            received_mbit=_state_number(document, "received_mbit"),
            queue_delay_s=_state_number(document, "queue_delay_s"),
            lost=lost,
            decided_at_s=None if decided is None else _state_number(document, "decided_at_s"),
        )

    @classmethod
    def decode(cls, text: str) -> EstimatorState:
        """The state ``encode`` wrote; ``SpecError`` naming what is wrong if not."""
        try:
            document = json.loads(text)
        except (ValueError, RecursionError):
            raise SpecError(f"estimator state={short_repr(text)} is not JSON") from None
        return cls.from_json(document)


_PHASES = {phase.value: phase for phase in Phase}


def _state_number(document: Mapping[str, object], field: str) -> float:
    return check_number(document.get(field), field=field, owner="estimator state", minimum=0.0)


class _Stream:
    __slots__ = ("last_seq", "samples")

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self.samples: deque[tuple[float, float, int]] = deque()  # (arrival_s, delay_s, size)


class BandwidthEstimator:
    """Usable capacity of one shared link, in Mbit/s of payload, from receptions.

    Feed every received frame to ``observe`` and call ``update`` periodically (every 50-200 ms);
    the estimate starts at ``initial_mbit`` (the configured maximum by default).
    """

    def __init__(
        self,
        *,
        max_mbit: float,
        initial_mbit: float | None = None,
        settings: EstimatorSettings | None = None,
    ) -> None:
        self.settings = settings or EstimatorSettings()
        self._max_mbit = _check_max(max_mbit)
        start = max_mbit if initial_mbit is None else initial_mbit
        if not (math.isfinite(start) and start > 0):
            raise SpecError(f"estimator initial_mbit={initial_mbit!r} must be a positive number")
        self._estimate = min(start, self._max_mbit)
        self._streams: dict[str, _Stream] = {}
        """By name, the one heard from longest ago first (``MAX_STREAMS`` at most)."""
        self._samples = 0
        """Frames kept over all streams (``MAX_SAMPLES`` at most)."""
        self.streams_evicted = 0
        """Streams evicted (silent the longest) to make room for a new one, over its life."""
        self.samples_refused = 0
        """Frames whose delay was not kept because ``MAX_SAMPLES`` were kept, over its life."""
        self._lost = 0
        self._last_update: float | None = None
        self._frozen_until = -math.inf
        self._capacity_mbit: float | None = None
        self._recent: deque[float] = deque(maxlen=_RATE_FRAMES + 1)
        """Arrival times of the last frames of all streams: the silence and the usual gap."""
        self._outage_since: float | None = None
        self._heard_s: float | None = None
        """The update that first saw the newest frames: silence counts on the update's clock,
        which is immune to how arrival times were mapped from another host's clock."""
        self._fresh = False
        self._judge_from = -math.inf
        self.last: Estimate | None = None

    @property
    def outage(self) -> bool:
        """Whether the link is down as far as the last ``update`` could tell."""
        return self._outage_since is not None

    @property
    def estimate_mbit(self) -> float:
        """The usable bandwidth now."""
        return self._estimate

    @property
    def stream_count(self) -> int:
        """How many streams are followed now (``MAX_STREAMS`` at most)."""
        return len(self._streams)

    @property
    def sample_count(self) -> int:
        """How many frames are kept now over all streams (``MAX_SAMPLES`` at most)."""
        return self._samples

    def observe(self, arrival: Arrival) -> None:
        """Take in one received frame (any order of streams; each stream in order)."""
        stream = self._streams.pop(arrival.stream, None)
        if stream is None:
            stream = _Stream()
            if len(self._streams) >= MAX_STREAMS:
                silent = self._streams.pop(next(iter(self._streams)))
                self._samples -= len(silent.samples)
                self.streams_evicted += 1
        self._streams[arrival.stream] = stream  # now the one heard from last
        last = stream.last_seq
        if last is not None and arrival.seq > last + 1:
            self._lost += arrival.seq - last - 1
        if last is None or arrival.seq > last or arrival.seq == 0:
            stream.last_seq = arrival.seq  # seq 0 again: the publisher restarted
        if self._samples < MAX_SAMPLES:
            stream.samples.append(
                (arrival.arrival_s, arrival.arrival_s - arrival.sent_s, arrival.size_bytes)
            )
            self._samples += 1
        else:
            self.samples_refused += 1
        if not self._recent or arrival.arrival_s >= self._recent[-1]:
            self._recent.append(arrival.arrival_s)
        self._fresh = True

    def _silence_limit_s(self) -> float:
        """How long without any frame is an outage: ``outage_s`` or a few usual gaps."""
        s = self.settings
        times = self._recent
        if len(times) < _RHYTHM_FRAMES:
            return math.inf  # the streams' rhythm is not known yet: no silence is too long
        usual = (times[-1] - times[0]) / (len(times) - 1)
        return max(s.outage_s, s.outage_gaps * usual)

    def _outage_update(self, now_s: float) -> Estimate | None:
        """The outage's part of ``update``: an Estimate while the link is down, else None."""
        fresh, self._fresh = self._fresh, False
        if fresh:
            self._heard_s = now_s
        if self._outage_since is None:
            heard = self._heard_s
            if heard is None or now_s - heard <= self._silence_limit_s():
                return None
            self._outage_since = heard
        elif fresh:
            # Back: restart what the backlog and the drops would distort, and hold a while.
            # The rhythm too: the outage's gap is not a usual gap, and would delay seeing a
            # second outage.
            self._outage_since = None
            self._streams.clear()
            self._samples = 0
            newest = self._recent[-1]
            self._recent.clear()
            self._recent.append(newest)
            self._lost = 0
            self._judge_from = now_s + self.settings.after_outage_s
            return None
        self._lost = 0
        self.last = Estimate(now_s, self._estimate, Phase.OUTAGE, 0.0, 0.0, 0.0, 0)
        return self.last

    def update(self, now_s: float, *, max_mbit: float | None = None) -> Estimate:
        """Move the estimate by what arrived up to ``now_s``; ``max_mbit`` changes the cap."""
        s = self.settings
        if max_mbit is not None:
            self._max_mbit = _check_max(max_mbit)
        dt = 0.0 if self._last_update is None else max(0.0, now_s - self._last_update)
        self._last_update = now_s
        down = self._outage_update(now_s)
        if down is not None:
            return down
        lost, self._lost = self._lost, 0
        settling = now_s < self._judge_from
        if settling:
            lost = 0  # what the middleware dropped while the link was down

        recent: list[tuple[float, float, int]] = []  # (arrival, queue delay, size), all streams
        # per stream: (latest queueing delay, least in the window, trend). Each publisher's
        # backlog sits in its own connection's buffers, so streams are judged one by one.
        judged: list[tuple[float, float, float]] = []
        for name in list(self._streams):
            samples = self._streams[name].samples
            while samples and samples[0][0] < now_s - s.base_window_s:
                samples.popleft()
                self._samples -= 1
            if not samples:
                del self._streams[name]  # a stream that stopped; its seq restarts if it returns
                continue
            base = min(delay for _, delay, _ in samples)
            queued = [(t, d - base, size) for t, d, size in samples]
            recent.extend(queued)
            # the trend needs a few frames, also from a slow stream: the window or the last 3
            mine = [q for q in queued if q[0] > now_s - s.window_s]
            if len(mine) < _TREND_FRAMES:
                horizon = now_s - _SPARSE_WINDOWS * s.window_s
                mine = [q for q in queued[-_TREND_FRAMES:] if q[0] > horizon]
            if mine:
                # a frame that waited behind another's is not a standing queue: the least
                # queueing in the window is
                slope = _slope([(t, q) for t, q, _ in mine])
                judged.append((queued[-1][1], min(q for _, q, _ in mine), slope))
        recent.sort()
        received = _receive_rate_mbit(recent, now_s, s.rate_window_s)
        window = [r for r in recent if r[0] > now_s - s.window_s]
        pairs = recent[-len(window) - 1 :] if len(window) >= _RATE_FRAMES else recent[-5:]

        queue = max((standing for _, standing, _ in judged), default=0.0)
        trend = max((slope for *_, slope in judged), default=0.0)
        overuse = lost > 0 or any(
            (latest > s.overuse_delay_s and slope > s.overuse_trend)
            or (standing > s.max_queue_delay_s and slope >= 0)
            for latest, standing, slope in judged
        )
        draining = bool(judged) and all(slope < -s.overuse_trend for *_, slope in judged)
        # the queue keeps growing until a decrease acts: drain what it will be by then
        backlog = max(
            (latest + max(0.0, slope) * (latest + s.response_s) for latest, _, slope in judged),
            default=0.0,
        )
        floor = s.floor_fraction * self._max_mbit
        if settling:
            phase = Phase.HOLD  # the backlog of the outage drains; nothing to judge yet
        elif overuse and now_s >= self._frozen_until:
            # Frames still queued were sent before this decrease could act: one decrease, then
            # wait until what is sent after it has had time to arrive.
            capacity = _busy_rate_mbit(pairs, s.overuse_delay_s / 2) or received
            if capacity > 0:
                self._capacity_mbit = capacity
                drain = backlog * capacity / s.drain_s
                target = max(s.backoff * capacity - drain, 0.5 * s.backoff * capacity)
                self._estimate = min(self._estimate, target)
                self._frozen_until = now_s + backlog + s.response_s
            phase = Phase.DECREASE
        elif overuse or draining or now_s < self._frozen_until:
            phase = Phase.HOLD  # the queue is still draining, or the decrease not yet seen
        elif received >= s.probe_fraction * self._estimate:
            low, high = s.near_band
            near = self._capacity_mbit is not None and (
                low * self._capacity_mbit <= self._estimate <= high * self._capacity_mbit
            )
            rate = s.slow_increase_per_s if near else s.fast_increase_per_s
            self._estimate *= (1.0 + rate) ** dt
            phase = Phase.INCREASE
        else:
            phase = Phase.HOLD  # the link is not used enough to tell whether more would fit
        self._estimate = min(self._max_mbit, max(floor, self._estimate))
        self.last = Estimate(now_s, self._estimate, phase, received, queue, trend, lost)
        return self.last


def _check_max(max_mbit: float) -> float:
    if not (math.isfinite(max_mbit) and max_mbit > 0):
        raise SpecError(f"estimator max_mbit={max_mbit!r} must be a positive number")
    return max_mbit


_MIN_SLOPE_POINTS = 3
"""A trend needs at least this many points."""
_MIN_SPREAD_S2 = 1e-6
"""Below this variance of times (s^2), points are simultaneous: no slope."""


def _slope(points: list[tuple[float, float]]) -> float:
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


def _busy_rate_mbit(ordered: list[tuple[float, float, int]], queued_s: float) -> float | None:
    """Delivery rate while the link was busy.

    A frame that waited in the queue arrived as soon as the one before it had, so its size over
    that gap is the link's rate (packet pairs).
    """
    size = gap = 0.0
    for (t_prev, _, _), (t, queue, frame) in itertools.pairwise(ordered):
        if queue > queued_s and t > t_prev:
            size += frame
            gap += t - t_prev
    return bytes_per_s_to_mbit(size / gap) if gap > 0 else None


def _receive_rate_mbit(
    ordered: list[tuple[float, float, int]], now_s: float, window_s: float
) -> float:
    """Mbit/s received over the window, or over the last few frames when they are sparse."""
    start = now_s - window_s
    inside = [r for r in ordered if r[0] > start]
    if len(inside) < _RATE_FRAMES and len(ordered) > len(inside):
        keep = min(_RATE_FRAMES, len(ordered) - 1)
        inside = ordered[len(ordered) - keep :] if keep else []
        start = ordered[len(ordered) - keep - 1][0]
    span = now_s - start
    return bytes_per_s_to_mbit(sum(size for *_, size in inside) / span) if span > 0 else 0.0
