"""What every design shares: the streams, their silences, outages, the update loop and bounds.

The estimator watches the frames that cross the link (receive time, size, sequence number and
the sender's send time) and moves its estimate like a congestion controller. How it reads
overuse and what it does then is its detector (``EstimatorSettings.detector``: one of
:mod:`dbml.estimator.designs`); whatever the design:

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

Streams and frames come from the network, so what is kept of them is bounded: ``MAX_STREAMS``
streams (one more evicts the one silent the longest) and ``MAX_SAMPLES`` frames over all of
them (past it a frame's delay is not kept, its sequence number still counts); the estimator
counts both, and its node (``dbml.runtime.estimator``) logs them once per flood.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from dbml.core.errors import SpecError
from dbml.core.spec import short_repr
from dbml.estimator.base import (
    RATE_FRAMES,
    Arrival,
    Detector,
    DetectorSettings,
    Estimate,
    Judged,
    Phase,
    Sample,
    View,
    check_positive,
    check_shares,
    receive_rate_mbit,
    slope,
)
from dbml.estimator.queue import QueueSettings

__all__ = ["MAX_SAMPLES", "MAX_STREAMS", "BandwidthEstimator", "EstimatorSettings"]

_TREND_FRAMES = 3
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


@dataclass(frozen=True, slots=True, kw_only=True)
class EstimatorSettings:
    """What every design shares, and the design (its detector's settings).

    The defaults were tuned on the testbed; a design's own thresholds are in its settings
    (``QueueSettings``, ``TrendlineSettings``, ``DeliveryRateSettings``).
    """

    window_s: float = 0.5
    """The delay trend is measured over this much recent time."""
    rate_window_s: float = 1.0
    """The receive rate is measured over this much recent time."""
    base_window_s: float = 15.0
    """A stream's base delay is its minimum one-way delay over this much time."""
    response_s: float = 0.4
    """After a decrease, how long the senders take to act on it (push, apply, first frame)."""
    probe_fraction: float = 0.6
    """Below this share of the estimate received, the link is not used enough to tell whether
    more would fit: no increase."""
    floor_fraction: float = 0.02
    """The estimate never falls below this fraction of the maximum."""
    outage_s: float = 0.5
    """Nothing received for this long (after frames came) is an outage: the link is down."""
    outage_gaps: float = 3.0
    """...or for this many of the recent mean inter-arrival gaps, whichever is longer."""
    after_outage_s: float = 2.0
    """After an outage, the backlog and the drops it caused are not judged for this long;
    the same for one stream back from its own silence while others flowed."""
    detector: DetectorSettings = field(default_factory=QueueSettings)
    """The design: how overuse is read, and what a cut and an increase are."""

    def __post_init__(self) -> None:
        check_positive(
            "estimator",
            self,
            (
                "window_s",
                "rate_window_s",
                "base_window_s",
                "response_s",
                "outage_s",
                "outage_gaps",
                "after_outage_s",
            ),
        )
        check_shares("estimator", self, ("probe_fraction", "floor_fraction"))
        if not isinstance(self.detector, DetectorSettings):
            raise SpecError(
                f"estimator detector={short_repr(self.detector)} is not a design's settings "
                "(see dbml.estimator.designs)"
            )


class _Stream:
    __slots__ = (
        "away",
        "back",
        "heard_s",
        "last_seq",
        "least_s",
        "lost",
        "rate_before_mbit",
        "rhythm",
        "samples",
        "settle_until_s",
    )

    def __init__(self) -> None:
        self.last_seq: int | None = None
        self.samples: deque[Sample] = deque()  # (arrival_s, delay_s, size)
        self.lost = 0
        """Frames lost (sequence gaps) since the last update."""
        self.least_s = math.inf
        """Its least one-way delay since its history (re)started: what ``observe`` returns
        a frame's queueing over, without a pass over its frames."""
        self.rhythm: deque[float] = deque(maxlen=RATE_FRAMES + 1)
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
    ``settings.detector`` picks how overuse is read (a design); the outages, the bounds and
    the streams' own silences are the same for every design.
    """

    def __init__(
        self,
        *,
        max_mbit: float,
        initial_mbit: float | None = None,
        settings: EstimatorSettings | None = None,
    ) -> None:
        self.settings = settings or EstimatorSettings()
        self._detector: Detector = self.settings.detector.detector(self.settings)
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
        self._recent: deque[float] = deque(maxlen=RATE_FRAMES + 1)
        """Arrival times of the last frames of all streams: the silence and the usual gap."""
        self._outage_since: float | None = None
        self._heard_s: float | None = None
        """The update that first saw the newest frames: silence counts on the update's clock,
        which is immune to how arrival times were mapped from another host's clock."""
        self._fresh: set[str] = set()
        """Streams with frames since the last update."""
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
                self._detector.forget(silent_name)
        self._streams[arrival.stream] = stream  # now the one heard from last
        if stream.away:
            # Back from its own silence: what it queued meanwhile and what was dropped of it
            # say nothing about the link, which the others kept using. Restart its history.
            self._samples -= len(stream.samples)
            stream.samples.clear()
            stream.rhythm.clear()
            stream.last_seq = None
            stream.least_s = math.inf
            stream.away, stream.back = False, True
            self._detector.forget(arrival.stream)
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
            self._detector.observe(arrival)
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
            self._detector.forget(None)
            self._samples = 0
            newest = self._recent[-1]
            self._recent.clear()
            self._recent.append(newest)
            self._judge_from = now_s + self.settings.after_outage_s
            return None
        self._fresh.clear()
        self._detector.forget(None)
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
                    receive_rate_mbit(samples, samples[-1][0], s.rate_window_s) if samples else 0.0
                )
        self._fresh.clear()

    def _speaks(self, name: str) -> bool | None:
        """Whether ``name``'s delays speak for the link now (None: it is not followed)."""
        stream, now_s = self._streams.get(name), self._last_update
        return None if stream is None or now_s is None else stream.judged(now_s)

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
        recent: list[Sample] = []  # (arrival, queue delay, size), all streams
        judged: list[Judged] = []
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
                self._detector.forget(name)
                continue
            speaks = stream.judged(now_s)
            if speaks:
                lost += stream.lost
            stream.lost = 0
            if not speaks:
                mine_rate = receive_rate_mbit(list(samples), now_s, s.rate_window_s)
                stand_in += stream.rate_before_mbit - mine_rate
            if not samples:
                if not stream.away:
                    del self._streams[name]  # stopped; its seq restarts if it returns
                    self._detector.forget(name)
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
                trend = slope([(t, q) for t, q, _ in mine])
                judged.append(
                    Judged(queued[-1][1], min(q for _, q, _ in mine), trend, samples, mine)
                )
        if settling:
            lost = 0  # what the middleware dropped while the link was down
        recent.sort()
        received = receive_rate_mbit(recent, now_s, s.rate_window_s)
        view = View(
            now_s=now_s,
            dt_s=dt,
            settling=settling,
            lost=lost,
            recent=recent,
            judged=judged,
            received=received,
            cut_rate=max(0.0, received + stand_in),
            estimate_mbit=self._estimate,
            max_mbit=self._max_mbit,
            speaks=self._speaks,
        )
        decision = self._detector.decide(view)
        floor = s.floor_fraction * self._max_mbit
        self._estimate = min(self._max_mbit, max(floor, decision.estimate_mbit))
        queue = max((j.least_s for j in judged), default=0.0)
        trend = max((j.slope for j in judged), default=0.0)
        self.last = Estimate(
            now_s,
            self._estimate,
            decision.phase,
            received,
            queue,
            trend,
            lost,
            reason=decision.reason,
        )
        return self.last


def _check_max(max_mbit: float) -> float:
    if not (math.isfinite(max_mbit) and max_mbit > 0):
        raise SpecError(f"estimator max_mbit={max_mbit!r} must be a positive number")
    return max_mbit
