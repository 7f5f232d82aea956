"""``dbml demo teleop --frames photos``: the paper's experiment on real frames, ladder against none.

Both robots' cameras move over real photographs (``dbml.media.photos``) at the paper's
resolutions and send JPEG on ``[topic]/optimized/compressed``. The scenario runs twice on the
same frames: with the ladder (rate and quality chosen together) and rate only (every frame at
the one JPEG quality whose frames are the paper's 84,000 B). The operator decodes every JPEG
and scores it (SSIM against the frame that was sent); per step and robot the result holds the
rate allocated, the frames per second delivered, their SSIM and the rung, and each run's
utility (``dbml.core.quality.channel_utility`` of what the operator measured, with the same
weights and preferences for both). It passes when, with the ladder, both robots get 10 Hz or
more in every step, a prioritised camera its maximum rate, every 1-s window of what arrived
stays within the budget plus one frame, and the utility is 10 % or more above rate only's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from dbml.core.errors import DbmlError
from dbml.core.ladder import Preference
from dbml.core.priority import normalize_priorities
from dbml.core.quality import WEIGHT_BASE, channel_utility
from dbml.core.spec import mbit_to_bytes_per_s
from dbml.demo.layouts import layout_of
from dbml.experiment.analysis import RATE_TOLERANCE_HZ, StepResult, Window
from dbml.experiment.analysis.windows import settle_s
from dbml.experiment.runner import Observer, Recording, run_experiment
from dbml.experiment.spec import HOSTS, Frames, RoleSpec, transport_entry
from dbml.harness.sniffer import WindowStats, window_stats
from dbml.scenarios.teleop import LINK_MBIT, MAX_RATE_HZ, ROBOTS, STEPS
from dbml.transports.registry import TransportEntry
from dbml.view.target import ViewTarget

__all__ = [
    "MIN_FPS",
    "MIN_GAIN",
    "MIN_STEP_S",
    "PHOTO_TRANSPORTS",
    "PhotoDemoResult",
    "PhotoRobot",
    "PhotoRun",
    "PhotoStep",
    "check_photo_options",
    "mean_ssim",
    "photo_steps",
    "preference_of",
    "run_photo",
    "run_photo_demo",
]

MIN_FPS = 10.0
"""The paper's minimum for teleoperation (Chen, Haas and Barnes 2007, as section 4 reads it)."""
MIN_GAIN = 0.10
"""How far above rate only the ladder's utility must be."""
MIN_STEP_S = 1.0
"""The shortest step that still times a rate after ``settle_s``."""


def preference_of(priority: float) -> Preference:
    """What a robot asks to keep: its frame rate when an event raised its priority."""
    return Preference.KEEP_RATE if priority > 0 else Preference.BALANCED


@dataclass(frozen=True, slots=True)
class PhotoRobot:
    """One robot in one step: its event's priority and what the operator measured."""

    topic: str
    priority: float
    weight: float
    """``WEIGHT_BASE`` plus eq. 2's normalised priority: the utility's weight."""
    measured: Window

    @property
    def preference(self) -> Preference:
        """What the robot asked to keep in this step."""
        return preference_of(self.priority)

    @property
    def utility(self) -> float:
        """The utility of what arrived: its SSIM and its delivered frames per second."""
        return channel_utility(
            weight=self.weight,
            quality=self.measured.ssim or 0.0,
            rate_hz=self.measured.delivered_hz,
            max_rate_hz=MAX_RATE_HZ,
            preference=self.preference,
        )

    @property
    def at_least_min_fps(self) -> bool:
        """Allocated 10 Hz or more and delivered it (within the demo's tolerance)."""
        allocated = self.measured.allocated_hz or 0.0
        return allocated >= MIN_FPS and self.measured.followed_rate(floor_hz=RATE_TOLERANCE_HZ)

    @property
    def at_max_if_prioritised(self) -> bool:
        """A prioritised camera is allocated its maximum rate and delivers it."""
        if self.priority <= 0:
            return True
        allocated = self.measured.allocated_hz or 0.0
        return allocated >= MAX_RATE_HZ * (1 - 1e-6) and self.measured.followed_rate(
            floor_hz=RATE_TOLERANCE_HZ
        )


@dataclass(frozen=True, slots=True)
class PhotoStep:
    """One step of one run."""

    step: StepResult
    robots: tuple[PhotoRobot, ...]

    @property
    def utility(self) -> float:
        """The robots' utilities together."""
        return sum(r.utility for r in self.robots)


@dataclass(frozen=True, slots=True)
class PhotoRun:
    """One run on real frames: with the ladder, or rate only."""

    ladder: bool
    steps: tuple[PhotoStep, ...]
    wire: WindowStats
    """What arrived at the operator in sliding 1-s windows (from the first step's settling)."""
    limit_bytes: float
    """The budget a second plus the largest frame that arrived."""
    interrupted: bool = False

    @property
    def utility(self) -> float:
        """Every step's utility together."""
        return sum(s.utility for s in self.steps)

    @property
    def ceiling(self) -> float:
        """The utility of every camera at its maximum rate with SSIM 1: no allocation exceeds it."""
        return sum(r.weight for s in self.steps for r in s.robots)

    @property
    def within_budget(self) -> bool:
        """No 1-s window above the budget plus one frame."""
        return self.wire.windows > 0 and self.wire.worst_bytes <= self.limit_bytes

    @property
    def complete(self) -> bool:
        """Every step ran to its end."""
        return not self.interrupted and len(self.steps) == len(STEPS)


@dataclass(frozen=True, slots=True)
class PhotoDemoResult:
    """The two runs and the verdict."""

    transport: TransportEntry
    step_seconds: float
    ladder: PhotoRun
    rate_only: PhotoRun | None

    @property
    def gain(self) -> float | None:
        """The ladder's utility over rate only's, less one (None: rate only did not run)."""
        if self.rate_only is None or self.rate_only.utility <= 0:
            return None
        return self.ladder.utility / self.rate_only.utility - 1

    @property
    def gain_ceiling(self) -> float | None:
        """The most any allocation could gain over this run's rate only (``PhotoRun.ceiling``).

        Where both cameras fit at their maximum rate without the ladder, there is little left
        to gain: this says how much the 10 % target leaves possible in this run.
        """
        if self.rate_only is None or self.rate_only.utility <= 0:
            return None
        return self.ladder.ceiling / self.rate_only.utility - 1

    @property
    def checks(self) -> dict[str, bool]:
        """Each condition of the verdict, by name."""
        robots = [r for s in self.ladder.steps for r in s.robots]
        gain = self.gain
        return {
            "complete": self.ladder.complete
            and self.rate_only is not None
            and self.rate_only.complete,
            "every_robot_at_10_hz": bool(robots) and all(r.at_least_min_fps for r in robots),
            "prioritised_at_maximum": bool(robots) and all(r.at_max_if_prioritised for r in robots),
            "within_budget": self.ladder.within_budget,
            "utility_gain_10_percent": gain is not None and gain >= MIN_GAIN,
        }

    @property
    def ok(self) -> bool:
        """Every check held."""
        return all(self.checks.values())


def _weights(step_index: int) -> list[float]:
    """Each robot's weight in a step: eq. 2 on the events' priorities and the paper's sizes."""
    step = STEPS[step_index]
    priorities = [event.priority for event in step.events]
    normalized = normalize_priorities(priorities, [c.size_bytes for c in ROBOTS])
    return [WEIGHT_BASE + float(p) for p in normalized]


def photo_steps(results: Sequence[StepResult]) -> tuple[PhotoStep, ...]:
    """The paper's two robots in each step, with their events' weights: the utility's terms.

    Also how a testbed run on real frames is judged (``dbml testbed teleop --frames photos``).
    """
    steps = []
    for result in results[: len(STEPS)]:
        weights = _weights(result.step - 1)
        events = STEPS[result.step - 1].events
        steps.append(
            PhotoStep(
                result,
                tuple(
                    PhotoRobot(camera.topic, event.priority, weight, measured)
                    for camera, event, weight, measured in zip(
                        ROBOTS, events, weights, result.robots, strict=True
                    )
                ),
            )
        )
    return tuple(steps)


def _run(recording: Recording, *, step_s: float, ladder: bool) -> PhotoRun:
    budget_bytes = mbit_to_bytes_per_s(LINK_MBIT)
    if recording.t0 is None:
        return PhotoRun(ladder, (), WindowStats(0, 0, 0.0), budget_bytes, interrupted=True)
    analysis = recording.analyse(step_s=step_s, link_mbit=LINK_MBIT)
    steps = photo_steps(analysis.steps)
    start = recording.t0 + settle_s(step_s)
    arrived = [(a.arrival_s, a.size_bytes) for a in recording.arrivals if a.arrival_s >= start]
    largest = max((size for _, size in arrived), default=0)
    limit = budget_bytes + largest
    return PhotoRun(
        ladder,
        tuple(steps),
        window_stats(arrived, limit_bytes=limit),
        limit,
        recording.interrupted,
    )


PHOTO_TRANSPORTS = ("zenoh", "memory")
"""Where dbml's own operator decodes and scores the frames (the other layouts' operator is a
plain ROS 2 node or speaks ROS 1, where the CompressedImage variant is not carried yet)."""


def check_photo_options(
    *, transport: str, step_seconds: float, plot: bool = False
) -> TransportEntry:
    """The transport ``--frames photos`` runs over; ``DbmlError`` naming a flag it cannot take."""
    entry = transport_entry(transport)
    if entry.name not in PHOTO_TRANSPORTS:
        raise DbmlError(
            f"--transport={transport!r} with --frames photos: one of {', '.join(PHOTO_TRANSPORTS)}"
        )
    if not step_seconds >= MIN_STEP_S:
        raise DbmlError(f"--step-seconds={step_seconds!r} must be >= {MIN_STEP_S:g}")
    if plot:
        raise DbmlError("--frames photos does not take --plot yet: its table has every figure")
    return entry


def run_photo(
    transport: TransportEntry,
    *,
    step_seconds: float,
    ladder: bool,
    observe: Observer | None = None,
    view: ViewTarget | None = None,
) -> PhotoRun:
    """One run of the scenario on real frames, with the ladder or rate only.

    ``view``: the operator's live view (``--foxglove``/``--record``), the JPEG it receives in
    its image panels.
    """
    layout = layout_of(transport)
    layout.check()
    specs = {
        role: RoleSpec(
            step_s=step_seconds,
            transport=transport,
            host=host,
            frames=Frames.PHOTOS,
            ladder=ladder,
        )
        for role, host in HOSTS.items()
    }
    if view is not None:
        specs["operator"] = replace(
            specs["operator"], foxglove=view.foxglove_flag, record=view.record_flag
        )
    with contextlib.ExitStack() as run:
        plan = layout.plan(specs, transport, run)
        recording = run_experiment(plan, what="demo", observe=observe)
    return _run(recording, step_s=step_seconds, ladder=ladder)


def run_photo_demo(
    transport: TransportEntry,
    *,
    step_seconds: float,
    observe: Callable[[bool], Observer | None] = lambda _ladder: None,
) -> PhotoDemoResult:
    """Both runs, the ladder's first; rate only is skipped when the first was interrupted.

    ``observe(ladder)``: what sees each run's reports (a live view per run).
    """
    first = run_photo(transport, step_seconds=step_seconds, ladder=True, observe=observe(True))
    second = None
    if not first.interrupted:
        second = run_photo(
            transport, step_seconds=step_seconds, ladder=False, observe=observe(False)
        )
    return PhotoDemoResult(transport, step_seconds, first, second)


def mean_ssim(run: PhotoRun, robot: int) -> float | None:
    """A robot's SSIM over the run's steps (None: none scored)."""
    scores = [s.robots[robot].measured.ssim for s in run.steps]
    known = [s for s in scores if s is not None]
    return float(np.mean(known)) if known else None
