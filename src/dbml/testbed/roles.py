"""The testbed's processes: one per role, each inside its own network namespace.

``python -m dbml.testbed.roles ROLE SPEC_JSON`` opens a zenoh session on the explicit endpoints in
the spec (shared memory off, so every byte crosses the shaped link), prints
``{"type": "ready"}``, waits for ``start <t0>`` on stdin and runs the scenario:

- ``r1``/``r2``: a robot publishing its camera's synthetic frames. Under ``dbml`` and ``static``
  through a managed publisher whose priority follows Table 2's events (the same code as
  ``dbml demo teleop``); under ``unmanaged`` through a plain publisher at 16 Hz, as without dbml.
- ``optimizer``: the optimizer node on the operator's side (``dbml`` or ``static`` only), with the
  link budget, the uplinks as links, and the estimator when asked for.
- ``operator``: receives both cameras and prints every frame (robot, sequence number, send and
  arrival time, size) and the parameters in force, in batches of JSON lines, for the runner to
  analyse. The namespaces share one clock, so arrival minus send time is the one-way latency.

It ends at the last step, on ``stop``, on stdin EOF, SIGINT or SIGTERM.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

from dbml.core.allocation import Strategy
from dbml.core.config import DbmSettings
from dbml.core.errors import TransportError
from dbml.core.spec import LinkSpec
from dbml.runtime.nodes import run_optimizer, stop_on_signals
from dbml.runtime import names
from dbml.runtime.metadata import MessageMeta, pack_meta
from dbml.runtime.rate import Rate
from dbml.runtime.reception import ReceptionReporter
from dbml.runtime.subscriber import ManagedSubscriber
from dbml.demo.roles import robot_role
from dbml.harness.processes import Emit, emit_json, serve_role
from dbml.scenarios.teleop import MAX_RATE_HZ, ROBOTS, STEPS
from dbml.transports.base import Handle, Sample, Transport, Variant, param_number
from dbml.transports.zenoh import ZenohTransport

__all__ = ["ROLES", "RoleSpec", "main"]

log = logging.getLogger("dbml.testbed")

ROLES = ("operator", "optimizer", "r1", "r2")
REPORT_INTERVAL_S = 0.2
TAIL_S = 1.0
"""The operator keeps receiving this long after the last step, for frames still in flight."""


@dataclass(frozen=True, slots=True, kw_only=True)
class RoleSpec:
    """Everything a role process needs, passed as one JSON argument."""

    policy: str
    step_s: float
    link_mbit: float
    utilization: float
    strategy: str
    estimate: bool
    uplinks_mbit: dict[str, float] = field(default_factory=dict)
    host: str
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> RoleSpec:
        return cls(**json.loads(text))

    @property
    def duration_s(self) -> float:
        return len(STEPS) * self.step_s


def _wait_until(wall_s: float, stop: threading.Event) -> bool:
    return not stop.wait(max(0.0, wall_s - time.time()))


def _unmanaged_robot(
    transport: Transport, index: int, t0: float, spec: RoleSpec, stop: threading.Event
) -> None:
    """What a robot does without dbml: publish every frame at the camera's maximum rate."""
    camera = ROBOTS[index]
    publisher = transport.declare_publisher(camera.topic, Variant.FULL)
    frame = bytes(camera.size_bytes)
    rate = Rate(lambda: MAX_RATE_HZ)
    seq = 0
    try:
        _wait_until(t0, stop)
        rate.reset()
        while not stop.is_set() and time.time() < t0 + spec.duration_s:
            rate.sleep()
            publisher.put(frame, pack_meta(seq, time.time_ns(), MAX_RATE_HZ))
            seq += 1
    finally:
        publisher.close()


def _optimizer(transport: Transport, t0: float, spec: RoleSpec, stop: threading.Event) -> None:
    settings = DbmSettings(spec.link_mbit, spec.utilization, 1.0, Strategy(spec.strategy))
    topics = {camera.robot: camera.topic for camera in ROBOTS}
    links = tuple(
        LinkSpec(f"uplink-{robot}", mbit, (topics[robot],))
        for robot, mbit in sorted(spec.uplinks_mbit.items())
    )
    run_optimizer(
        transport,
        settings=settings,
        links=links,
        stop=stop,
        duration_s=t0 + spec.duration_s + TAIL_S - time.time(),
        estimate=spec.estimate,
    )


def _operator(
    transport: Transport, t0: float, spec: RoleSpec, stop: threading.Event, emit: Emit
) -> None:
    lock = threading.Lock()
    frames: list[list[float]] = []

    def receiver(index: int) -> Any:
        def on_sample(sample: Sample) -> None:
            arrival = time.time()
            try:
                meta = MessageMeta.decode(sample.attachment)
            except TransportError:
                return  # not a dbml publisher
            row = [index, meta.seq, meta.sent_ns / 1e9, arrival, len(sample.payload), meta.rate_hz]
            with lock:
                frames.append(row)

        return on_sample

    handles: list[Handle | ManagedSubscriber] = []
    reporter: ReceptionReporter | None = None
    if spec.policy == "unmanaged":
        for i, camera in enumerate(ROBOTS):
            handles.append(transport.subscribe(camera.topic, receiver(i), Variant.FULL))
    else:
        reporter = ReceptionReporter(transport).start()  # for the estimator, if one runs
        for i, camera in enumerate(ROBOTS):
            handles.append(
                ManagedSubscriber(transport, camera.topic, receiver(i), reporter=reporter)
            )

    def params() -> dict[str, Any]:
        store = transport.params
        estimate = param_number(store.get(names.ESTIMATE))
        bandwidth = param_number(store.get(names.BANDWIDTH))
        utilization = param_number(store.get(names.UTILIZATION)) or 1.0
        budget = estimate  # an estimate is the budget in use; else bandwidth x utilization
        if budget is None and bandwidth is not None:
            budget = bandwidth * utilization
        state = store.get(names.ESTIMATOR_STATE)
        return {
            "allocated_hz": [param_number(store.get(names.current_value(c.topic))) for c in ROBOTS],
            "budget_mbit": budget,
            "estimate_mbit": estimate,
            "estimator": state if isinstance(state, str) else None,
        }

    try:
        end = t0 + spec.duration_s + TAIL_S
        while not stop.is_set() and time.time() < end:
            stop.wait(REPORT_INTERVAL_S)
            with lock:
                batch, frames[:] = list(frames), []
            emit({"type": "tick", "t": time.time(), "frames": batch, **params()})
        emit({"type": "done"})
    finally:
        for handle in handles:
            handle.close()
        if reporter is not None:
            reporter.close()


def _run_role(
    role: str, transport: Transport, *, t0: float, spec: RoleSpec, stop: threading.Event, emit: Emit
) -> None:
    if role == "operator":
        _operator(transport, t0, spec, stop, emit)
    elif role == "optimizer":
        _optimizer(transport, t0, spec, stop)
    elif spec.policy == "unmanaged":
        _unmanaged_robot(transport, ROLES.index(role) - 2, t0, spec, stop)
    else:
        robot_role(transport, ROLES.index(role) - 2, t0, spec.step_s, stop)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2 or args[0] not in ROLES:
        sys.stderr.write(f"usage: python -m dbml.testbed.roles {{{','.join(ROLES)}}} SPEC_JSON\n")
        return 2
    role, spec = args[0], RoleSpec.from_json(args[1])
    logging.basicConfig(level=logging.WARNING, format=f"{role}: %(name)s: %(message)s")

    with stop_on_signals() as stop:
        transport = ZenohTransport(host=spec.host, listen=spec.listen, connect=spec.connect)
        try:
            transport.wait_for_peers(15.0)
            serve_role(
                role,
                stop,
                lambda t0: _run_role(role, transport, t0=t0, spec=spec, stop=stop, emit=emit_json),
            )
        finally:
            transport.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
