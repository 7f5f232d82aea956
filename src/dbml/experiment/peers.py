"""What the plain ROS 2 peers share, whichever ROS 2 they speak (zenoh-ros2-sdk or rclpy).

The demo and the testbed play the robots' cameras and the operator with plain ROS 2 nodes (no
dbml in their data path: ``ros2peers`` over rmw_zenoh's wire format, ``rclpypeers`` over rclpy),
so dbml is shown managing topics whose publishers and subscribers know nothing of it. Both kinds
share: the topics and types, the camera's pacing, the priorities a camera publishes (Table 2's
events, eq. 6-7, republished so a late bridge hears them), the operator's record of each frame
and its reports in ``roles``' format, so the same runner and analysis judge every run.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

from dbml.core.errors import DbmlError
from dbml.core.priority import collision_priority, time_to_collision_s
from dbml.experiment.analysis import Arrival
from dbml.experiment.operator import operator_tick
from dbml.experiment.spec import TAIL_S, TICK_S, RoleSpec, wait_until
from dbml.harness.child import Emit, emit_json
from dbml.runtime.params import ParamView
from dbml.runtime.serve import Lifetime
from dbml.scenarios.teleop import ROBOTS, STEPS, RobotCamera, Step
from dbml.transports.base import PRIORITY_SUFFIX, Variant

__all__ = [
    "FIRST_FRAMES_TIMEOUT_S",
    "FLOAT64_TYPE",
    "IMAGE_TYPE",
    "OPTIMIZED_SUFFIX",
    "PRIORITY_REPEAT_S",
    "PRIORITY_SUFFIX",
    "FrameRecorder",
    "peer_roles",
    "replay_priorities",
    "report_ticks",
    "run_paced",
    "step_priority",
    "wait_first_frames",
]

IMAGE_TYPE = "sensor_msgs/msg/Image"
FLOAT64_TYPE = "std_msgs/msg/Float64"
OPTIMIZED_SUFFIX = Variant.OPTIMIZED.key("")
"""A managed topic's copy at the allocated rate: what a ROS 2 operator subscribes to."""
PRIORITY_REPEAT_S = 1.0
"""Each priority is published again this often: a ROS 2 topic keeps no value for latecomers."""
FIRST_FRAMES_TIMEOUT_S = 50.0
"""How long the operator waits for a frame of every managed camera before it reports ready
(the runner waits 60 s for every role)."""
_FIRST_FRAMES_POLL_S = 0.05


def peer_roles(cameras: Sequence[RobotCamera] = ROBOTS) -> tuple[str, ...]:
    """The roles plain ROS 2 peers play: the operator and the robots (the optimizer is dbml's)."""
    return ("operator", *(camera.robot.lower() for camera in cameras))


def step_priority(step: Step, index: int) -> float:
    """Robot ``index``'s camera priority in ``step``: eq. 6-7 of its distance and speed.

    The same pure functions as the managed robot's ``collision_priority_source``, published on
    a ROS 2 topic instead of written as a parameter.
    """
    event = step.events[index]
    return collision_priority(time_to_collision_s(event.distance_m, event.speed_m_per_s))


def run_paced(send: Callable[[], None], *, rate_hz: float, stop: threading.Event) -> None:
    """``send()`` every ``1 / rate_hz`` s until ``stop``, as a camera driver: never a burst.

    Paced on an absolute schedule (no drift); a send late by more than a period is not caught up.
    """
    period_s = 1.0 / rate_hz
    next_s = time.monotonic()
    while not stop.is_set():
        send()
        next_s += period_s
        now = time.monotonic()
        next_s = max(next_s, now - period_s)  # late by more than a frame: do not catch up
        stop.wait(max(0.0, next_s - now))


def replay_priorities(
    send: Callable[[float], None],
    index: int,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    steps: Sequence[Step] = STEPS,
) -> None:
    """``send`` the priority of each step from its start, again every ``PRIORITY_REPEAT_S``.

    Robot ``index``'s of ``steps`` (Table 2's, or a fleet's: ``fleet_steps``), until the last
    step, ``stop``, or a dbml thread's death (``life``).
    """
    if not wait_until(t0, stop):
        return
    while not life.over():
        now = time.time()
        k = int((now - t0) // spec.step_s)
        if k >= len(steps):
            return
        send(step_priority(steps[k], index))
        if not wait_until(min(t0 + (k + 1) * spec.step_s, now + PRIORITY_REPEAT_S), stop):
            return


class FrameRecorder:
    """An operator's record of each frame: robot, count, send and arrival time, size.

    Fed from subscription callbacks (any thread), read by the tick loop.
    """

    def __init__(self, robots: int = len(ROBOTS)) -> None:
        self._lock = threading.Lock()
        self._rows: list[Arrival] = []
        self._counts = [0 for _ in range(robots)]

    def record(
        self,
        index: int,
        *,
        arrival_s: float,
        sent_s: float | None,
        size_bytes: int,
        seq: int | None = None,
        rate_hz: float | None = None,
    ) -> None:
        """One frame of robot ``index``.

        ``seq`` None: the per-topic count from 0. ``rate_hz``: the rate the frame says it was
        sent at, None for a plain ROS 2 message of a managed channel (it carries none).
        """
        with self._lock:
            count = self._counts[index]
            self._counts[index] += 1
            self._rows.append(
                Arrival(
                    robot=index,
                    seq=count if seq is None else seq,
                    sent_s=sent_s,
                    arrival_s=arrival_s,
                    size_bytes=size_bytes,
                    rate_hz=rate_hz,
                )
            )

    def counts(self) -> list[int]:
        """Frames received so far, per robot."""
        with self._lock:
            return list(self._counts)

    def take(self) -> list[Arrival]:
        """The frames since the last call."""
        with self._lock:
            rows, self._rows = self._rows, []
        return rows


def wait_first_frames(
    recorder: FrameRecorder, topics: Sequence[str], stop: threading.Event
) -> None:
    """Return once every topic delivered a frame; raise naming those that did not."""
    deadline = time.monotonic() + FIRST_FRAMES_TIMEOUT_S
    while not all(recorder.counts()) and time.monotonic() < deadline and not stop.is_set():
        stop.wait(_FIRST_FRAMES_POLL_S)
    missing = [t for t, n in zip(topics, recorder.counts(), strict=True) if n == 0]
    if missing and not stop.is_set():
        raise DbmlError(
            f"operator: no frame on {', '.join(missing)} within {FIRST_FRAMES_TIMEOUT_S:g} s "
            "(are the bridges and the robots running?)"
        )


def report_ticks(
    view: ParamView,
    recorder: FrameRecorder,
    t0: float,
    spec: RoleSpec,
    stop: threading.Event,
    *,
    life: Lifetime,
    cameras: Sequence[RobotCamera] = ROBOTS,
    variant: Variant = Variant.OPTIMIZED,
    emit: Emit = emit_json,
) -> None:
    """The operator's run: a report every ``TICK_S`` in ``roles``' format, then ``done``.

    Every subscription is of ``variant`` of each of ``cameras`` (by default the optimized copy
    of Table 2's); a run that lost a thread is not done (the runner fails it).
    """
    variants = [variant.value for _ in cameras]
    while not life.over() and time.time() < t0 + spec.duration_s + TAIL_S:
        stop.wait(TICK_S)
        emit(operator_tick(view, recorder.take(), variants, cameras=cameras).encode())
    if not life.failed:
        emit({"type": "done"})
