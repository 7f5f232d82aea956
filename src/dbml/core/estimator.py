"""Estimate a shared link's usable capacity from what the receivers get.

The paper assumes the budget is known; real radio links are not. The estimator watches the
frames that cross the link (receive time, size, sequence number and the sender's send time) and
moves its estimate like a congestion controller. How it reads overuse and what it does then is
its :class:`Design` (three, compared on the testbed's recorded traces in docs/estimator.md):

- ``delivery-rate`` (after BBR): the budget cruises at the link's rate (the
  packet-pair rate measured at the last cut, raised by probes the link carried); every
  ``cruise_s`` a round asks ``probe_gain`` more, each one carried triples the next step, one
  that queues is drained for a round. A queue beyond one frame of another stream, growing or
  standing, means the link is full: the budget drops below the link's rate until what is
  queued has drained (down to ``drain_gain``), then cruises at that rate. The queue is
  measured over each stream's least delay since the last cut: a slower link makes every
  frame's own transmission longer, which is not a queue.
- ``trendline`` (after WebRTC GCC): the slope of the accumulated delay variation against an
  adaptive threshold; a cut to ``trend_backoff`` of the receive rate.
- ``queue`` (the first design, the default: the others' probing costs frames after a drop on a
  drop-tail link): queueing delay above ``overuse_delay_s`` and rising, or above
  ``max_queue_delay_s``, or frames lost (sequence gaps) is overuse; a cut to ``backoff`` of the
  packet-pair rate minus what drains the queue within ``drain_s``, then a hold while the queue
  drains; an increase otherwise, slowly near the capacity last measured, fast away from it.

Whatever the design:

- **outage** when nothing at all arrives for ``outage_s`` (or ``outage_gaps`` of the recent
  inter-arrival gaps, for slow streams): the link is down. The estimate is kept, not cut:
  nothing was measured, and a cut would slow the restoration. When frames arrive again, what
  comes first is the backlog the senders queued before they noticed (seconds of queueing) and
  sequence gaps are what the middleware dropped meanwhile: neither is congestion, so for
  ``after_outage_s`` the stream history is restarted, losses are not counted and the
  estimate holds.
- **one stream silent** while others flow (its own rhythm, as an outage) is that robot's
  outage, not the link's: back, its history restarts and for ``after_outage_s`` its backlog,
  its sequence gaps and its old send times are not judged; meanwhile its rate before the
  silence stands in for it in the receive rate a cut is based on, so the others' budget is
  not cut for its silence.
- never above the configured maximum, never below ``floor_fraction`` of it.

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
    "Design",
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


class Design(enum.StrEnum):
    """How overuse is read and what a cut and an increase are (docs/estimator.md compares them).

    ``queue``: a standing queue or a rising one, a cut to the packet-pair rate (the first
    design). ``trendline``: WebRTC GCC's slope of the accumulated delay variation against an
    adaptive threshold, AIMD with a cut to ``trend_backoff`` of the receive rate.
    ``delivery-rate``: BBR's max-filtered delivery rate, probed up by ``probe_gain`` on a
    cycle, with a standing queue as the bound that resets the filter.
    """

    QUEUE = "queue"
    TRENDLINE = "trendline"
    DELIVERY_RATE = "delivery-rate"


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
    """After an outage, the backlog and the drops it caused are not judged for this long;
    the same for one stream back from its own silence while others flowed."""
    design: Design = Design.QUEUE
    trend_frames: int = 20
    """``trendline``: the slope is fitted over this many recent delay-variation samples."""
    trend_smoothing: float = 0.9
    """``trendline``: the accumulated delay variation's exponential smoothing."""
    trend_gain: float = 4.0
    """``trendline``: the slope times min(samples, 60) times this is compared to the threshold."""
    trend_threshold: float = 12.5
    """``trendline``: the adaptive threshold's start (GCC: 12.5), kept within [6, 600]."""
    trend_backoff: float = 0.85
    """``trendline``: a cut to this share of the receive rate (GCC: 0.85)."""
    probe_gain: float = 1.1
    """``delivery-rate``: the budget in a probe round, as a share of the filtered rate."""
    startup_gain: float = 2.0
    """``delivery-rate``: each probe the link carried triples the next one's step, to this."""
    drain_gain: float = 0.5
    """``delivery-rate``: the deepest cut, as a share of the link's rate, to drain a queue."""
    cruise_gain: float = 1.0
    """``delivery-rate``: between probes, the budget as a share of the filtered rate."""
    bw_window_s: float = 2.5
    """``delivery-rate``: the delivery rate is the maximum over this much time."""
    round_s: float = 1.0
    """``delivery-rate``: one round: a budget change acted on (``response_s``) and measured."""
    cruise_s: float = 2.0
    """``delivery-rate``: time at the filtered rate between probes."""
    queue_target_s: float = 0.05
    """``delivery-rate``: queueing beyond one other stream's frame above this means the link
    is full: the filter restarts from what was delivered, the budget drains the queue."""

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
            "trend_gain",
            "trend_threshold",
            "probe_gain",
            "startup_gain",
            "cruise_gain",
            "bw_window_s",
            "round_s",
            "cruise_s",
            "queue_target_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SpecError(f"estimator {name}={value!r} must be a positive number")
        for name in ("trend_frames",):
            count = getattr(self, name)
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise SpecError(f"estimator {name}={count!r} must be a positive integer")
        if self.trend_frames < _MIN_SLOPE_POINTS:
            raise SpecError(f"estimator trend_frames={self.trend_frames!r} must be >= 3")
        if not isinstance(self.design, Design):
            raise SpecError(f"estimator design={self.design!r} is not one of {', '.join(Design)}")
        for name in (
            "backoff",
            "probe_fraction",
            "floor_fraction",
            "trend_smoothing",
            "trend_backoff",
            "drain_gain",
        ):
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
    """A decrease's wall-clock time (s) of decision, also in the holds after it while the
    estimate is the cut's: the testbed times a cut by it to the millisecond, where a reader that
    polls the parameter sees it only as often as it polls (and may see only the hold)."""

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
    __slots__ = (
        "away",
        "back",
        "heard_s",
        "last_seq",
        "least_s",
        "lost",
        "prev",
        "rate_before_mbit",
        "rhythm",
        "samples",
        "settle_until_s",
    )

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self.samples: deque[tuple[float, float, int]] = deque()  # (arrival_s, delay_s, size)
        self.lost = 0
        """Frames lost (sequence gaps) since the last update."""
        self.least_s = math.inf
        """Its least one-way delay since its history (re)started: what ``observe`` returns
        a frame's queueing over, without a pass over its frames."""
        self.rhythm: deque[float] = deque(maxlen=_RATE_FRAMES + 1)
        """Its last frames' arrival times: its usual gap."""
        self.heard_s: float | None = None
        """The update that first saw its newest frame (its silence counts on that clock)."""
        self.away = False
        """Silent past its own rhythm while the link was up: the robot's outage, not the link's."""
        self.back = False
        """A frame came while away; the next update starts its settling."""
        self.settle_until_s = -math.inf
        """Until then its backlog and its gaps are not judged."""
        self.rate_before_mbit = 0.0
        """What it received before it went silent: its share while it is away or settling."""
        self.prev: tuple[float, float] | None = None
        """``trendline``: its previous frame's (send, arrival) time."""

    def silence_limit_s(self, settings: EstimatorSettings) -> float:
        """How long without a frame of its own is its outage (as ``outage_s``, per stream)."""
        times = self.rhythm
        if len(times) < _RHYTHM_FRAMES:
            return math.inf
        usual = (times[-1] - times[0]) / (len(times) - 1)
        return max(settings.outage_s, settings.outage_gaps * usual)

    def judged(self, now_s: float) -> bool:
        """Whether its delays and its losses speak for the link now."""
        return not self.away and now_s >= self.settle_until_s


class BandwidthEstimator:
    """Usable capacity of one shared link, in Mbit/s of payload, from receptions.

    Feed every received frame to ``observe`` and call ``update`` periodically (every 50-200 ms);
    the estimate starts at ``initial_mbit`` (the configured maximum by default).
    ``settings.design`` picks how overuse is read (:class:`Design`); the outages, the bounds
    and the streams' own silences are the same for every design.
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
        self._last_update: float | None = None
        self._frozen_until = -math.inf
        self._capacity_mbit: float | None = None
        self._recent: deque[float] = deque(maxlen=_RATE_FRAMES + 1)
        """Arrival times of the last frames of all streams: the silence and the usual gap."""
        self._outage_since: float | None = None
        self._heard_s: float | None = None
        """The update that first saw the newest frames: silence counts on the update's clock,
        which is immune to how arrival times were mapped from another host's clock."""
        self._fresh: set[str] = set()
        """Streams with frames since the last update."""
        self._judge_from = -math.inf
        self.last: Estimate | None = None
        # trendline
        self._new: list[tuple[float, float, str]] = []
        """Frames since the last update, (arrival, send, stream): the delay variations."""
        self._accumulated_s = 0.0
        self._smoothed_s = 0.0
        self._trend_points: deque[tuple[float, float]] = deque()
        self._trend_count = 0
        self._threshold = 0.0
        self._overusing_s = 0.0
        self._previous_trend = 0.0
        self._trend_seen_s: float | None = None
        self._trend_signal = Phase.INCREASE
        """``trendline``: overuse (DECREASE), underuse (HOLD) or normal (INCREASE)."""
        # delivery rate
        self._bw: deque[tuple[float, float]] = deque()
        """(time, delivery rate in Mbit/s): the maximum over ``bw_window_s`` is the rate."""
        self._gain = 1.0
        self._round_until = -math.inf
        self._cruise_until = -math.inf
        self._probe_base_mbit = 0.0
        self._base_from = -math.inf
        """The last cut: queueing is over each stream's least delay since (the link's rate,
        and so each frame's own transmission time, may have changed)."""

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

    def observe(self, arrival: Arrival) -> float:
        """Take in one received frame (any order of streams; each stream in order).

        Returns its queueing: its one-way delay over the least its stream had (0 for a
        stream's first frame), so a node can judge at once a frame that queued instead of
        waiting for its next update.
        """
        stream = self._streams.pop(arrival.stream, None)
        if stream is None:
            stream = _Stream()
            if len(self._streams) >= MAX_STREAMS:
                silent_name = next(iter(self._streams))
                silent = self._streams.pop(silent_name)
                self._fresh.discard(silent_name)
                self._samples -= len(silent.samples)
                self.streams_evicted += 1
        self._streams[arrival.stream] = stream  # now the one heard from last
        if stream.away:
            # Back from its own silence: what it queued meanwhile and what was dropped of it
            # say nothing about the link, which the others kept using. Restart its history.
            self._samples -= len(stream.samples)
            stream.samples.clear()
            stream.rhythm.clear()
            stream.last_seq = stream.prev = None
            stream.least_s = math.inf
            stream.away, stream.back = False, True
        last = stream.last_seq
        if last is not None and arrival.seq > last + 1:
            stream.lost += arrival.seq - last - 1
        if last is None or arrival.seq > last or arrival.seq == 0:
            stream.last_seq = arrival.seq  # seq 0 again: the publisher restarted
        if self._samples < MAX_SAMPLES:
            stream.samples.append(
                (arrival.arrival_s, arrival.arrival_s - arrival.sent_s, arrival.size_bytes)
            )
            self._samples += 1
            if self.settings.design is Design.TRENDLINE:
                self._new.append((arrival.arrival_s, arrival.sent_s, arrival.stream))
        else:
            self.samples_refused += 1
        if not self._recent or arrival.arrival_s >= self._recent[-1]:
            self._recent.append(arrival.arrival_s)
        if not stream.rhythm or arrival.arrival_s >= stream.rhythm[-1]:
            stream.rhythm.append(arrival.arrival_s)
        self._fresh.add(arrival.stream)
        delay = arrival.arrival_s - arrival.sent_s
        queued = max(0.0, delay - stream.least_s) if math.isfinite(stream.least_s) else 0.0
        stream.least_s = min(stream.least_s, delay)
        return queued

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
        fresh = bool(self._fresh)
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
            self._fresh.clear()
            self._new.clear()
            self._samples = 0
            newest = self._recent[-1]
            self._recent.clear()
            self._recent.append(newest)
            self._judge_from = now_s + self.settings.after_outage_s
            return None
        self._fresh.clear()
        self._new.clear()
        for stream in self._streams.values():
            stream.lost = 0
        self.last = Estimate(now_s, self._estimate, Phase.OUTAGE, 0.0, 0.0, 0.0, 0)
        return self.last

    def _stream_silences(self, now_s: float) -> None:
        """One stream silent while others flow is its robot's outage, not the link's.

        It goes ``away`` past its own rhythm; back, it settles for ``after_outage_s``: its
        delays and losses are not judged, and what it received before stands in for its
        share of the receive rate, so the others' budget is not cut for its silence.
        """
        s = self.settings
        for name, stream in self._streams.items():
            if name in self._fresh:
                stream.heard_s = now_s
                if stream.back:
                    stream.back = False
                    stream.settle_until_s = now_s + s.after_outage_s
            elif (
                not stream.away
                and stream.heard_s is not None
                and now_s - stream.heard_s > stream.silence_limit_s(s)
            ):
                stream.away = True
                samples = list(stream.samples)
                stream.rate_before_mbit = (
                    _receive_rate_mbit(samples, samples[-1][0], s.rate_window_s) if samples else 0.0
                )
        self._fresh.clear()

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
        self._stream_silences(now_s)
        settling = now_s < self._judge_from
        lost = 0
        recent: list[tuple[float, float, int]] = []  # (arrival, queue delay, size), all streams
        # per stream: (latest queueing delay, least in the window, trend). Each publisher's
        # backlog sits in its own connection's buffers, so streams are judged one by one.
        judged: list[tuple[float, float, float]] = []
        # the same since the last cut, with the stream's frame size: ``delivery-rate``
        short: list[_Queue] = []
        # a silent stream's share: its rate before, instead of its silence or its backlog
        stand_in = 0.0
        for name in list(self._streams):
            stream = self._streams[name]
            samples = stream.samples
            while samples and samples[0][0] < now_s - s.base_window_s:
                samples.popleft()
                self._samples -= 1
            if stream.away and (stream.heard_s or now_s) < now_s - s.base_window_s:
                del self._streams[name]  # gone for good: no more a share of the link
                self._samples -= len(samples)
                continue
            speaks = stream.judged(now_s)
            if speaks:
                lost += stream.lost
            stream.lost = 0
            if not speaks:
                mine_rate = _receive_rate_mbit(list(samples), now_s, s.rate_window_s)
                stand_in += stream.rate_before_mbit - mine_rate
            if not samples:
                if not stream.away:
                    del self._streams[name]  # stopped; its seq restarts if it returns
                continue
            base = min(delay for _, delay, _ in samples)
            queued = [(t, d - base, size) for t, d, size in samples]
            recent.extend(queued)
            if not speaks:
                continue
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
                if s.design is Design.DELIVERY_RATE:
                    short.append(_short_queue(samples, mine, self._base_from, slope))
        if settling:
            lost = 0  # what the middleware dropped while the link was down
        recent.sort()
        received = _receive_rate_mbit(recent, now_s, s.rate_window_s)
        cut_rate = max(0.0, received + stand_in)
        trend_signal = self._trendline(now_s)
        view = _View(now_s, dt, settling, lost, recent, judged, received, cut_rate, short)
        if s.design is Design.TRENDLINE:
            phase = self._decide_trendline(view, trend_signal)
        elif s.design is Design.DELIVERY_RATE:
            phase = self._decide_delivery_rate(view)
        else:
            phase = self._decide_queue(view)
        floor = s.floor_fraction * self._max_mbit
        self._estimate = min(self._max_mbit, max(floor, self._estimate))
        queue = max((standing for _, standing, _ in judged), default=0.0)
        trend = max((slope for *_, slope in judged), default=0.0)
        self.last = Estimate(now_s, self._estimate, phase, received, queue, trend, lost)
        return self.last

    # -- the first design: a standing or rising queue, a cut to the packet-pair rate -----------

    def _decide_queue(self, v: _View) -> Phase:
        s = self.settings
        judged = v.judged
        overuse = v.lost > 0 or any(
            (latest > s.overuse_delay_s and slope > s.overuse_trend)
            or (standing > s.max_queue_delay_s and slope >= 0)
            for latest, standing, slope in judged
        )
        draining = bool(judged) and all(slope < -s.overuse_trend for *_, slope in judged)
        if v.settling:
            return Phase.HOLD  # the backlog of the outage drains; nothing to judge yet
        if overuse and v.now_s >= self._frozen_until:
            # Frames still queued were sent before this decrease could act: one decrease, then
            # wait until what is sent after it has had time to arrive.
            backlog = _backlog_s(judged, s.response_s)
            capacity = _busy_rate_mbit(v.pairs(s.window_s), s.overuse_delay_s / 2) or v.cut_rate
            if capacity > 0:
                self._capacity_mbit = capacity
                drain = backlog * capacity / s.drain_s
                target = max(s.backoff * capacity - drain, 0.5 * s.backoff * capacity)
                self._estimate = min(self._estimate, target)
                self._frozen_until = v.now_s + backlog + s.response_s
            return Phase.DECREASE
        if overuse or draining or v.now_s < self._frozen_until:
            return Phase.HOLD  # the queue is still draining, or the decrease not yet seen
        return self._increase(v)

    def _increase(self, v: _View) -> Phase:
        """Up, if the link is used: slowly near the capacity last measured, fast away from it."""
        s = self.settings
        if v.received < s.probe_fraction * self._estimate:
            return Phase.HOLD  # the link is not used enough to tell whether more would fit
        low, high = s.near_band
        near = self._capacity_mbit is not None and (
            low * self._capacity_mbit <= self._estimate <= high * self._capacity_mbit
        )
        rate = s.slow_increase_per_s if near else s.fast_increase_per_s
        self._estimate *= (1.0 + rate) ** v.dt_s
        return Phase.INCREASE

    # -- trendline: GCC's delay-gradient detector ---------------------------------------------

    def _trendline(self, now_s: float) -> Phase:
        """Feed the new frames' delay variations to the trendline; whether it says overuse.

        Per stream the variation is (arrival gap - send gap), immune to clock offsets; the
        streams' variations, in arrival order, accumulate into one series whose smoothed slope
        over the last ``trend_frames`` samples, scaled, is compared to an adaptive threshold.
        """
        s = self.settings
        if s.design is not Design.TRENDLINE:
            return Phase.INCREASE
        frames, self._new = sorted(self._new), []
        for arrival, sent, name in frames:
            stream = self._streams.get(name)
            if stream is None:
                continue
            prev, stream.prev = stream.prev, (sent, arrival)
            if prev is None or not stream.judged(now_s) or now_s < self._judge_from:
                continue
            variation = (arrival - prev[1]) - (sent - prev[0])
            self._accumulated_s += variation
            self._smoothed_s = (
                s.trend_smoothing * self._smoothed_s + (1 - s.trend_smoothing) * self._accumulated_s
            )
            points = self._trend_points
            points.append((arrival, self._smoothed_s))
            if len(points) > s.trend_frames:
                points.popleft()
            self._trend_count += 1
            if len(points) < s.trend_frames:
                continue
            trend = min(self._trend_count, _TREND_SAMPLES_MAX) * _slope(list(points))
            modified = trend * s.trend_gain
            self._detect(arrival, modified)
        return self._trend_signal

    def _detect(self, at_s: float, modified: float) -> None:
        """GCC's overuse detector: above the threshold long enough and still rising."""
        s = self.settings
        if self._threshold == 0.0:
            self._threshold = s.trend_threshold
        gap_s = 0.0 if self._trend_seen_s is None else max(0.0, at_s - self._trend_seen_s)
        self._trend_seen_s = at_s
        if modified > self._threshold:
            self._overusing_s += gap_s
            if self._overusing_s > _OVERUSE_TIME_S and modified >= self._previous_trend:
                self._trend_signal = Phase.DECREASE
        else:
            self._overusing_s = 0.0
            # under: the queue drains, hold (GCC); normal: increase
            self._trend_signal = Phase.HOLD if modified < -self._threshold else Phase.INCREASE
        self._previous_trend = modified
        # adapt: up fast towards a large trend, down slowly; ignore a spike far above it
        excess = abs(modified) - self._threshold
        if excess <= _THRESHOLD_SPIKE:
            k = _THRESHOLD_UP_PER_MS if excess > 0 else _THRESHOLD_DOWN_PER_MS
            step_ms = min(gap_s * 1000.0, _THRESHOLD_STEP_MAX_MS)
            self._threshold += step_ms * k * excess
            self._threshold = min(_THRESHOLD_MAX, max(_THRESHOLD_MIN, self._threshold))

    def _decide_trendline(self, v: _View, signal: Phase) -> Phase:
        """GCC's AIMD: a cut to ``trend_backoff`` of the receive rate on overuse.

        Hold while the queue drains (underuse), increase otherwise.
        """
        s = self.settings
        if v.settling:
            return Phase.HOLD
        overuse = signal is Phase.DECREASE
        if signal is Phase.HOLD:
            return Phase.HOLD
        if (overuse or v.lost > 0) and v.now_s >= self._frozen_until:
            rate = v.cut_rate
            if rate > 0:
                self._capacity_mbit = rate
                self._estimate = min(self._estimate, s.trend_backoff * rate)
                self._frozen_until = v.now_s + s.response_s
            return Phase.DECREASE
        if overuse or v.now_s < self._frozen_until:
            return Phase.HOLD
        return self._increase(v)

    # -- delivery rate: BBR's max filter and probe cycle --------------------------------------

    def _decide_delivery_rate(self, v: _View) -> Phase:
        """Budget = gain x the most delivered lately; a queue beyond one frame resets it.

        The delivery rate (what arrived over ``round_s`` less the reaction) is max-filtered
        over ``bw_window_s`` while the budget cruises or probes (a drain's arrivals are the
        backlog, in bursts). Between probes the budget cruises at ``cruise_gain`` of the
        link's rate; every ``cruise_s`` a round asks ``probe_gain`` more, and if the link
        carried it (delivered more, queued nothing) the next round's step is three times
        larger, up to ``startup_gain`` (BBR's probing up); a probe whose large frames start to
        queue ends at once and a round at ``2 - probe_gain`` drains what it queued. A queue
        beyond what one frame of another stream explains, standing or growing, means the link
        is full: its rate is the packet-pair rate (at least half the last second's), and the
        budget drains what is queued (down to ``drain_gain`` of it), then cruises.
        """
        s = self.settings
        now = v.now_s
        if v.settling:
            return Phase.HOLD
        bw = self._bw
        while bw and bw[0][0] < now - s.bw_window_s:
            bw.popleft()
        used = v.received >= s.probe_fraction * self._estimate
        reference = max(v.received, self._capacity_mbit or 0.0)
        # a stream of small frames waits behind the large ones: only two in a row count
        largest = max((q.size_bytes for q in v.short), default=0)
        excess = [
            (
                (q.latest_s if 2 * q.size_bytes >= largest else q.pair_s) - wait,
                q.least_s - wait,
                q.trend,
            )
            for k, q in enumerate(v.short)
            for wait in (_other_frame_s(k, v.short, reference),)
        ]
        full = v.lost > 0 or any(
            least > s.queue_target_s or (latest > s.queue_target_s and slope > s.overuse_trend)
            for latest, least, slope in excess
        )
        if full and now >= self._frozen_until:
            busy = _busy_rate_mbit(v.pairs(s.window_s), s.queue_target_s / 2)
            # a burst of frames read together is not the link's rate: what arrived over the
            # last second bounds it from below. Only what arrived by ``now``: a node judges a
            # little in the past, and the frames reported since would count over a second that
            # ends before them (judged at once on a fresh report, the floor read 10.25 Mbit/s
            # of an 11-Mbit/s link just cut to 5, and the budget cruised over the new link)
            floor = _receive_rate_mbit([r for r in v.recent if r[0] <= now], now, s.rate_window_s)
            rate = max(busy or 0.0, _CUT_RATE_FLOOR * floor) or v.cut_rate
            if rate > 0:
                # the queue grows by the overload until the cut acts: what the senders were
                # told over what the link delivers (the trend, from a few frames, lags it)
                overload = max([self._estimate / rate - 1.0, *(sl for *_, sl in excess)])
                latest = max((q for q, *_ in excess), default=0.0)
                backlog = max(0.0, latest + max(0.0, overload) * s.response_s)
                share = max(s.drain_gain, 1.0 - backlog / s.drain_s)
                self._estimate = min(self._estimate, share * rate)
                drain_s = backlog / (1.0 - share) if share < 1 else 0.0
                self._frozen_until = now + s.response_s + drain_s
                self._capacity_mbit = min(rate, self._capacity_mbit or rate)
                if busy is not None and busy > (self._capacity_mbit or 0.0):
                    self._capacity_mbit = busy
                bw.clear()
                self._gain = 0.0  # draining: cruise once it is done
                self._round_until = self._frozen_until
                self._base_from = now
            return Phase.DECREASE
        delivered = _receive_rate_mbit(v.recent, now, max(s.window_s, s.round_s - s.response_s))
        if self._gain >= 1 and delivered > 0 and used and not full:
            bw.append((now, delivered))
        # a probe's queue shows first in the streams of large frames (a small frame's delay
        # is mostly the wait behind a large one): growing at all there ends the probe
        quiet = not any(
            q.latest_s > s.queue_target_s / 2 and q.trend > s.overuse_trend
            for q in v.short
            if 2 * q.size_bytes >= largest
        )
        if self._gain > 1 and not quiet:
            # the probe queues: the link has no more room; drain what it queued for a round
            self._gain = max(s.drain_gain, 2.0 - s.probe_gain)
            self._estimate = self._gain * self._probe_base_mbit
            self._round_until = self._frozen_until = now + s.round_s
            return Phase.HOLD
        if now < self._round_until:
            return Phase.INCREASE if self._gain > 1 else Phase.HOLD
        best = max((rate for _, rate in bw), default=0.0)
        capacity = self._capacity_mbit or best
        if self._gain > 1:
            # a probe round ended without a queue: did the link carry it (more arrived)? Then
            # ask more (start-up); else cruise at what the link is known to carry
            if best >= (1.0 + (self._gain - 1.0) / 2) * self._probe_base_mbit:
                self._capacity_mbit = capacity = max(capacity, min(best, self._estimate))
                if self._estimate < self._max_mbit:
                    # each probe carried triples the next one's step (BBR's probing up)
                    self._probe_base_mbit = self._estimate
                    self._gain = min(s.startup_gain, 1.0 + _PROBE_GROWTH * (self._gain - 1.0))
                    self._estimate *= self._gain
                    self._round_until = now + s.round_s
                    return Phase.INCREASE
            self._gain = 0.0
        if self._gain == 1.0:
            if now >= self._cruise_until and used and self._estimate < self._max_mbit:
                self._probe_base_mbit = self._estimate
                self._gain = s.probe_gain
                self._estimate = self._gain * self._probe_base_mbit
                self._round_until = now + s.round_s
                return Phase.INCREASE
            return Phase.INCREASE if used else Phase.HOLD  # cruising: the rate follows the link
        # after a drain: cruise at the link's rate
        self._gain = 1.0
        self._cruise_until = now + s.cruise_s
        if capacity > 0:
            self._estimate = s.cruise_gain * capacity
        return Phase.HOLD


@dataclass(frozen=True, slots=True)
class _View:
    """What one update measured, for the design that decides on it."""

    now_s: float
    dt_s: float
    settling: bool
    lost: int
    recent: list[tuple[float, float, int]]
    """(arrival, queueing delay, size) of all streams' kept frames, in arrival order."""
    judged: list[tuple[float, float, float]]
    """Per judged stream: (latest queueing delay, least in the window, trend)."""
    received: float
    cut_rate: float
    """The receive rate, with a silent stream's share as before its silence."""
    short: list[_Queue]
    """``delivery-rate``: per judged stream, its queueing since the last cut."""

    def pairs(self, window_s: float) -> list[tuple[float, float, int]]:
        """The frames of the last window (and the one before them): the packet pairs."""
        window = [r for r in self.recent if r[0] > self.now_s - window_s]
        return self.recent[-len(window) - 1 :] if len(window) >= _RATE_FRAMES else self.recent[-5:]


_PROBE_GROWTH = 3.0
"""``delivery-rate``: a probe the link carried makes the next one's step this much larger."""
_CUT_RATE_FLOOR = 0.5
"""``delivery-rate``: a cut's link rate is at least this share of the last second's rate."""
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


@dataclass(frozen=True, slots=True)
class _Queue:
    """``delivery-rate``: one stream's queueing over its least delay since the last cut."""

    latest_s: float
    pair_s: float
    """The lesser of its last two frames': one frame's wait behind a burst is not a queue."""
    least_s: float
    """The least in the window: a standing queue."""
    trend: float
    size_bytes: int
    """Its largest frame in the window."""


def _short_queue(
    samples: deque[tuple[float, float, int]],
    mine: list[tuple[float, float, int]],
    since_s: float,
    slope: float,
) -> _Queue:
    """A stream's queueing over its least delay since ``since_s`` (the last cut).

    A frame's delay holds its own transmission, which grows when the link slows: a base from
    before the cut would read that as a standing queue for as long as it remembers the faster
    link. After the cut the queue drains, so the least delay since is the new link's.
    """
    recent = [d for t, d, _ in samples if t > since_s] or [samples[-1][1]]
    base = min(recent)
    latest = max(0.0, samples[-1][1] - base)
    pair = max(0.0, min(d for _, d, _ in list(samples)[-2:]) - base)
    offset = min(d for _, d, _ in samples) - base  # the queued values are over the long base
    least = max(0.0, min(q for _, q, _ in mine) + offset)
    return _Queue(latest, pair, least, slope, max(size for *_, size in mine))


def _other_frame_s(index: int, streams: list[_Queue], rate_mbit: float) -> float:
    """How long a frame may wait behind one frame of another stream: not a standing queue."""
    largest = max((q.size_bytes for k, q in enumerate(streams) if k != index), default=0)
    return largest * 8e-6 / rate_mbit if rate_mbit > 0 else 0.0


def _backlog_s(judged: list[tuple[float, float, float]], response_s: float) -> float:
    """The queue by the time a decrease acts: it keeps growing until then."""
    return max(
        (latest + max(0.0, slope) * (latest + response_s) for latest, _, slope in judged),
        default=0.0,
    )


def _span_rate_mbit(
    ordered: list[tuple[float, float, int]], now_s: float, window_s: float
) -> float:
    """Mbit/s over the frames of the window: their bytes after the first over their span.

    When the window holds fewer than a few frames, the last few, if recent.
    """
    inside = [r for r in ordered if now_s - window_s < r[0] <= now_s]
    if len(inside) < _RATE_FRAMES:
        horizon = now_s - _SPARSE_WINDOWS * window_s
        inside = [r for r in ordered[-_RATE_FRAMES:] if horizon < r[0] <= now_s]
    if len(inside) < _RATE_FRAMES:
        return 0.0
    span = inside[-1][0] - inside[0][0]
    return bytes_per_s_to_mbit(sum(size for *_, size in inside[1:]) / span) if span > 0 else 0.0


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
