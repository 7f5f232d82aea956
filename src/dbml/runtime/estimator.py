"""The bandwidth estimator as a node part: reception reports in, a budget for the optimizer out.

It listens to ``/dbm/reception`` (what managed subscribers actually receive), maps each
reporter's clock onto its own (the smallest report transit seen, so reporters on other machines
work too), runs :class:`~dbml.core.estimator.BandwidthEstimator` every ``interval_s``, and
publishes the estimate in ``/dbm/estimated_bandwidth_in_mbit`` with its state in
``/dbm/estimator_state`` for ``dbml monitor``. The cap is the configured budget,
``/dbm/max_bandwidth_in_mbit`` times ``/dbm/max_bandwidth_utilization``: the estimate never
exceeds it.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

from dbml.core.errors import TransportError
from dbml.core.estimator import Arrival, BandwidthEstimator, Estimate, EstimatorSettings
from dbml.runtime import names
from dbml.runtime.params import ParamView
from dbml.runtime.reception import RECEPTION_TOPIC, REPORT_INTERVAL_S, ReceptionReport
from dbml.runtime.worker import PeriodicWorker
from dbml.transports.base import Sample, Transport

__all__ = ["ESTIMATE_INTERVAL_S", "LinkEstimator"]

log = logging.getLogger("dbml.estimator")

_PUBLISH_CHANGE = 0.01
"""Publish the estimate when it moves by this fraction (or the phase changes)."""
ESTIMATE_INTERVAL_S = 0.1
"""How often the estimator judges the link."""
REPORT_LAG_S = REPORT_INTERVAL_S * 1.5
"""Frames arrive up to one report interval late: the estimator judges the window before."""


class LinkEstimator:
    """Estimate the shared link from reception reports; ``budget_mbit`` feeds the optimizer."""

    def __init__(
        self,
        transport: Transport,
        *,
        settings: EstimatorSettings | None = None,
        interval_s: float = ESTIMATE_INTERVAL_S,
        report_lag_s: float = REPORT_LAG_S,
        on_change: Callable[[], None] | None = None,
    ) -> None:
        self._transport = transport
        self._settings = settings
        self._report_lag_s = report_lag_s
        self.on_change = on_change
        """Called when the published estimate changes (the optimizer's ``poke``)."""
        self._lock = threading.Lock()
        self._estimator: BandwidthEstimator | None = None
        self._offsets: dict[str, float] = {}
        self._published: tuple[float, str] | None = None
        self._view = ParamView.of(transport.params)
        self._worker = PeriodicWorker(
            self.tick, interval_s=interval_s, name="dbml-estimator", log=log
        )
        self._subscription = transport.subscribe(RECEPTION_TOPIC, self._on_report)

    def cap_mbit(self) -> float | None:
        """The configured budget (bandwidth times utilization): the estimate's ceiling."""
        return self._view.dbm().configured_mbit

    def budget_mbit(self) -> float | None:
        """The current estimate, or None before the budget is configured."""
        with self._lock:
            return None if self._estimator is None else self._estimator.estimate_mbit

    def _on_report(self, sample: Sample) -> None:
        try:
            report = ReceptionReport.decode(sample.payload)
        except TransportError as err:
            log.warning("%s", err)
            return
        now = self._transport.now()
        with self._lock:
            # arrival on our clock = arrival on theirs + offset; transit >= 0 bounds the offset
            offset = min(self._offsets.get(report.host, math.inf), now - report.now_s)
            self._offsets[report.host] = offset
            if self._estimator is None:
                return
            for frame in report.frames:
                self._estimator.observe(
                    Arrival(
                        stream=f"{report.host}{frame.topic}",
                        seq=frame.seq,
                        sent_s=frame.sent_ns / 1e9,
                        arrival_s=frame.arrival_s + offset,
                        size_bytes=frame.size_bytes,
                    )
                )

    def tick(self) -> Estimate | None:
        """One estimator update (the thread calls this every ``interval_s``)."""
        cap = self.cap_mbit()
        if cap is None:
            return None
        with self._lock:
            if self._estimator is None:
                self._estimator = BandwidthEstimator(max_mbit=cap, settings=self._settings)
            # frames arrive up to one report interval late: judge the window that is complete
            estimate = self._estimator.update(
                self._transport.now() - self._report_lag_s, max_mbit=cap
            )
        self._publish(estimate)
        return estimate

    def _publish(self, estimate: Estimate) -> None:
        value, phase = estimate.estimate_mbit, estimate.phase.value
        last = self._published
        if (
            last is not None
            and last[1] == phase
            and abs(value - last[0]) <= _PUBLISH_CHANGE * last[0]
        ):
            return
        self._published = (value, phase)
        params = self._transport.params
        params.set(names.ESTIMATE, round(value, 4))
        params.set(
            names.ESTIMATOR_STATE,
            f"{phase}: received {estimate.received_mbit:.2f} Mbit/s, "
            f"queueing {estimate.queue_delay_s * 1000:.0f} ms, lost {estimate.lost}",
        )
        if self.on_change is not None:
            self.on_change()

    @property
    def alive(self) -> bool:
        """False once its thread died (the command then exits non-zero)."""
        return self._worker.alive

    def start(self) -> LinkEstimator:
        """Judge the link every interval on a thread of its own."""
        self._worker.start()
        return self

    def close(self) -> None:
        """Stop and withdraw the estimate, so nobody reads a stale one."""
        self._worker.stop()
        self._subscription.close()
        if self._published is not None:
            self._transport.params.set(names.ESTIMATE, None)
            self._transport.params.set(names.ESTIMATOR_STATE, None)
