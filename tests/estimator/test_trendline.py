"""The ``trendline`` design (GCC's delay gradient): what it cuts for, and to what."""

from __future__ import annotations

import math
from typing import Any

import pytest

from dbml.core.errors import SpecError
from dbml.estimator import (
    Arrival,
    BandwidthEstimator,
    Estimate,
    EstimatorSettings,
    Phase,
    TrendlineSettings,
)

GAP_S = 0.04
"""25 frames/s of 50 KB: 10 Mbit/s."""
FRAME_BYTES = 50_000
GROWTH_FROM_S = 3.0


def _run(growth_per_s: float, *, seconds: float = 6.0) -> list[Estimate]:
    """One stream; from ``GROWTH_FROM_S`` its delay grows ``growth_per_s``; updated every other."""
    estimator = BandwidthEstimator(
        max_mbit=20.0, settings=EstimatorSettings(detector=TrendlineSettings())
    )
    estimates = []
    for k in range(round(seconds / GAP_S)):
        sent = k * GAP_S
        arrival = sent + 0.01 + growth_per_s * max(0.0, sent - GROWTH_FROM_S)
        estimator.observe(Arrival("a", k, sent, arrival, FRAME_BYTES))
        if k % 2:
            estimates.append(estimator.update(arrival))
    return estimates


def test_a_steady_delay_is_never_cut() -> None:
    assert Phase.DECREASE not in {e.phase for e in _run(0.0)}


def test_a_growing_delay_is_cut_to_the_backoff_of_the_receive_rate() -> None:
    estimates = _run(0.2)
    first = next(e for e in estimates if e.phase is Phase.DECREASE)
    assert GROWTH_FROM_S < first.t_s < GROWTH_FROM_S + 0.5  # a few frames' slope, then a cut
    assert first.estimate_mbit == pytest.approx(TrendlineSettings().backoff * first.received_mbit)
    assert all(e.phase is not Phase.DECREASE for e in estimates if e.t_s <= GROWTH_FROM_S)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("frames", 2, "frames=2 must be >= 3"),
        ("frames", True, "frames=True must be a positive integer"),
        ("smoothing", 0.0, r"smoothing=0.0 must be in \(0, 1\]"),
        ("threshold", math.nan, "threshold=nan must be a positive number"),
    ],
)
def test_bad_settings_name_the_field(field: str, value: Any, match: str) -> None:
    kwargs: dict[str, Any] = {field: value}
    with pytest.raises(SpecError, match=match):
        TrendlineSettings(**kwargs)
