"""What an analysis takes (``Arrival``, ``Tick``) and what it finds, as frozen records."""

from __future__ import annotations

from dataclasses import dataclass

from dbml.experiment.analysis.thresholds import RATE_TOLERANCE
from dbml.protocol.messages import EstimatorState

__all__ = [
    "Analysis",
    "Arrival",
    "LinkChange",
    "LinkPhase",
    "Outage",
    "SeriesPoint",
    "StepResult",
    "StreamLatency",
    "Tick",
    "Window",
]


@dataclass(frozen=True, slots=True)
class Arrival:
    """One frame as the operator received it (wall-clock times; the hosts share a clock)."""

    robot: int
    seq: int | None
    """The publisher's sequence number (None: no metadata, as over ROS 1)."""
    sent_s: float | None
    arrival_s: float
    size_bytes: int
    rate_hz: float | None
    """The rate the publisher applied when it sent this frame."""
    ssim: float | None = None
    """A camera's JPEG decoded by the operator, scored against the frame that was sent (None:
    not a camera's JPEG, or not scored)."""


@dataclass(frozen=True, slots=True)
class Tick:
    """The parameters the operator saw at ``t_s`` (wall clock)."""

    t_s: float
    allocated_hz: tuple[float | None, ...]
    budget_mbit: float | None
    estimate_mbit: float | None
    estimator: EstimatorState | None = None
    """The estimator's state (phase, receive rate, queueing, losses), when one runs."""
    variants: tuple[str, ...] = ()
    """The copy each robot's subscriber takes (``full`` or ``optimized``)."""
    encodings: tuple[str | None, ...] = ()
    """The rung pushed to each robot's camera (``x1 q80``; None: none, or no ladder)."""


@dataclass(frozen=True, slots=True)
class Window:
    """One robot over one window: the measured part of a step, or one point of the series."""

    robot: str
    allocated_hz: float | None
    delivered_hz: float
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    lost: int
    goodput_mbit: float
    variant: str | None = None
    ssim: float | None = None
    """The mean SSIM of the frames scored in the window (None: none was)."""
    encoding: str | None = None
    """The rung pushed to the robot's camera at the window's end (None: none)."""
    allocated_mean_hz: float | None = None
    """The allocations in force over the window, weighted by time (None: not known; then
    ``allocated_hz``). The two differ when the allocation moved within the window."""

    def within_rate(self, *, floor_hz: float = 0.0) -> bool:
        """Delivered within ``RATE_TOLERANCE`` of what was allocated over the window.

        Judged against the allocations in force over the window, not only the last: a camera
        moved to q90 at 13.3 Hz for 0.6 s of a 1-s window and back to 16 Hz delivered 14.24 Hz
        (``dbml demo teleop --frames photos``, after its ladder's probe), all it was allowed.
        """
        allocated = self.allocated_hz if self.allocated_mean_hz is None else self.allocated_mean_hz
        if not allocated or not self.allocated_hz:
            return False
        tolerance = max(RATE_TOLERANCE * allocated, floor_hz)
        return abs(self.delivered_hz - allocated) <= tolerance

    def followed_rate(self, *, floor_hz: float = 0.0) -> bool:
        """Delivered between the window's mean allocation and its last, within tolerance.

        A rate that moved and came back within the window reached the publisher a reaction
        after the operator's ticks (every ``TICK_S``) saw it, which sample it: a camera moved
        from 16 Hz and back delivered 15.51 Hz where the ticks' mean was 14.36 (the photo demo,
        a fresh-clone CI run). Looser than :meth:`within_rate`: a publisher that did not follow
        a move that lasted (still at the rate before it, beyond both) fails.
        """
        last, mean = self.allocated_hz, self.allocated_mean_hz
        if mean is None or not last:
            return self.within_rate(floor_hz=floor_hz)
        low, high = min(mean, last), max(mean, last)
        tolerance = max(RATE_TOLERANCE * low, floor_hz)
        return low - tolerance <= self.delivered_hz <= high + tolerance


@dataclass(frozen=True, slots=True)
class StepResult:
    """One step: every robot's window and the budget and link at its end."""

    step: int
    robots: tuple[Window, ...]
    budget_mbit: float | None
    estimate_mbit: float | None
    link_mbit: float

    @property
    def goodput_mbit(self) -> float:
        """What all robots delivered."""
        return sum(r.goodput_mbit for r in self.robots)


@dataclass(frozen=True, slots=True)
class SeriesPoint:
    """The ``WINDOW_S`` ending ``t_s`` seconds after step 1 started."""

    t_s: float
    robots: tuple[Window, ...]
    budget_mbit: float | None
    estimator: str | None
    """The estimator's state as a line to read (``EstimatorState.text``)."""
    link_mbit: float

    @property
    def goodput_mbit(self) -> float:
        """What all robots delivered."""
        return sum(r.goodput_mbit for r in self.robots)


@dataclass(frozen=True, slots=True)
class LinkChange:
    """A change of the link's rate and how the system followed it."""

    t_s: float
    from_mbit: float
    to_mbit: float
    recovery_s: float | None = None
    """A drop: from when on every window had p95 < ``RECOVERED_P95_MS`` and no loss."""
    max_latency_p95_ms: float | None = None
    lost_after: int = 0
    budget_recovery_s: float | None = None
    """A rise: when the budget reached ``BUDGET_BACK_FRACTION`` of the new rate."""
    first_cut_s: float | None = None
    """A drop: when the budget first fell below the one in force before it (the estimator's
    decision time when its state carries one, else the operator's first tick that saw it)."""
    goodput_share_after: float | None = None
    """Goodput from ``GOODPUT_AFTER_S`` after the change to the next, as a share of the new
    rate (an over-cut shows here)."""

    @property
    def drop(self) -> bool:
        """Whether the link got slower."""
        return self.to_mbit < self.from_mbit


@dataclass(frozen=True, slots=True)
class LinkPhase:
    """Between two changes of the link rate, all robots together: RFC 8867's per-phase figures."""

    start_s: float
    end_s: float
    link_mbit: float
    goodput_mbit: float
    latency_p95_ms: float | None
    lost: int

    @property
    def utilisation(self) -> float:
        """Goodput as a share of the shaped rate (0 while the link is down)."""
        return self.goodput_mbit / self.link_mbit if self.link_mbit > 0 else 0.0


@dataclass(frozen=True, slots=True)
class Analysis:
    """Everything measured in one run."""

    steps: tuple[StepResult, ...] = ()
    series: tuple[SeriesPoint, ...] = ()
    changes: tuple[LinkChange, ...] = ()
    phases: tuple[LinkPhase, ...] = ()


@dataclass(frozen=True, slots=True)
class StreamLatency:
    """One stream's one-way latency over a whole run (the urgent stream beside the cameras)."""

    name: str
    received: int
    lost: int
    latency_p50_ms: float | None
    latency_p95_ms: float | None
    latency_max_ms: float | None


@dataclass(frozen=True, slots=True)
class Outage:
    """A link outage (0 Mbit in the schedule) and the restoration after it."""

    start_s: float
    end_s: float
    """When the link came back (seconds after step 1 started)."""
    urgent: str
    """The most urgent channel's robot when the link came back."""
    first_urgent_s: float | None
    """From the restoration to the urgent channel's first frame, stale or not."""
    first_fresh_urgent_s: float | None
    """...to its first frame sent after the restoration (not the backlog of the outage)."""
    stale: int
    """Frames sent before the restoration that arrived after it: the outage's backlog."""
    lost: int
    """Frames lost (sequence gaps) from the outage's start to ``OUTAGE_AFTER_S`` after it."""
    worst_window_mbit: float | None
    """The most any 1-s window carried in the ``OUTAGE_AFTER_S`` after the restoration: the
    wire, with the backlog sent before the link went down."""
    worst_sent_after_mbit: float | None
    """The same of frames sent after the restoration only: what the release sent."""
    budget_mbit: float | None
    """The largest budget in force in that time (None: nothing allocated, unmanaged)."""
    over_budget_mbit: float | None = None
    """How far the wire's worst window went over the budget in force over that window
    (negative: under it). Each window is judged against its own budget, the time-weighted mean
    of the budgets in force across it: a budget cut after the restoration must not be hidden
    by the larger one before it, nor a raise counted as excess."""
    release_over_budget_mbit: float | None = None
    """The same of what was sent after the restoration only: what the release sent."""


@dataclass(frozen=True, slots=True)
class Recovery:
    """One robot after one of its links came back from an outage."""

    robot: str
    scope: str
    """Whose link went down: ``"link"`` (the shared one, every robot's) or a robot's own."""
    down_s: float
    """When the link went down (seconds after step 1 started)."""
    back_s: float
    """When it came back."""
    recovery_s: float | None
    """From ``back_s`` to the start of the first 1-s window in which the robot delivered its
    allocation (None: not before its next outage or the run's end)."""
    stuck: bool
    """Not at its allocation in any window of the ``STUCK_WINDOW_S`` before its next outage or
    the run's end: at its fail-safe minimum, or silent."""

    def back_within(self, limit_s: float) -> bool:
        """Whether it delivered its allocation within ``limit_s`` and was not stuck after."""
        return self.recovery_s is not None and self.recovery_s <= limit_s and not self.stuck
