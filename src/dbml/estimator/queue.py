"""The ``queue`` design (the default): a queue that stands or rises past the link's pace.

Overuse: queueing that stands above ``max_queue_delay_s``; queueing that rises above
``overuse_delay_s`` (plus, near a rate the link was measured at, one frame of another stream's
wait, the link's own pace); frames lost. A queue that rose while the link's median rate of the
last seconds (packet pairs) is ``headroom`` above the estimate drains by itself (a radio fade's
backlog, a burst): no cut. Otherwise a cut to ``backoff`` of the link's rate less what drains the
queue within ``drain_s``; before enough frames have queued to measure that rate the cut is
provisional, undone if the frames behind it cross at the rate offered before (a fade), kept if
slower (a fall); read with the frame before it, whose pair may straddle the fall, the cut is
measured again by the frames after. Once drained (no stream's newest frame waiting longer than
its own slower transmission and one frame of another stream), the estimate goes back to
``backoff`` of the rate measured and stays there until that rate is ``memory_s`` old, then
probes up slowly near it and fast away from it;
frames of the largest stream crossing faster than in the seconds before, or as fast as before
the last fall (the link rose), end the stay and the slow band, and the estimate goes at once to
the rate their shorter transmission implies (``rise_step`` times itself at most); so it does,
after an outage, to the rate of the frames since if that is far above it. After a fall, a
frame's own longer transmission at the rate measured is not read as queue.

It reads, per stream that speaks for the link, its newest and least queueing and their slope and
its frames' one-way delays; the packet pairs of the last ``window_s``; the frames lost. A pair,
a standing queue and a drained one are judged only on frames that waited for the frame ahead
(:func:`dbml.estimator.base.behind`): a frame sent into an idle link that queued in a fade, or
crossed a slower radio in more time, waited for nothing.
"""

from __future__ import annotations

import bisect
import itertools
import math
import statistics
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from dbml.core.errors import SpecError
from dbml.estimator.base import (
    PATH_S,
    RATE_FRAMES,
    Arrival,
    Decision,
    Judged,
    Phase,
    Sample,
    SharedSettings,
    View,
    behind,
    bunched,
    busy_rate_mbit,
    check_positive,
    check_shares,
)

__all__ = ["QueueDetector", "QueueSettings", "increase"]


@dataclass(frozen=True, slots=True, kw_only=True)
class QueueSettings:
    """The ``queue`` design's thresholds and rates; the defaults were tuned on the testbed."""

    overuse_delay_s: float = 0.04
    """Queueing delay above this, while rising faster than ``overuse_trend``, is overuse."""
    overuse_trend: float = 0.05
    """Seconds of queueing delay gained per second."""
    max_queue_delay_s: float = 0.15
    """Queueing delay above this is overuse unless it is already falling."""
    backoff: float = 0.95
    """A cut is to this share of the packet-pair rate (less what drains the queue)."""
    drain_s: float = 1.0
    """A cut leaves room to drain the queue within this long."""
    slow_increase_per_s: float = 0.05
    fast_increase_per_s: float = 0.25
    near_band: tuple[float, float] = (0.8, 1.1)
    """Around the capacity last measured under overuse (as fractions), increase slowly."""
    least_pairs: int = 3
    """The link's rate needs this many packet pairs (a fade spans one); a cut before them is
    provisional..."""
    undo_s: float = 1.0
    """...and undone if within this long the pairs measure ``undo_share`` of the estimate before
    it (a fade's backlog crossing at the link's pace, as TCP's recovery allows)."""
    undo_share: float = 0.8
    provisional_share: float = 0.92
    """A provisional cut is to this share of the estimate."""
    plateau_s: float = 4.0
    """Back at the rate a cut measured, the estimate stays there this long before it probes
    above it (the link's rise, seen, ends the stay)."""
    rise_delay_s: float = 0.02
    rise_window_s: float = 5.0
    """A stream's frames crossing ``rise_delay_s`` faster than any in the ``rise_window_s``
    before, or as fast as before the last fall (within ``rise_delay_s``): the link rose (its
    frames' own transmission is shorter), the slow band is left."""
    rise_step: float = 2.0
    """On a rise, the estimate goes at once to the link's rate the shorter transmission implies,
    at most this many times what it was."""
    link_window_s: float = 3.0
    """The link's median rate over this long says whether a queue drains by itself."""
    memory_s: float = 8.0
    """A cut's measure of the link holds the increase back (no probe above it) this long."""
    headroom: float = 1.1
    """A queue while the link carries this many times the estimate or more drains by itself
    (a fade's backlog, a burst): hold, no cut."""

    def __post_init__(self) -> None:
        check_positive(
            "estimator",
            self,
            (
                "overuse_delay_s",
                "max_queue_delay_s",
                "drain_s",
                "undo_s",
                "plateau_s",
                "link_window_s",
                "memory_s",
                "rise_delay_s",
                "rise_window_s",
                "rise_step",
                "headroom",
                "slow_increase_per_s",
                "fast_increase_per_s",
            ),
        )
        check_shares("estimator", self, ("backoff", "undo_share", "provisional_share"))
        if self.least_pairs < 1:
            raise SpecError(f"estimator least_pairs={self.least_pairs!r} must be at least 1")

    def detector(self, shared: SharedSettings) -> QueueDetector:
        """A fresh ``queue`` detector."""
        return QueueDetector(self, shared)


class QueueDetector:
    """A queue that stands or rises past the link's pace; a cut to the link's rate."""

    def __init__(self, settings: QueueSettings, shared: SharedSettings) -> None:
        self.settings = settings
        self._shared = shared
        self._frozen_until = -math.inf
        """No new cut before this: what was sent before the last one is still arriving."""
        self._capacity_mbit: float | None = None
        """The link's rate measured at the last cut (or found faster since)."""
        self._provisional_mbit: float | None = None
        """The estimate before a cut made before the link's rate could be measured."""
        self._provisional_s = -math.inf
        self._provisional_until = -math.inf
        self._cruise_until = -math.inf
        """Back at the link's rate after a cut: no probe above it before this (unless it rose)."""
        self._drained_s = -math.inf
        """When the last cut's queue drained (the return to the link's rate)."""
        self._capacity_s = -math.inf
        """When the last cut measured the link's rate."""
        self._aged_mbit: float | None = None
        """That rate once ``memory_s`` old and not confirmed: the estimate probes slowly near it."""
        self._cut_from_mbit = math.inf
        """The estimate the last cut was made from."""
        self._rates: deque[tuple[float, float]] = deque()
        """(when, Mbit/s): the link's rate at each update that measured it, ``link_window_s``."""
        self._rose = False
        """The link was seen to rise since the last cut."""
        self._paced_s = math.inf
        """When the last cut's queue had drained (the estimate back at the rate it measured):
        frames since then cross at the pace of the link after it."""
        self._risen_mbit: float | None = None
        """The link's rate a rise implies: the increases go there (``rise_step`` at a time)."""
        self._fall: tuple[float, float, float] | None = None
        """(when, Mbit/s before, Mbit/s after) of the last fall a cut measured, until it rises."""
        self._why_cut = ""
        """The last cut's reason, repeated in the holds that follow it."""
        self._why_provisional = ""
        """What the provisional cut read, for the cut that a fall measured makes of it."""
        self._back_from_outage = False
        """The link was down: once its backlog drained, the link it came back at is read once."""
        self._straddle: tuple[float, float] | None = None
        """(start, until) after a cut measured with the frame before the provisional cut: that
        frame's pair may straddle the fall, so the frames after it measure the link again."""
        self._queued_provisional = True
        """It read a queue (not frames lost): frames that then cross unqueued undo it."""
        self._restore = False
        """The last cut went below the link's rate to drain the queue: back to it once drained."""
        self._restore_to_mbit = 0.0
        """Where that is, should the cut's measure be gone by then (the link rose)."""

    def observe(self, arrival: Arrival) -> None:
        """Nothing: it reads the streams' delays from the view."""

    def forget(self, stream: str | None) -> None:
        """The link went down (``None``): a provisional cut read the start of the outage."""
        if stream is None:
            self._back_from_outage = True
            self._straddle = None  # what arrives after an outage did not cross the fall
            if self._provisional_mbit is not None:
                self._provisional_until = math.inf

    def decide(self, view: View) -> Decision:
        """Cut on overuse once a cut could have acted; hold while it drains; increase."""
        s, shared = self.settings, self._shared
        judged = view.judged
        estimate = view.estimate_mbit
        if self._provisional_until == math.inf and self._provisional_mbit is not None:
            # The queue the provisional cut read was the outage's start; the outage keeps the
            # estimate from before it, as it does for every design.
            before, self._provisional_mbit = self._provisional_mbit, None
            self._frozen_until, self._restore = -math.inf, False
            return Decision(Phase.HOLD, max(estimate, before), "outage: provisional cut undone")
        if view.settling:
            return Decision(Phase.HOLD, estimate, "outage's backlog drains")
        fastest = _PLAUSIBLE * view.max_mbit
        before_mbit = self._capacity_mbit if self._capacity_mbit is not None else self._aged_mbit
        recent_s = view.now_s - shared.window_s
        rise = (
            None
            if before_mbit is None
            else _faster(
                judged, since_s=view.now_s - s.rise_window_s, recent_s=recent_s, by_s=s.rise_delay_s
            )
        )
        if before_mbit is not None and rise is not None:
            # Frames cross in less time than any in the seconds before: the link rose, what
            # the last cut measured no longer holds the increase back, and how much sooner
            # they arrive says by how much.
            shorter_s, size_bytes = rise
            self._risen_mbit = _risen_mbit(before_mbit, shorter_s, size_bytes, fastest)
            self._rose_back()
        elif self._fall is not None and _as_fast_as_before(
            judged, self._fall[0], self._paced_s, recent_s=recent_s, by_s=s.rise_delay_s
        ):
            # Frames cross as fast as they did before the fall (once its queue drained, they
            # crossed slower): the link carries again what it carried then.
            self._risen_mbit = self._fall[1]
            self._rose_back()
        if self._back_from_outage:
            # Back from an outage (its settle over): the frames since crossed behind one another
            # at the rate the link came back at. A radio may come back far faster than it went:
            # the estimate goes there at once, not at the pace of a probe from a rate the link
            # no longer has. Far faster only: the pairs of frames TCP held read above the link.
            self._back_from_outage = False
            after = _median_pair_mbit(view.recent, s.overuse_delay_s / 2, fastest, shared.window_s)
            last = max(estimate, before_mbit or 0.0)
            if after is not None and after >= _BACK_FASTER * last:
                self._risen_mbit = after
                self._rose_back()
        pairs = view.pairs(shared.window_s)
        measured = busy_rate_mbit(
            pairs, s.overuse_delay_s / 2, least=s.least_pairs, fastest_mbit=fastest
        )
        if measured is not None:
            # Frames a stall held back reach the receiver together: their pairs say nothing of
            # the link. One faster than the estimate could ever use is not taken for it.
            measured = min(measured, fastest)
            self._rates.append((view.now_s, measured))
        while self._rates and self._rates[0][0] < view.now_s - s.link_window_s:
            self._rates.popleft()
        # The link's rate of the last seconds: frames that queue behind a fade cross as TCP's
        # recovery lets them (slower than the link), or all at once from the receiver's buffer
        # (faster): the median reading of the last seconds speaks for the link.
        link_mbit = statistics.median(r for _, r in self._rates) if self._rates else None
        if self._capacity_mbit is not None and view.now_s > self._capacity_s + s.memory_s:
            # Not confirmed by a cut for a while: probe above it, slowly near it.
            self._aged_mbit, self._capacity_mbit = self._capacity_mbit, None
        undone = self._settle_provisional(view, pairs)
        if undone is not None:
            return undone
        remeasured = self._remeasure(view, pairs)
        if remeasured is not None:
            return remeasured
        # Near a rate the link was measured at (or rising to one), a frame may wait for one
        # frame of another stream to cross: that wait is the link's own pace, not a queue that
        # grows.
        pace_s = 0.0
        near = self._capacity_mbit
        pace_mbit = link_mbit if link_mbit is not None and estimate <= link_mbit else None
        if self._rose and measured is not None:
            pace_mbit = measured
        if near is not None and estimate <= s.near_band[1] * near:
            pace_mbit = near
        if pace_mbit:
            pace_s = 8e-6 / pace_mbit
        queued = s.overuse_delay_s / 2
        latest = _since(view.recent, view.now_s - s.link_window_s)
        waited = {f for p, f in itertools.pairwise(latest) if behind(p, f, queued, fastest)}
        # Probing above the rate a cut measured, a queue that rises at half the pace is read:
        # the probe found the link's edge, and a later reading is a larger spike.
        edge = near if near is not None else self._aged_mbit
        probing = edge is not None and estimate > edge
        trend = s.overuse_trend * (_PROBING_TREND if probing else 1.0)
        # probing, a frame crossing more slowly is taken for the queue it may be
        slower = _none if probing else self._slower_s
        sizes = [size for *_, size in pairs]
        overuse, standing = _overuse(view, s, sizes, pace_s, waited, trend=trend, slower=slower)
        draining = bool(judged) and all(j.slope < -s.overuse_trend for j in judged)
        if overuse and view.now_s >= self._frozen_until:
            if not standing and link_mbit is not None and link_mbit >= s.headroom * estimate:
                # The link carries more than is offered: a queue that rose (a burst, a fade's
                # backlog, the frames a sender dropped while it could not send) drains by
                # itself. One that stands does not.
                return Decision(
                    Phase.HOLD, estimate, f"{overuse}; drains: link {link_mbit:.2f} Mbit/s"
                )
            if measured is None:
                if self._provisional_mbit is not None:
                    return Decision(Phase.HOLD, estimate, self._why_cut)
                # Too few frames queued to tell a fade from a fall: cut on what arrived, and
                # undo it if the frames behind say the link carried what was offered.
                # The cut is shallow: the same signal (a frame that waited) comes from a link at
                # its own pace.
                self._provisional_mbit = estimate
                self._straddle = None
                self._provisional_s = view.now_s
                self._provisional_until = view.now_s + s.undo_s
                self._frozen_until = view.now_s + shared.response_s
                self._why_provisional = overuse
                # Frames lost with no queue standing are no fade's backlog to wait out.
                self._queued_provisional = standing or view.lost == 0
                self._why_cut = f"{overuse}; provisional"
                return Decision(Phase.DECREASE, s.provisional_share * estimate, self._why_cut)
            self._provisional_mbit = None
            return self._cut(view, measured, why=overuse)
        if overuse or draining or view.now_s < self._frozen_until:
            # Still draining, or the cut not yet seen.
            return Decision(Phase.HOLD, estimate, self._why_cut if self._why_cut else overuse)
        if self._restore and any(
            j.latest_s
            > max(
                s.max_queue_delay_s,
                _other_frame_s(j, sizes, pace_s)
                + (0.0 if probing else self._slower_s(j, newest=True)),
            )
            and j.window[-1] in waited
            for j in judged
        ):
            # Below the link's rate to drain a queue: a stream's newest frame still waited (more
            # than a standing queue's, or than its own longer transmission on a slower link and
            # one frame of another stream: 84 KB take 168 ms more at 2.87 Mbit/s than at 10.1).
            return Decision(Phase.HOLD, estimate, self._why_cut)
        if self._capacity_mbit is not None:
            # Drained: cruise at the link's rate the cut measured, not below it.
            # Never above the estimate the cut was made from: it overused the link.
            cruise = min(s.backoff * self._capacity_mbit, self._cut_from_mbit)
            self._paced_s = min(self._paced_s, view.now_s)
            if self._restore and estimate < cruise:
                self._restore = False
                self._cruise_until = view.now_s + s.plateau_s
                self._drained_s = view.now_s
                return Decision(Phase.INCREASE, cruise, "drained: back to the link's rate")
            # Frames that queued behind others say the link's rate without overuse: found
            # faster than the cut's (the link rose), it leaves the slow band. The median of the
            # pairs since the cut's queue drained, each once and over a window at least: frames
            # a stall bunched arrive within milliseconds, often as the queue drains, and the
            # updates' readings repeat them while they are in the window.
            since_cut = _since(view.recent, max(self._capacity_s, self._drained_s))
            faster = _median_pair_mbit(since_cut, queued, fastest, shared.window_s)
            if faster is not None and faster > s.near_band[1] * self._capacity_mbit:
                self._capacity_mbit = faster
            elif view.now_s < self._cruise_until or estimate >= cruise:
                # No probe above the rate measured while it holds: a rise shows as frames
                # crossing faster, and each probe past the link's edge is a spike of latency.
                return Decision(Phase.HOLD, estimate, "at the link's rate measured")
        elif self._restore and estimate < self._restore_to_mbit:
            # The link rose (or the cut's measure aged) while its queue drained: back to the
            # rate the cut measured at least, and from there up at pace.
            self._restore = False
            return Decision(
                Phase.INCREASE, self._restore_to_mbit, "drained: back to the link's rate"
            )
        self._restore = False
        self._why_cut = ""
        decision = increase(
            view,
            self._capacity_mbit if self._capacity_mbit is not None else self._aged_mbit,
            probe_fraction=shared.probe_fraction,
            slow_per_s=s.slow_increase_per_s,
            fast_per_s=s.fast_increase_per_s,
            near_band=s.near_band,
        )
        if self._rose and decision.phase is Phase.INCREASE:
            risen = self._risen_mbit
            if risen is None:
                return Decision(decision.phase, decision.estimate_mbit, "the link rose")
            step = min(s.backoff * risen, s.rise_step * estimate)
            if step <= decision.estimate_mbit:
                self._risen_mbit = None  # there: on at the usual pace
            return Decision(
                decision.phase,
                max(decision.estimate_mbit, step),
                f"the link rose to {risen:.2f} Mbit/s",
            )
        return decision

    def _settle_provisional(self, view: View, pairs: list[Sample]) -> Decision | None:
        """Undo a provisional cut the link's rate did not call for; let a called-for one stand."""
        before = self._provisional_mbit
        if before is None:
            return None
        # The link's rate from the frames that arrived since the cut (the ones before it may
        # have crossed before a fall), and the one before them: frames a stall held back come
        # out together, and their pairs read with the gap that ends where they start.
        since = _since(pairs, self._provisional_s)
        fastest = _PLAUSIBLE * view.max_mbit
        measured = busy_rate_mbit(
            since, self.settings.overuse_delay_s / 2, least=_SETTLE_PAIRS, fastest_mbit=fastest
        )
        if measured is not None:
            measured = min(measured, fastest)
        # Or every stream's frames since the cut crossed without waiting: the queue drained by
        # itself (a fade's backlog at a rate the link carries), which it does not at a rate
        # above a fall's. Every stream's: a publisher's backlog sits in its own connection,
        # and another's small frame may cross between its frames.
        drained = self._queued_provisional and _unqueued_since(
            view, self._provisional_s, self.settings.overuse_delay_s / 2, fastest
        )
        if drained or (measured is not None and measured >= self.settings.undo_share * before):
            # A fade: what queued crossed at (nearly) the rate offered before the cut.
            self._provisional_mbit = None
            self._frozen_until = -math.inf
            self._restore = False
            self._why_cut = ""
            why = "the queue drained" if drained else f"link {measured:.2f} Mbit/s"
            return Decision(
                Phase.INCREASE, max(view.estimate_mbit, before), f"provisional cut undone: {why}"
            )
        if measured is not None:
            # A fall: the cut to the link's rate, now measured, at once. Read with the frame
            # before the cut, whose pair may straddle the fall: unless the first two frames after
            # it came out together (a stall's gap, which starts at that frame), the frames after
            # it measure the link again (``_remeasure``).
            self._provisional_mbit = None
            cut = self._cut(view, measured, why=self._why_provisional)
            if measured > 0 and _straddles(since, self._provisional_s, self.settings, fastest):
                self._straddle = (self._provisional_s, view.now_s + self.settings.undo_s)
            return cut
        if view.now_s >= self._provisional_until:
            # Nothing measured to undo it: it stands, and a queue may cut again.
            self._provisional_mbit = None
            self._frozen_until = min(self._frozen_until, view.now_s)
        return None

    def _remeasure(self, view: View, pairs: list[Sample]) -> Decision | None:
        """A cut measured from a pair that may straddle the fall, measured without it.

        The frame that arrived before the provisional cut may have been sent just after the one
        ahead of it arrived and crossed partly at the rate before the fall: the pair reads
        faster than the link (5.71 Mbit/s on a 5-Mbit/s link's 4.79 of payload, recorded). The
        cut does not wait for the frames after it (a retransmission's stall may hold them past
        an outage's silence); once they measure a slower link, it goes down to theirs.
        """
        if self._straddle is None or self._provisional_mbit is not None:
            return None
        start_s, until_s = self._straddle
        if view.now_s > until_s or self._capacity_mbit is None:
            self._straddle = None
            return None
        fastest = _PLAUSIBLE * view.max_mbit
        after = _after(pairs, start_s)
        measured = busy_rate_mbit(
            after, self.settings.overuse_delay_s / 2, least=_SETTLE_PAIRS, fastest_mbit=fastest
        )
        if measured is None:
            return None
        self._straddle = None
        if not 0 < measured < _REMEASURED_SHARE * self._capacity_mbit:
            return None
        fall = self._fall
        cut = self._cut(view, measured, why=f"{self._why_provisional}; measured after the fall")
        if fall is not None:
            self._fall = (fall[0], fall[1], measured)  # the same fall, now measured
        return cut

    def _cut(self, view: View, capacity: float, *, why: str) -> Decision:
        """A cut to ``backoff`` of ``capacity`` less what drains the queue; then a freeze."""
        s, estimate = self.settings, view.estimate_mbit
        self._straddle = None
        if capacity <= 0:
            return Decision(Phase.DECREASE, estimate, f"{why}; nothing received")
        # The queue grows no faster than what is offered (the estimate at most) exceeds what
        # the link carries: a burst's slope (frames of two allocations at once, as one
        # replaces the other) does not go on until the cut acts.
        growth = max(0.0, estimate / capacity - 1.0)
        backlog = _backlog_s(
            view.judged, self._shared.response_s, max_slope=growth, low_s=s.overuse_delay_s / 2
        )
        self._capacity_mbit = capacity
        self._aged_mbit = None
        self._capacity_s = view.now_s
        # A cut before the last one's queue drained is the same episode: it was made from the
        # estimate before the first.
        self._cut_from_mbit = max(estimate, self._cut_from_mbit) if self._restore else estimate
        self._restore = True
        self._restore_to_mbit = min(s.backoff * capacity, self._cut_from_mbit)
        drain = backlog * capacity / s.drain_s
        target = max(s.backoff * capacity - drain, 0.5 * s.backoff * capacity)
        # Frames still queued were sent before this decrease could act: wait until what is
        # sent after it has had time to arrive.
        self._frozen_until = view.now_s + backlog + self._shared.response_s
        self._rose = False
        self._risen_mbit = None
        self._paced_s = math.inf
        if capacity < estimate:
            self._fall = (view.now_s, estimate, capacity)
        self._why_cut = f"{why}; link {capacity:.2f} Mbit/s, backlog {backlog * 1e3:.0f} ms"
        return Decision(Phase.DECREASE, min(estimate, target), self._why_cut)

    def _rose_back(self) -> None:
        """The link rose: no cut's measure holds the increase back."""
        self._capacity_mbit = self._aged_mbit = None
        self._rose = True
        self._fall = None

    def _slower_s(self, judged: Judged, *, newest: bool = False) -> float:
        """How much slower ``judged``'s largest (or ``newest``) frame crosses than at its least.

        A least delay met before the last fall was met on a link that carried at least the
        estimate then: since, the frame's own transmission takes longer at the rate measured,
        and that is no queue (84 KB: 75 ms more at 4.76 Mbit/s than at 10.1).
        """
        if self._fall is None or not judged.samples:
            return 0.0
        fall_s, before_mbit, after_mbit = self._fall
        least_t, _, _ = min(judged.samples, key=lambda sample: sample[1])
        if least_t >= fall_s or after_mbit <= 0:
            return 0.0
        own = judged.window[-1][2] if newest else max(size for *_, size in judged.samples)
        return own * 8e-6 * (1.0 / after_mbit - 1.0 / before_mbit)


def _none(_: Judged) -> float:
    """No allowance."""
    return 0.0


def increase(
    view: View,
    capacity_mbit: float | None,
    *,
    probe_fraction: float,
    slow_per_s: float,
    fast_per_s: float,
    near_band: tuple[float, float],
) -> Decision:
    """Up, if the link is used: slowly near ``capacity_mbit`` (the last cut's), fast away."""
    estimate = view.estimate_mbit
    if view.received < probe_fraction * estimate:
        return Decision(Phase.HOLD, estimate)  # not used enough to tell whether more fits
    low, high = near_band
    near = capacity_mbit is not None and (low * capacity_mbit <= estimate <= high * capacity_mbit)
    rate = slow_per_s if near else fast_per_s
    return Decision(Phase.INCREASE, estimate * (1.0 + rate) ** view.dt_s)


_PLAUSIBLE = 1.25
"""Packet pairs faster than this many times the configured budget are the receiver's bunching."""
_PROBING_TREND = 0.5
"""Above the rate a cut measured, a rising queue is read at this share of ``overuse_trend``."""
_SINCE_CUT = 5
"""Packet pairs since a cut that may say the link rose (their median)."""
_BACK_FASTER = 1.5
"""After an outage, a link read this many times the estimate (and the rate last measured) came
back faster. Frames TCP held read faster than the link: 6.75 Mbit/s on one that carried 4.79
(recorded on the testbed's drop, an outage declared inside the fall's stall)."""
_SETTLE_PAIRS = 2
"""Two pairs since a provisional cut settle it: one that spans a fade is slow, the median (the
faster of two) is the link's."""
_STRADDLE_FRAMES = 3
"""The frame before the cut, the first after it and the next: a pair, and whether a stall's."""
_REMEASURED_SHARE = 0.95
"""Frames after a fall that read the link below this share of what its cut read cut again."""


def _since(recent: list[Sample], start_s: float) -> list[Sample]:
    """The frames (in arrival order) that arrived after ``start_s``, and the one before them."""
    first = bisect.bisect_right(recent, (start_s, math.inf, 0))
    return recent[max(0, first - 1) :]


def _after(recent: list[Sample], start_s: float) -> list[Sample]:
    """The frames (in arrival order) that arrived after ``start_s``."""
    return recent[bisect.bisect_right(recent, (start_s, math.inf, 0)) :]


def _straddles(since: list[Sample], start_s: float, s: QueueSettings, fastest_mbit: float) -> bool:
    """Whether ``since``'s first frame, before ``start_s``, read a pair with the next one.

    Such a pair may straddle a fall. Not if the frames after it came out together: then it
    starts the stall's reading, whose gap is the stall's own.
    """
    if len(since) < _STRADDLE_FRAMES:
        return False
    return (
        since[0][0] <= start_s
        and behind(since[0], since[1], s.overuse_delay_s / 2, fastest_mbit, same_instant=True)
        and not bunched(since[1], since[2], fastest_mbit)
    )


def _median_pair_mbit(
    frames: list[Sample], queued_s: float, fastest_mbit: float, window_s: float
) -> float | None:
    """The median of ``_SINCE_CUT`` pairs or more among ``frames`` spanning ``window_s``.

    Frames a stall bunched arrive within milliseconds and often all at once: a reading says
    how fast the link is only over a window, each pair once (since a cut, or an outage).
    """
    if not frames or frames[-1][0] - frames[0][0] < window_s:
        return None
    rate = busy_rate_mbit(frames, queued_s, least=_SINCE_CUT, fastest_mbit=fastest_mbit)
    return None if rate is None else min(rate, fastest_mbit)


def _unqueued_since(view: View, start_s: float, queued_s: float, fastest_mbit: float) -> bool:
    """Whether each stream with frames since ``start_s`` had one that waited for nothing.

    It did not queue (``queued_s``), or the link idled before it: it arrived more than its
    queueing, its own transmission at ``fastest_mbit`` and ``PATH_S`` after the frame ahead.
    """
    recent = _since(view.recent, start_s)
    idle = {
        frame
        for (t_prev, _, _), frame in itertools.pairwise(recent)
        if frame[1] < queued_s
        or frame[0] - t_prev > frame[1] + frame[2] * 8e-6 / fastest_mbit + PATH_S
    }
    crossed = [[f for f in j.window if f[0] > start_s] for j in view.judged]
    crossed = [frames for frames in crossed if frames]
    return bool(crossed) and all(any(f in idle for f in frames) for frames in crossed)


def _overuse(
    view: View,
    s: QueueSettings,
    sizes: list[int],
    pace_s: float,
    waited: set[Sample],
    *,
    trend: float,
    slower: Callable[[Judged], float],
) -> tuple[str, bool]:
    """What says the link is overused, in a few words (empty if nothing does).

    And whether it is a queue that stands (rather than one that rose, or frames lost).
    ``sizes``: the recent frames' bytes; ``pace_s``: seconds a byte takes on the link (0: not
    known), so a stream's frame may wait for one larger frame of another stream; ``waited``:
    the recent frames that crossed right behind another; ``trend``: the slope of a queue that
    rises; ``slower``: how much longer a stream's own frame takes than when its least delay
    was met.
    """
    allowance = {id(j): _other_frame_s(j, sizes, pace_s) + slower(j) for j in view.judged}
    for j in view.judged:
        # A queue stands only where frames wait behind frames. A large frame's own
        # transmission on a link slower than when its stream's least delay was measured (a
        # radio's rate moves) delays it as much (84 KB: 167 ms more at 3 Mbit/s than at 11.7)
        # on a link that idles between frames.
        if (
            j.least_s > max(s.max_queue_delay_s, allowance[id(j)])
            and j.slope >= 0
            and j.window[-1] in waited
        ):
            return f"standing queue {j.least_s * 1e3:.0f} ms", True
    if view.lost > 0:
        return f"{view.lost} lost", False
    for j in view.judged:
        if j.latest_s > s.overuse_delay_s + allowance[id(j)] and j.slope > trend:
            return f"queue {j.latest_s * 1e3:.0f} ms rising {j.slope:.2f} s/s", False
    return "", False


def _other_frame_s(judged: Judged, sizes: list[int], pace_s: float) -> float:
    """How long a frame of ``judged``'s stream may wait for another stream's frame to cross.

    The other frame is the largest one of another size class: the largest of all for a stream
    of smaller frames, the largest smaller than its own for the stream of the largest.
    """
    if not pace_s or not sizes:
        return 0.0
    own = max((size for *_, size in judged.samples), default=0)
    largest = max(sizes)
    other = largest if own < largest else max((n for n in sizes if n < own), default=0)
    return other * pace_s


def _largest(judged: list[Judged]) -> Judged | None:
    """The stream of the largest frames: their own transmission is most of their delay."""
    sized = [j for j in judged if j.samples]
    return max(sized, key=lambda j: max(size for *_, size in j.samples)) if sized else None


def _faster(
    judged: list[Judged], *, since_s: float, recent_s: float, by_s: float
) -> tuple[float, int] | None:
    """How much faster the stream of the largest frames crossed lately than in the seconds before.

    Its least one-way delay since ``recent_s`` is ``by_s`` below its least between ``since_s``
    and then (a clock offset cancels: both are the same stream's): (that many seconds shorter,
    its largest frame's size), else None. The largest frames, because their own transmission is
    most of their delay: a small frame's varies with what it waited behind.
    """
    largest = _largest(judged)
    if largest is None:
        return None
    before = [d for t, d, _ in largest.samples if since_s <= t < recent_s]
    now = [d for t, d, _ in largest.samples if t >= recent_s]
    if len(before) < RATE_FRAMES or not now or min(now) >= min(before) - by_s:
        return None
    return min(before) - min(now), max(size for *_, size in largest.samples)


def _as_fast_as_before(
    judged: list[Judged], fall_s: float, paced_s: float, *, recent_s: float, by_s: float
) -> bool:
    """Whether the stream of the largest frames crosses as fast as before ``fall_s`` again.

    Its least one-way delay was met before the fall; every frame of it since ``paced_s`` (the
    fall's queue drained) crossed more than twice ``by_s`` slower: its own transmission is
    longer on the link after the fall (an overload's queue drained to the least is no fall);
    and one since ``recent_s`` within ``by_s`` of that least.
    """
    largest = _largest(judged)
    if largest is None:
        return False
    least_t, least_s, _ = min(largest.samples, key=lambda sample: sample[1])
    since = [d for t, d, _ in largest.samples if paced_s <= t < recent_s]
    now = [d for t, d, _ in largest.samples if t >= recent_s]
    return (
        least_t < fall_s
        and bool(since)
        and bool(now)
        and min(since) > least_s + 2 * by_s
        and min(now) <= least_s + by_s
    )


def _risen_mbit(
    before_mbit: float, shorter_s: float, size_bytes: int, fastest_mbit: float
) -> float | None:
    """The link's rate once a frame crosses ``shorter_s`` sooner than at ``before_mbit``.

    Its own transmission (``size_bytes``) is that much shorter. None if that is faster than
    ``fastest_mbit``: the frames it was compared with had queued, and it says nothing of the link.
    """
    megabits = size_bytes * 8e-6
    takes_s = megabits / before_mbit - shorter_s
    if takes_s <= megabits / fastest_mbit:
        return None
    return megabits / takes_s


def _backlog_s(judged: list[Judged], response_s: float, *, max_slope: float, low_s: float) -> float:
    """The queue by the time a decrease acts.

    It keeps growing until then, at most at ``max_slope`` (seconds of queueing a second).
    """
    return max(
        (
            j.latest_s
            + min(max(0.0, j.slope, _ramp(j, low_s)), max_slope) * (j.latest_s + response_s)
            for j in judged
        ),
        default=0.0,
    )


def _ramp(judged: Judged, low_s: float) -> float:
    """How fast the queue grew since the stream's last frame that queued at most ``low_s``.

    The trend window's regression also spans the frames before a fall, so it reads a fraction
    of the pace at which the queue grows after it: the ramp from where it began does not.
    """
    window = judged.window
    if not window:
        return 0.0
    newest_s, newest_q, _ = window[-1]
    start = next((sample for sample in reversed(window[:-1]) if sample[1] <= low_s), None)
    if start is None or newest_s <= start[0]:
        return 0.0
    return (newest_q - start[1]) / (newest_s - start[0])
