"""Reaction time: a priority change to the publisher running at the new rate, across processes.

An optimizer, two managed publishers (Table 2's cameras: /r1/camera 84,000 B on robot1,
/r2/camera 21,000 B on robot2, 1-16 Hz, 11 Mbit/s) and a remote subscriber to each (host
operator) run as separate ``python -m dbml`` processes on a private loopback zenoh mesh. The
optimizer's period is 60 s, so only its event trigger can explain a fast reaction. This process
flips ``/r1/camera/dbm/priority`` between 1 and 0 (R1 16 Hz with R2 1.48 Hz, then R1 12.37 Hz
with R2 16 Hz) and times each flip, from the ``set`` to the arrival of
``/r1/camera/dbm/frequency/applied_value`` at the new rate: that parameter is written by R1's
publisher process once it applies the rate, so each sample is change -> optimizer process ->
publisher process -> back here. A flip not acknowledged within the timeout is a miss. Reference:
the paper's fixed 1 s optimisation period, which reacts within up to 1000 ms. Prints JSON with
``--json``, a table then the JSON otherwise.

``--transport rclpy`` runs the same processes over real ROS 2 (rclpy, Fast DDS) in a ROS 2
domain claimed for the run, their logs in a temporary directory. The change is then made the
ROS 2 way: a ``SetParameters`` call on the node ``/r1/camera/dbm`` that R1's publisher process
hosts, from a plain rclpy node of this process, exactly what ``ros2 param set /r1/camera/dbm
priority 1.0`` sends (``--setter dbml``: through this process's ``params.set``, as ``dbml
priority`` does, which makes the same call). The timer starts before the request is sent; the
acknowledgement is R1's ``frequency.applied_value`` changing on that node, heard through
``/parameter_events``. The service's own round trip (request to response) is reported beside it.

``--foxglove`` measures the same series twice in one run: first without the live view (the
reference), then with the optimizer serving it (``dbml optimizer --foxglove PORT --record
FILE``) to a Foxglove client of this process that subscribes to every channel, as the app does.
Both documents are printed, with the view's cost: the difference of the percentiles, and what
the optimizer process said its view spent per look.

    python bench/reaction.py [--json] [--changes 200] [--transport zenoh|rclpy] [--setter ros2|dbml]
                             [--foxglove]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from dbml import ChannelSpec, Problem, allocate
from dbml.harness.ros2env import (
    claim_domain,
    fastdds_shm_files,
    remove_fastdds_shm,
    ros2_child_env,
)
from dbml.protocol import names
from dbml.transports.base import ParamValue, Transport
from dbml.transports.zenoh import ZenohTransport
from dbml.view.client import FoxgloveClient
from nodes import Nodes

R1, R2 = "/r1/camera", "/r2/camera"
CAMERAS = ((R1, 84_000, "robot1"), (R2, 21_000, "robot2"))
MIN_HZ, MAX_HZ = 1.0, 16.0
BUDGET_MBIT = 11.0
PERIOD_S = 60
PRIORITIES = (1.0, 0.0)
"""Alternated, starting from 0: each flip changes R1's allocated rate (and R2's)."""
TIMEOUT_S = 2.0
"""Per change: longer than this without R1's acknowledgement is a miss."""
READY_S = 30.0
"""Processes started until both channels are managed and allocated."""
MEASURE_S = 30.0
"""Wall-clock bound on the whole series of changes."""
STOP_S = 10.0
SERVICE_S = 10.0
"""rclpy: how long the bench waits for R1's parameter node to answer before the first set."""
REFERENCE = "the paper's fixed 1 s optimisation period (up to 1000 ms)"
TRANSPORTS = ("zenoh", "rclpy")
SETTERS = ("ros2", "dbml")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def expected_rates(priority: float) -> dict[str, float]:
    """What the optimizer must allocate with R1 at ``priority`` and R2 at 0 (Table 2's logic)."""
    problem = Problem(
        tuple(
            ChannelSpec(topic, MIN_HZ, MAX_HZ, float(size), priority if topic == R1 else 0.0)
            for topic, size, _ in CAMERAS
        ),
        bandwidth_mbit=BUDGET_MBIT,
    )
    return allocate(problem, strategy="paper").rates_by_topic()


def same_rate(value: ParamValue, rate: float) -> bool:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    return math.isclose(value, rate, rel_tol=1e-9, abs_tol=1e-12)


class Probe:
    """Wakes waiters on every parameter change; stamps the arrival of R1's awaited ack."""

    def __init__(self, transport: Transport) -> None:
        self._params = transport.params
        self._cond = threading.Condition()
        self._awaited: float | None = None
        self._arrived: float | None = None
        self._handle = transport.params.watch(self._on_param)

    def _on_param(self, name: str, value: ParamValue) -> None:
        now = time.perf_counter()
        with self._cond:
            if (
                name == names.applied(R1)
                and self._awaited is not None
                and self._arrived is None
                and same_rate(value, self._awaited)
            ):
                self._arrived = now
            self._cond.notify_all()

    def arm(self, rate_hz: float) -> None:
        with self._cond:
            self._awaited, self._arrived = rate_hz, None

    def arrival(self, timeout_s: float) -> float | None:
        """When R1's publisher acknowledged the armed rate (perf_counter), None on timeout."""
        with self._cond:
            self._cond.wait_for(lambda: self._arrived is not None, timeout=timeout_s)
            return self._arrived

    def wait_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        with self._cond:
            return bool(self._cond.wait_for(predicate, timeout=timeout_s))

    def settled(self, rates: dict[str, float]) -> bool:
        """Both channels managed, allocated ``rates`` and acknowledged by their publishers."""
        get = self._params.get
        return all(
            get(names.managed(topic)) is True
            and same_rate(get(names.current_value(topic)), rate)
            and same_rate(get(names.applied(topic)), rate)
            for topic, rate in rates.items()
        )

    def close(self) -> None:
        self._handle.close()


def start_fleet(fleet: Nodes, config: Path, view: tuple[str, ...] = ()) -> None:
    fleet.start("optimizer", "optimizer", "--config", str(config), "--host", "base", *view)
    for topic, size, host in CAMERAS:
        fleet.start(
            f"publish-{host}",
            "publish",
            topic,
            "--size-bytes",
            str(size),
            "--min-hz",
            f"{MIN_HZ:g}",
            "--max-hz",
            f"{MAX_HZ:g}",
            "--host",
            host,
        )
        fleet.start(f"subscribe-{host}", "subscribe", topic, "--host", "operator")


class Ros2Setter:
    """What ``ros2 param set [topic]/dbm priority V`` does, from a plain rclpy node of its own.

    One ``SetParameters`` request per change to the channel's parameter node (hosted by the
    publisher's process); the responses are checked and timed on the node's executor thread.
    """

    def __init__(self, domain_id: int) -> None:
        from rcl_interfaces.srv import SetParameters

        from dbml.harness.ros2node import PrivateRos
        from dbml.transports.rclpy.nodes import node_of

        self._request_type = SetParameters.Request
        _parameter, node_name, self._ros2_name = node_of(names.priority(R1))
        self._ros = PrivateRos(domain_id=domain_id, name="param-set")
        try:
            node = self._ros.node("bench_param_set")
            self._client: Any = node.create_client(SetParameters, f"{node_name}/set_parameters")
        except BaseException:
            self._ros.close()
            raise
        self._lock = threading.Lock()
        self.round_trips_ms: list[float] = []
        self.refused: list[str] = []
        self.unanswered = 0
        self._ros.start()

    def wait_for_service(self, timeout_s: float) -> bool:
        return bool(self._client.wait_for_service(timeout_sec=timeout_s))

    def set(self, value: float) -> None:
        from rclpy.parameter import Parameter

        request = self._request_type(
            parameters=[Parameter(self._ros2_name, value=float(value)).to_parameter_msg()]
        )
        sent = time.perf_counter()
        future = self._client.call_async(request)
        future.add_done_callback(partial(self._answered, sent))

    def _answered(self, sent: float, future: Any) -> None:
        elapsed_ms = (time.perf_counter() - sent) * 1e3
        response = future.result()
        with self._lock:
            if response is None:
                self.unanswered += 1
                return
            self.round_trips_ms.append(elapsed_ms)
            self.refused += [r.reason for r in response.results if not r.successful]

    def close(self) -> None:
        self._ros.close()


@dataclass
class Network:
    """One run's network: this process's transport, the children's environment and flags."""

    transport: Transport
    env: dict[str, str]
    transport_args: list[str]
    set_priority: Callable[[float], None]
    setter: str
    """How a change is made: ``dbml`` (``params.set``) or ``ros2`` (a ``SetParameters`` call)."""
    ros2: Ros2Setter | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@contextlib.contextmanager
def open_network(transport_name: str, setter: str, workdir: Path) -> Iterator[Network]:
    """The run's private network: a loopback zenoh mesh, or a claimed ROS 2 domain."""
    if transport_name == "zenoh":
        port = free_port()
        # This session first, so it holds the rendezvous for the whole run.
        transport = ZenohTransport(host="bench", port=port)
        try:
            yield Network(
                transport,
                dict(os.environ, DBML_ZENOH_PORT=str(port)),
                [],
                partial(transport.params.set, names.priority(R1)),
                "dbml",
            )
        finally:
            transport.close()
        return
    from dbml.transports.rclpy import RclpyTransport

    with claim_domain() as domain_id:
        env = ros2_child_env(domain_id=domain_id, log_dir=workdir / "ros-log")
        saved = dict(os.environ)
        os.environ.update(env)  # this process's rclpy: the same logs and discovery profile
        rclpy_transport: RclpyTransport | None = None
        ros2: Ros2Setter | None = None
        try:
            rclpy_transport = RclpyTransport(host="bench", domain_id=domain_id)
            if setter == "ros2":
                ros2 = Ros2Setter(domain_id)
                set_priority = ros2.set
            else:
                set_priority = partial(rclpy_transport.params.set, names.priority(R1))
            yield Network(
                rclpy_transport,
                env,
                ["--transport", "rclpy", "--domain-id", str(domain_id)],
                set_priority,
                setter,
                ros2,
                {"domain_id": domain_id},
            )
        finally:
            if ros2 is not None:
                ros2.close()
            if rclpy_transport is not None:
                rclpy_transport.close()
            os.environ.clear()
            os.environ.update(saved)


class Viewer:
    """A Foxglove client on its own thread, subscribed to every channel, counting messages."""

    def __init__(self, url: str) -> None:
        self._url = url
        self._stop = threading.Event()
        self.client: Any = None
        """The ``FoxgloveClient`` once connected."""
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name="viewer", daemon=True)
        self._thread.start()

    def _run(self) -> None:

        try:
            with FoxgloveClient(self._url, timeout_s=READY_S) as client:
                self.client = client
                client.pump(self._stop.is_set, timeout_s=MEASURE_S + 2 * READY_S)
        except Exception as err:  # said in the document, not a dead bench
            self.error = repr(err)

    def counts(self) -> dict[str, int]:
        client = self.client
        if client is None:
            return {}
        return {topic: len(messages) for topic, messages in dict(client.messages).items()}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=STOP_S)


VIEW_COST = re.compile(r"live view: (\d+) looks, ([0-9.]+) ms mean, ([0-9.]+) ms max per look")


def view_cost(log_text: str) -> dict[str, float] | None:
    """What the optimizer's view said it spent per look (at its close)."""
    found = VIEW_COST.findall(log_text)
    if not found:
        return None
    looks, mean_ms, max_ms = found[-1]
    return {"looks": int(looks), "mean_ms": float(mean_ms), "max_ms": float(max_ms)}


def measure(
    changes: int, transport_name: str = "zenoh", setter: str = "ros2", *, foxglove: bool = False
) -> dict[str, Any]:
    table = {p: expected_rates(p) for p in PRIORITIES}
    if same_rate(table[PRIORITIES[0]][R1], table[PRIORITIES[1]][R1]):
        raise SystemExit("the priorities chosen do not change R1's rate")
    with (
        tempfile.TemporaryDirectory(prefix="dbml-reaction-") as tmp,
        open_network(transport_name, setter, Path(tmp)) as network,
    ):
        workdir = Path(tmp)
        config = workdir / "dbm.yaml"
        config.write_text(
            f"dbm:\n  max_bandwidth_in_mbit: {BUDGET_MBIT:g}\n"
            f"  optimization_rate_in_seconds: {PERIOD_S:g}\n"
        )
        transport = network.transport
        fleet = Nodes(network.env, network.transport_args, workdir)
        view: tuple[str, ...] = ()
        viewer: Viewer | None = None
        if foxglove:
            port = free_port()
            view = ("--foxglove", f"127.0.0.1:{port}", "--record", str(workdir / "view.mcap"))
        probe: Probe | None = None
        latencies_ms: list[float] = []
        misses = unsettled = attempted = 0
        shm: list[Path] = []
        try:
            probe = Probe(transport)
            start_fleet(fleet, config, view)
            if foxglove:
                viewer = Viewer(f"ws://{view[1]}")
            if not transport.wait_for_peers(READY_S):
                raise SystemExit(f"no dbml process reached\n{fleet.logs()}")
            if network.ros2 is not None and not network.ros2.wait_for_service(SERVICE_S):
                raise SystemExit(
                    f"{R1}/dbm/set_parameters did not answer within {SERVICE_S:g} s\n{fleet.logs()}"
                )
            network.set_priority(PRIORITIES[-1])
            ready = probe.wait_until(
                lambda: probe.settled(table[PRIORITIES[-1]]) or bool(fleet.exited()), READY_S
            )
            if not ready or fleet.exited():
                seen = json.dumps(transport.params.snapshot("/r"), sort_keys=True)
                raise SystemExit(
                    f"not allocated within {READY_S:g} s (exited: {fleet.exited() or 'none'})\n"
                    f"this process's view: {seen}\n{fleet.logs()}"
                )
            if transport_name == "rclpy":
                shm = fastdds_shm_files(fleet.pids)  # removed after the run, should one be killed

            deadline = time.monotonic() + MEASURE_S
            for i in range(changes):
                if time.monotonic() >= deadline or fleet.exited():
                    break
                priority = PRIORITIES[i % len(PRIORITIES)]
                rates = table[priority]
                probe.arm(rates[R1])
                start = time.perf_counter()
                network.set_priority(priority)
                arrived = probe.arrival(TIMEOUT_S)
                attempted += 1
                if arrived is None:
                    misses += 1
                else:
                    latencies_ms.append((arrived - start) * 1e3)
                # R2's side of the flip too, so each change starts from a quiet fleet.
                if not probe.wait_until(partial(probe.settled, rates), TIMEOUT_S):
                    unsettled += 1
            exited = fleet.exited()
        finally:
            if probe is not None:
                probe.close()
            if viewer is not None:
                viewer.close()
            fleet.stop()
            if shm:
                remove_fastdds_shm(shm)
        optimizer_log = (workdir / "optimizer.log").read_text(errors="replace")

    def stat(values: list[float], q: float | None) -> float | None:
        if not values:
            return None
        value = max(values) if q is None else float(np.percentile(values, q))
        return round(value, 3)

    document: dict[str, Any] = {
        "benchmark": "reaction",
        "transport": transport_name,
        "changes": attempted,
        "p50_ms": stat(latencies_ms, 50),
        "p99_ms": stat(latencies_ms, 99),
        "max_ms": stat(latencies_ms, None),
        "misses": misses,
        "reference": REFERENCE,
        "period_s": PERIOD_S,
        "timeout_ms": round(TIMEOUT_S * 1e3),
        "unsettled": unsettled,
        "exited": exited,
        "setter": network.setter,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "foxglove": foxglove,
        **network.extra,
    }
    if viewer is not None:
        document["viewer_messages"] = viewer.counts()
        document["viewer_error"] = viewer.error
        document["view_cost_per_look"] = view_cost(optimizer_log)
    if network.ros2 is not None:
        trips = network.ros2.round_trips_ms
        document["set_parameters_round_trip_p50_ms"] = stat(trips, 50)
        document["set_parameters_round_trip_p99_ms"] = stat(trips, 99)
        document["set_parameters_refused"] = len(network.ros2.refused)
        document["set_parameters_unanswered"] = network.ros2.unanswered
        if network.ros2.refused:
            document["set_parameters_refusal"] = network.ros2.refused[0]
    return document


def _difference(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else round(a - b, 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--changes", type=int, default=200, help="priority changes (default 200)")
    parser.add_argument(
        "--transport", choices=TRANSPORTS, default="zenoh", help="zenoh (default) or rclpy"
    )
    parser.add_argument(
        "--setter",
        choices=SETTERS,
        default="ros2",
        help="rclpy: a plain node's SetParameters call (ros2, default) or params.set (dbml)",
    )
    parser.add_argument(
        "--foxglove",
        action="store_true",
        help="measure without the live view, then with the optimizer serving it to a client",
    )
    args = parser.parse_args()
    if args.changes < 1:
        parser.error("--changes must be >= 1")
    if args.foxglove:
        without = measure(args.changes, args.transport, args.setter)
        with_view = measure(args.changes, args.transport, args.setter, foxglove=True)
        compared: dict[str, Any] = {
            "benchmark": "reaction_with_foxglove",
            "reference": "the same series without the live view, in this run",
            "without_view": without,
            "with_view": with_view,
            "p50_ms_added": _difference(with_view["p50_ms"], without["p50_ms"]),
            "p99_ms_added": _difference(with_view["p99_ms"], without["p99_ms"]),
        }
        print(json.dumps(compared))
        return
    document = measure(args.changes, args.transport, args.setter)
    if args.json:
        print(json.dumps(document))
        return

    def ms(value: float | None) -> str:
        return "-" if value is None else f"{value:.2f}"

    title = "priority change -> publisher applied, across processes"
    table = Table(title=f"{title} ({document['transport']}, set by {document['setter']})")
    for name in ("changes", "misses", "p50 ms", "p99 ms", "max ms", "reference"):
        table.add_column(name, justify="right")
    table.add_row(
        str(document["changes"]),
        str(document["misses"]),
        ms(document["p50_ms"]),
        ms(document["p99_ms"]),
        ms(document["max_ms"]),
        "1000 (period 1 s)",
    )
    table.caption = f"optimizer period {PERIOD_S:g} s: only the event trigger reacts this fast"
    Console().print(table)
    print(json.dumps(document))


if __name__ == "__main__":
    main()
