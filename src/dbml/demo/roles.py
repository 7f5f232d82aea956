"""The paper's teleoperation scenario, live: optimizer, two robots and an operator.

Over zenoh or ROS 1 each role is its own OS process with its own host identity (over ROS 1, its
own ROS_IP); over the memory transport they are threads of one process. The robots publish
synthetic 84,000 / 21,000 byte frames (over ROS 1, ``sensor_msgs/Image`` messages of that size)
and set their camera priority from Table 2's replayed distance and speed at every
step (eq. 6-7); the operator receives through managed subscribers and measures what arrives.

Process protocol (``python -m dbml.demo.roles ROLE``): the role prints ``{"type": "ready"}``, waits
for ``start <t0>`` on stdin (wall-clock seconds of step 1), runs, and ends at the last step, on
``stop``, on stdin EOF, SIGINT or SIGTERM. The operator prints JSON lines: ``status`` several
times a second, one ``step`` per step and ``done``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from dbml.core.allocation import Strategy
from dbml.core.config import DbmSettings
from dbml.runtime.nodes import stop_on_signals
from dbml.runtime import names
from dbml.runtime.metadata import MessageMeta
from dbml.runtime.optimizer import OptimizerNode
from dbml.runtime.priority import collision_priority_source
from dbml.runtime.publisher import ManagedPublisher
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.harness.processes import Emit, emit_json, serve_role
from dbml.scenarios.teleop import LINK_MBIT, MAX_RATE_HZ, MIN_RATE_HZ, ROBOTS, STEPS
from dbml.transports.base import Sample, Transport
from dbml.transports.registry import open_transport

__all__ = ["ROLES", "Arrivals", "operator_role", "optimizer_role", "robot_role"]

log = logging.getLogger("dbml.demo")

STATUS_INTERVAL_S = 0.25


def settle_s(step_s: float) -> float:
    """Time after a step starts before its rate is measured: the change has to take effect
    (one old period at worst, 1 s at the 1 Hz minimum)."""
    return min(1.0, step_s / 3)


def _wait_until(wall_s: float, stop: threading.Event) -> bool:
    """Sleep until a wall-clock time; False if stopped first."""
    return not stop.wait(max(0.0, wall_s - time.time()))


def optimizer_role(transport: Transport, t0: float, step_s: float, stop: threading.Event) -> None:
    settings = DbmSettings(LINK_MBIT, 1.0, 1.0, Strategy.PAPER)
    node = OptimizerNode(transport, settings=settings).start()
    try:
        _wait_until(t0 + len(STEPS) * step_s + 1.0, stop)
    finally:
        node.stop()


def robot_role(
    transport: Transport, index: int, t0: float, step_s: float, stop: threading.Event
) -> None:
    camera = ROBOTS[index]
    publisher = ManagedPublisher(
        transport, camera.topic, min_rate_hz=MIN_RATE_HZ, max_rate_hz=MAX_RATE_HZ
    )

    camera_priority = collision_priority_source(transport, camera.topic)
    frame = transport.camera_frame(camera.topic, camera.size_bytes)

    # The robot's own end, not ``stop``: over the memory transport every role shares ``stop``,
    # and a robot done with its last frame must not end the operator before its last report.
    finished = threading.Event()

    def replay_events() -> None:
        for k, step in enumerate(STEPS):
            if not _wait_until(t0 + k * step_s, finished) or stop.is_set():
                return
            event = step.events[index]
            camera_priority.update(event.distance_m, event.speed_m_per_s)

    events = threading.Thread(target=replay_events, name=f"events-{camera.robot}", daemon=True)
    end = t0 + len(STEPS) * step_s
    try:
        publisher.publish(frame)  # the first frame makes the size known before step 1
        events.start()
        _wait_until(t0, stop)
        publisher.rate.reset()
        while not stop.is_set() and time.time() < end:
            publisher.rate.sleep()
            publisher.publish(frame)
    finally:
        finished.set()
        events.join(timeout=2)
        publisher.close()


@dataclass
class Arrivals:
    """Arrival times (wall clock) and metadata of one robot's frames at the operator."""

    times: list[float] = field(default_factory=list)
    seqs: list[int] = field(default_factory=list)
    sizes: list[int] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, sample: Sample) -> None:
        now = time.time()
        seq = MessageMeta.decode(sample.attachment).seq if sample.attachment else -1
        with self.lock:
            self.times.append(now)
            self.seqs.append(seq)
            self.sizes.append(len(sample.payload))

    def rate_between(self, start: float, end: float) -> float | None:
        """Messages per second from inter-arrival times of frames received in [start, end]."""
        with self.lock:
            gaps = [
                b - a for a, b in zip(self.times, self.times[1:], strict=False) if start <= b <= end
            ]
        return len(gaps) / sum(gaps) if gaps and sum(gaps) > 0 else None


def operator_role(
    transport: Transport, t0: float, step_s: float, stop: threading.Event, emit: Emit
) -> None:
    arrivals = [Arrivals() for _ in ROBOTS]
    subscribers = [
        ManagedSubscriber(transport, camera.topic, arrivals[i].add)
        for i, camera in enumerate(ROBOTS)
    ]

    def allocated(topic: str) -> float | None:
        value = transport.params.get(names.current_value(topic))
        return float(value) if isinstance(value, int | float) else None

    try:
        _wait_until(t0, stop)
        step = 0
        while step < len(STEPS) and not stop.is_set():
            start, end = t0 + step * step_s, t0 + (step + 1) * step_s
            now = time.time()
            if now >= end:
                robots = []
                for i, camera in enumerate(ROBOTS):
                    event = STEPS[step].events[i]
                    measured = arrivals[i].rate_between(start + settle_s(step_s), end)
                    robots.append(
                        {
                            "robot": camera.robot,
                            "topic": camera.topic,
                            "tc_s": None if event.tc_s == float("inf") else event.tc_s,
                            "priority": event.priority,
                            "allocated_hz": allocated(camera.topic),
                            "measured_hz": measured,
                            "variant": subscribers[i].variant.value,
                        }
                    )
                emit({"type": "step", "step": step + 1, "robots": robots})
                step += 1
                continue
            robots_now: list[dict[str, Any]] = []
            status = {"type": "status", "t": now - t0, "step": step + 1, "robots": robots_now}
            for i, camera in enumerate(ROBOTS):
                # inter-arrival rate over the last two seconds: smoother than a count
                rate = arrivals[i].rate_between(now - 2.0, now) or 0.0
                robots_now.append(
                    {
                        "robot": camera.robot,
                        "allocated_hz": allocated(camera.topic),
                        "measured_hz": rate,
                        "bytes_per_s": rate * camera.size_bytes,
                    }
                )
            emit(status)
            stop.wait(min(STATUS_INTERVAL_S, max(0.0, end - time.time())))
        emit({"type": "done"})
    finally:
        for subscriber in subscribers:
            subscriber.close()


ROLES = ("optimizer", "r1", "r2", "operator")


def run_role(
    role: str,
    transport: Transport,
    *,
    t0: float,
    step_s: float,
    stop: threading.Event,
    emit: Emit,
) -> None:
    if role == "optimizer":
        optimizer_role(transport, t0, step_s, stop)
    elif role in ("r1", "r2"):
        robot_role(transport, ROLES.index(role) - 1, t0, step_s, stop)
    elif role == "operator":
        operator_role(transport, t0, step_s, stop, emit)
    else:
        raise ValueError(f"role={role!r} is not one of {ROLES}")


def _main(argv: list[str] | None = None) -> int:
    """One role as an OS process, driven over stdin/stdout by ``dbml demo teleop``."""
    parser = argparse.ArgumentParser(prog="python -m dbml.demo.roles")
    parser.add_argument("role", choices=ROLES)
    parser.add_argument("--step-seconds", type=float, required=True)
    parser.add_argument("--host", help="zenoh host identity (ROS 1 takes ROS_IP/ROS_HOSTNAME)")
    parser.add_argument("--transport", choices=["zenoh", "ros1"], default="zenoh")
    args = parser.parse_args(argv)

    with stop_on_signals() as stop:
        transport: Transport
        if args.transport == "ros1":
            from dbml.transports.ros1 import Ros1Transport

            transport = Ros1Transport(node_name=f"dbml_{args.role}")
        else:
            transport = open_transport("zenoh", host=args.host)
        # After the node starts: rospy replaces the root handlers with its own log file.
        logging.basicConfig(
            force=True, level=logging.WARNING, format=f"{args.role}: %(name)s: %(message)s"
        )
        try:
            wait = getattr(transport, "wait_for_peers", None)
            if wait is not None:
                wait(10.0)
            serve_role(
                args.role,
                stop,
                lambda t0: run_role(
                    args.role, transport, t0=t0, step_s=args.step_seconds, stop=stop, emit=emit_json
                ),
            )
        finally:
            transport.close()
    return 0


if __name__ == "__main__":
    sys.exit(_main())
